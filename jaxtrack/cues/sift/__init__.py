"""The SIFT cue (Section III-D): OpenCV keypoints and ratio matching on the host, outlier filters and
the assignment to model points in JAX, ending as padded 2D-3D correspondences (`Cue.SIFT`)."""

from ._assign import backprojection_filter as backprojection_filter
from ._assign import reprojection_errors as reprojection_errors
from ._assign import sift_correspondences as sift_correspondences
from ._detect import SiftConfig as SiftConfig
from ._detect import SiftMatches as SiftMatches
from ._detect import detect_sift as detect_sift
from ._detect import match_descriptors as match_descriptors
from ._detect import opencv_threads as opencv_threads
from ._detect import sift_matches as sift_matches
from ._filters import SiftParams as SiftParams
from ._filters import remove_gross_and_static as remove_gross_and_static
from ._filters import sift_params as sift_params

"""Image cues; each turns image(s) and tracker state into correspondences or weights.

- `flow`: dense variational optical flow in the object region (eq. 6-8) and its correspondences;
- `levelset`: the region cue, level-set segmentation with a shape prior and shape matching (eq. 11-15);
- `sift`: SIFT matches (OpenCV on the host) moved to model points (Section III-D);
- `occlusion`: the appearance model and the occlusion map r(x) that protects both motion cues (eq. 9-10).
"""

from . import flow as flow
from . import levelset as levelset
from . import occlusion as occlusion
from . import sift as sift

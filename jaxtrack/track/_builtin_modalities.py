"""Imports the built-in modalities so that they register (`jaxtrack.modality.register_modality`)."""

from ..cues.flow._modality import OpticalFlow
from ..cues.levelset._modality import LevelSetRegion
from ..cues.lines._modality import LineRegion
from ..cues.sift._modality import SiftKeypoints

BUILTIN_MODALITIES = (LevelSetRegion, LineRegion, OpticalFlow, SiftKeypoints)

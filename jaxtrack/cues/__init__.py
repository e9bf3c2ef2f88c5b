"""Image cues; each turns image(s) and tracker state into correspondences or weights."""

from . import flow as flow

"""Host-side checks of calibration and pose inputs at the API edge (numpy; never inside jit).

Each returns the value as a float64 numpy array or raises `ValueError` whose message starts with the
caller's `name` for the value (an argument, or "file: field" for data read from disk), so the user
learns which input is wrong, not just that a shape somewhere did not match.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

# |RRᵀ − I| allowed for a stored rotation: BOP files and hand-written JSON keep ~6-8 digits, and a
# matrix this close to SO(3) changes projections by < 1e-4 relative; anything further is not a rotation.
ROTATION_ATOL = 1e-4


def checked_array(value: npt.ArrayLike, name: str, size: int | None = None) -> np.ndarray:
    """`value` as a finite float64 array (flattened to `size` values when given)."""
    try:
        arr = np.asarray(value, np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} must be numeric, got {value!r}") from e
    if size is not None:
        arr = arr.reshape(-1)
        if arr.size != size:
            raise ValueError(f"{name} must hold {size} values, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr.tolist()}")
    return arr


def checked_intrinsics(K: npt.ArrayLike, name: str = "K") -> np.ndarray:
    """(3, 3) pinhole intrinsics [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0 (so K is invertible).

    A 9-value list (BOP's cam_K) is reshaped row-major.
    """
    K = checked_array(K, name)
    if K.shape == (9,):
        K = K.reshape(3, 3)
    if K.shape != (3, 3):
        raise ValueError(f"{name} must be a 3x3 matrix (or 9 values), got shape {K.shape}")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"{name} must have focal lengths fx = K[0,0] > 0 and fy = K[1,1] > 0 (a zero or singular K "
                         f"maps every point to one pixel), got fx={K[0, 0]:g}, fy={K[1, 1]:g}")
    if K[1, 0] != 0 or not np.allclose(K[2], [0, 0, 1]):
        raise ValueError(f"{name} must be upper triangular with last row (0, 0, 1), got {K.tolist()}")
    return K


def checked_rotation(R: npt.ArrayLike, name: str = "R") -> np.ndarray:
    """(3, 3) rotation matrix: 9 finite values with RRᵀ = I (to `ROTATION_ATOL`) and det R = +1."""
    R = checked_array(R, name, size=9).reshape(3, 3)
    defect = np.abs(R @ R.T - np.eye(3)).max()
    if defect > ROTATION_ATOL or np.linalg.det(R) < 0:
        raise ValueError(f"{name} is not a rotation matrix (max |RRᵀ − I| = {defect:.3g}, det R = "
                         f"{np.linalg.det(R):.3g}; need RRᵀ = I within {ROTATION_ATOL:g} and det R = +1)")
    return R


def checked_image_size(width: float, height: float, name: str = "image size") -> tuple[int, int]:
    """(width, height) as positive Python ints; floats must be whole numbers, bools are refused."""
    out = []
    for label, v in (("width", width), ("height", height)):
        numeric = isinstance(v, int | np.integer | float | np.floating) and not isinstance(v, bool | np.bool_)
        if not numeric or not np.isfinite(v) or v != int(v):
            raise ValueError(f"{name}: {label} must be a whole number of pixels, got {v!r}")
        if int(v) <= 0:
            raise ValueError(f"{name}: {label} must be positive, got {v!r}")
        out.append(int(v))
    return out[0], out[1]

"""One status type for the whole library, in the manner of optimistix's `RESULTS`.

Every jitted computation that can fail (the pose solver, the renderer, the flow solver, the cues, the
tracker) returns an int32 `Status` array next to its result instead of raising: inside `jit`, `vmap`
and `lax.scan` a failure is a value. Statuses are combined with `first_failure` (the first non-OK
code, in the order given), and turned into an exception only at an API edge, by `check_status` with
`throw=True`.

Codes are plain ints so that they vmap, scan, serialise (JSON lines) and compare cheaply; each has a
message and a flag saying whether the accompanying result may still be used (`usable`).
"""

from __future__ import annotations

import enum

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


class Status(enum.IntEnum):
    """Outcome codes shared by every jaxtrack computation (an int32 array inside jit).

    OK, MAX_STEPS, RENDER_OVERFLOW, UNCERTAIN and RECOVERED are usable (a warning at most); the others mean the
    accompanying result is a safe fallback (for a pose: the initial pose), not an answer.
    """

    OK = 0
    MAX_STEPS = 1
    SOLVER_FAILED = 2
    NONFINITE = 3
    TOO_FEW = 4
    INVALID_INPUT = 5
    DEGENERATE = 6
    RENDER_OVERFLOW = 7
    OUT_OF_VIEW = 8
    UNCERTAIN = 9
    LOST = 10
    RECOVERED = 11

    @property
    def message(self) -> str:
        return _MESSAGES[self]

    @property
    def usable(self) -> bool:
        return bool(_USABLE[self])


_MESSAGES = {
    Status.OK: "success",
    Status.MAX_STEPS: "the iteration budget ran out; the result is the last (finite) iterate",
    Status.SOLVER_FAILED: "the solver reported a singular system or divergence; the initial value is returned",
    Status.NONFINITE: "a NaN or inf appeared in the iterate or the input data; the initial value is returned",
    Status.TOO_FEW: "fewer effective constraints than degrees of freedom",
    Status.INVALID_INPUT: "invalid input: a NaN/inf value, a negative weight, an out-of-range index, "
    "a parameter outside its domain, or an initial pose that is not a rigid transform in front of the camera",
    Status.DEGENERATE: "the problem is rank-deficient (e.g. coincident or collinear points): "
    "the pose is not determined by the data",
    Status.RENDER_OVERFLOW: "a rasteriser patch class exceeded its capacity; some triangles were not drawn",
    Status.OUT_OF_VIEW: "the object is not visible in the image(s)",
    Status.UNCERTAIN: "tracked, but the evidence for the pose is weak",
    Status.LOST: "the evidence says the object was lost",
    Status.RECOVERED: "the object was lost and found again (keyframes or pose hypotheses; a new start from its pose)",
}
_USABLE = np.array([s in (Status.OK, Status.MAX_STEPS, Status.RENDER_OVERFLOW, Status.UNCERTAIN, Status.RECOVERED)
                    for s in Status])


class StatusError(RuntimeError):
    """Raised at an API edge (`throw=True`) for a status that is not usable."""

    def __init__(self, status: Status, context: str = ""):
        self.status = Status(status)
        where = f"{context}: " if context else ""
        super().__init__(f"{where}{self.status.name} ({self.status.message})")


def is_usable(status) -> jax.Array:
    """True where the accompanying result may be used (OK or a warning), elementwise, jittable."""
    return jnp.asarray(_USABLE)[jnp.clip(jnp.asarray(status, jnp.int32), 0, len(Status) - 1)]


def status_where(pred, status, otherwise) -> jax.Array:
    """`status` where `pred` holds, else `otherwise` (int32, broadcast)."""
    return jnp.where(pred, jnp.asarray(status, jnp.int32), jnp.asarray(otherwise, jnp.int32)).astype(jnp.int32)


def first_failure(*statuses) -> jax.Array:
    """The first non-OK status of the arguments, in order (OK if all are OK); elementwise, jittable.

    The order is the priority: list the cause before its consequences, e.g.
    `first_failure(input_status, solver_status)`.
    """
    if not statuses:
        raise ValueError("first_failure needs at least one status")
    out = jnp.asarray(statuses[-1], jnp.int32)
    for s in reversed(statuses[:-1]):
        s = jnp.asarray(s, jnp.int32)
        out = jnp.where(s != Status.OK, s, out)
    return out


def check_status(status, throw: bool = True, context: str = ""):
    """The API edge: raise `StatusError` for an unusable status when `throw` (else return it).

    Works on concrete arrays (raises on the first unusable element) and inside `jit` (through
    `eqx.error_if`, a runtime error of the compiled program).
    """
    if not throw:
        return status
    status = jnp.asarray(status, jnp.int32)
    if isinstance(status, jax.core.Tracer):
        bad = ~is_usable(status)
        return eqx.error_if(status, bad, f"{context}: unusable status (see jaxtrack.Status)")
    flat = np.asarray(status).reshape(-1)
    for code in flat:
        if not _USABLE[int(code)]:
            raise StatusError(Status(int(code)), context)
    return status

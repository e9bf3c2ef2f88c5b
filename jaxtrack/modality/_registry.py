"""The registry of modalities: names → classes, row tags → names.

Everything that iterates over cues asks here: the tracker's configuration (`TrackerConfig.cues`), the
fusion, the per-cue counts of `FrameResult` and `frames.jsonl`, the CLI's `--cues` choices and the
benchmarks. A new modality is one module that defines a `Modality` subclass and registers it:

    @register_modality
    class MyPoints(Modality):
        name = "points"
        ...
        @classmethod
        def from_config(cls, config): return cls()

Built-in modalities keep the tags of `jaxtrack.solve.Cue` (REGION, FLOW, SIFT); a class registered
without a tag (`cue = 0`) gets the next free one from 16 up.
"""

from __future__ import annotations

from ._protocol import Modality

_MODALITIES: dict[str, type] = {}
_FIRST_FREE_TAG = 16


def register_modality(cls: type) -> type:
    """Register a `Modality` subclass under `cls.name` (usable as a class decorator).

    Raises:
        TypeError: not a Modality subclass; ValueError: no name, or a name or tag taken by another class.
    """
    if not (isinstance(cls, type) and issubclass(cls, Modality)):
        raise TypeError(f"register_modality expects a Modality subclass, got {cls!r}")
    name = getattr(cls, "name", "")
    if not name or not isinstance(name, str):
        raise ValueError(f"{cls.__name__}.name must be a non-empty string")
    old = _MODALITIES.get(name)
    if old is not None and old.__qualname__ != cls.__qualname__:
        raise ValueError(f"a modality named {name!r} is already registered ({old.__module__}.{old.__qualname__})")
    if not cls.cue:
        taken = {c.cue for c in _MODALITIES.values()}
        cls.cue = max([_FIRST_FREE_TAG - 1, *taken]) + 1
    elif any(c.cue == cls.cue and c.name != name for c in _MODALITIES.values()):
        raise ValueError(f"modality {name!r}: row tag {cls.cue} is taken")
    _MODALITIES[name] = cls
    return cls


def modality_class(name: str) -> type:
    """The registered class of `name` (ValueError naming the choices when unknown)."""
    try:
        return _MODALITIES[name]
    except KeyError:
        raise ValueError(f"unknown modality {name!r}; registered: {', '.join(modality_names())}") from None


def modality_names() -> tuple[str, ...]:
    """Registered modality names, in registration order (built-ins first)."""
    return tuple(_MODALITIES)


def cue_names() -> dict[int, str]:
    """Row tag → modality name, for every registered modality."""
    return {cls.cue: name for name, cls in _MODALITIES.items()}

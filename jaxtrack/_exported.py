"""Traced programs kept on disk between processes (`jax.export`), so that a warm process skips the Python trace and
the lowering of the tracker's large programs, not only XLA's compile.

The on-disk XLA compilation cache (`enable_compilation_cache`) keeps compiled executables, but every new process
still traces the step in Python and lowers it to StableHLO before it can look the executable up: 4.1 of the 6.1 s
that a warm process spent on its first all-cues step (640x480, this 2-core CPU). `persistent_jit(fn)` is
`eqx.filter_jit(fn)` that also keeps, per call signature, the exported (traced and lowered) program in
`<cache folder>/exported/`; a process that finds it deserialises it (milliseconds) and calls it, and the compile
cache gives the executable.

A signature is what decides the program: the function, the arguments' tree structure with its static leaves
(everything that is not an array: configs, raster plans, crop shapes), the arrays' shapes and dtypes, the source of
the `jaxtrack` package as imported (hashed at import), the versions of jax, jaxlib, equinox, optimistix, lineax,
numpy and ml_dtypes, the backend, the registered modalities, the jax settings that change a trace (x64, matmul
precision, dtype and rank promotion, NaN/inf checks, PRNG) and $JAXTRACK_VIEW_SUBDIVISIONS. It is pickled and
hashed. A signature that cannot be pickled (a lambda in a static field) or that refers to a class or function
outside those packages (its code could change under the same name: a user's modality, also one registered by
name) runs `eqx.filter_jit` as before. So do calls under a transformation (vmap, grad: tracers among the
arguments), calls with weakly typed arrays (an exported program's inputs and outputs are strongly typed), and an
entry whose program fails to run (then for good, in this process). A pickle that differs between processes only
misses: the program is exported again under another name.

Every program here, kept or plain, compiles with `compiler_options()` (XLA's defaults; $JAXTRACK_FUSION_EMITTERS=0
trades run time for a shorter compile, below), except, in the default "tiered" mode, a `tiered` kept program (the
tracker's step: with an empty cache it compiles quickly first and a background process makes its optimised build,
`jaxtrack._tiered`) and a `quick` kept program (run once per start: the quick build only). Without a folder both take
the plain path with `compiler_options()`.

Off unless a folder is set: `enable_compilation_cache` sets it (`jaxtrack track`, `bench`, the experiments);
`JAXTRACK_EXPORT_CACHE=0` turns it off. Serialisation needs the `flatbuffers` package (a dependency).
"""

from __future__ import annotations

import functools
import hashlib
import io
import os
import pathlib
import pickle
import tempfile
import threading
import time
import types
import warnings
import weakref

import equinox as eqx
import jax
import numpy as np

_FOLDER: list[pathlib.Path | None] = [None]

# XLA:CPU's older elemental emitters instead of its MLIR fusion emitters: XLA compiles the tracker's two large programs in
# about two thirds of the time (26.9 → 17.3 s, probe), but the programs run slower (ms per frame 28-29 → 33-34 on 1 camera,
# 114-118 → 148-150 on 4). $JAXTRACK_FUSION_EMITTERS: "0", every program with these options (the test suite, whose
# trackers run a few frames each: tests/conftest.py); "1", XLA's defaults everywhere (one compile, the faster programs);
# "auto" (the default), XLA's defaults except for the tiered programs (`persistent_jit(..., tiered=True)`: the tracker's
# step), which compile with these options first and are replaced by XLA's default build from a background process
# (`jaxtrack._tiered`). README "Fast compile, slower frames". Should XLA drop the option, every compile with it fails with
# "No such compile option" (the suite would say so first).
CPU_COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False}
FUSION_EMITTERS_VALUES = ("0", "1", "auto")


def compile_mode(platform: str | None = None) -> str:
    """How `persistent_jit` compiles on `platform` (default: jax's default backend), from $JAXTRACK_FUSION_EMITTERS:
    "quick" (`CPU_COMPILER_OPTIONS` everywhere), "default" (XLA's defaults everywhere; any backend but the CPU), or
    "tiered" (XLA's defaults, tiered programs in two tiers)."""
    value = os.environ.get("JAXTRACK_FUSION_EMITTERS", "auto")
    if value not in FUSION_EMITTERS_VALUES:
        raise ValueError(f"$JAXTRACK_FUSION_EMITTERS must be 0, 1 or auto, got {value!r}")
    if (platform or jax.default_backend()) != "cpu":
        return "default"
    return {"0": "quick", "1": "default", "auto": "tiered"}[value]


def compiler_options(platform: str | None = None) -> dict | None:
    """XLA compile options of the programs `persistent_jit` makes on `platform` (default: jax's default backend):
    `CPU_COMPILER_OPTIONS` in the "quick" `compile_mode` (the faster compile, the slower program), else none (XLA's
    defaults; a tiered program's first tier is chosen in `persistent_jit`)."""
    return dict(CPU_COMPILER_OPTIONS) if compile_mode(platform) == "quick" else None


def _options_key(options: dict | None) -> tuple:
    """`options` as a hashable key (XLA's defaults: the empty tuple)."""
    return tuple(sorted((options or {}).items()))


def _jit_options(options: dict | None) -> dict:
    """jit's keyword for `options` (none for XLA's defaults: a jax without `compiler_options` still runs those)."""
    return {} if options is None else {"compiler_options": options}


def _nested_options_error(error: Exception) -> bool:
    """Whether `error` is jax refusing compile options on a jit nested in a caller's trace (whose arguments were all
    concrete, so no tracer told us): the call then runs inside the caller's program, with its options."""
    return isinstance(error, ValueError) and "can only be passed to top-level" in str(error)


_PLAIN = object()  # an entry meaning "this signature runs eqx.filter_jit"
_MISSING_TIER = object()  # `persistent_jit._tier`: not asked yet


def enable_exported_cache(folder: str | os.PathLike | None) -> pathlib.Path | None:
    """Keep exported programs in `folder` (made if missing); None turns the cache off. $JAXTRACK_EXPORT_CACHE=0 keeps it
    off whatever the folder. Returns the folder in use."""
    if folder is None or os.environ.get("JAXTRACK_EXPORT_CACHE", "1") == "0":
        _FOLDER[0] = None
        return None
    path = pathlib.Path(folder)
    path.mkdir(parents=True, exist_ok=True)
    _FOLDER[0] = path
    return path


# --- pickling eqx treedefs: equinox marks a module's array fields with a sentinel in the tree's aux data ---------
class _Probe(eqx.Module):
    a: object


_MISSING = jax.tree_util.tree_structure(_Probe(0.0)).node_data()[1][0]


# Code that the source hash covers, or whose version is in the signature. A class or function from anywhere else
# (a user's modality in a notebook) can change without changing its pickled name: such a signature is not kept.
_KNOWN_CODE = ("jaxtrack", "jax", "jaxlib", "equinox", "optimistix", "lineax", "numpy", "ml_dtypes", "builtins",
               "collections", "copyreg", "dataclasses", "enum", "functools", "operator", "types", "typing")


class _UnknownCode(Exception):
    """The signature refers to code whose changes it cannot see."""


def _is_known(obj) -> bool:
    return (getattr(obj, "__module__", None) or "").split(".")[0] in _KNOWN_CODE


class _Pickler(pickle.Pickler):
    def persistent_id(self, obj):
        return "eqx-missing" if obj is _MISSING else None

    def reducer_override(self, obj):
        # Pickled by reference, its code is not in the bytes: only code the signature otherwise covers.
        if isinstance(obj, type | types.FunctionType | types.BuiltinFunctionType | types.MethodType) and not _is_known(obj):
            raise _UnknownCode(f"{obj.__module__}.{getattr(obj, '__qualname__', obj)}")
        return NotImplemented


class _Unpickler(pickle.Unpickler):
    def persistent_load(self, pid):
        if pid != "eqx-missing":
            raise pickle.UnpicklingError(f"unknown persistent id {pid!r}")
        return _MISSING


def _dumps(obj, fast: bool = False) -> bytes:
    """Pickled `obj`; `fast`: without pickle's memo, so the bytes depend on values alone, not on which equal objects
    are one object (a signature: an interned "sift" in one configuration's cues and a split string in another's named
    different files). A self-referencing object then fails to pickle (no disk cache for that signature)."""
    buffer = io.BytesIO()
    pickler = _Pickler(buffer, protocol=4)
    pickler.fast = fast
    pickler.dump(obj)
    return buffer.getvalue()


def _loads(data: bytes):
    return _Unpickler(io.BytesIO(data)).load()


@functools.cache
def _canonical(dtype, x64: bool | None = None) -> str:
    """The dtype name an array of `dtype` has inside jax (float64 → float32 without x64; `x64` keys the cache)."""
    return str(jax.dtypes.canonicalize_dtype(dtype))


def _source_environment() -> tuple:
    """jaxtrack's source (every .py file under the package, as on disk now) and the versions of the libraries that
    trace it."""
    import importlib.metadata

    digest = hashlib.sha256()
    root = pathlib.Path(__file__).resolve().parent
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    versions = []
    for name in ("jax", "jaxlib", "equinox", "optimistix", "lineax", "numpy", "ml_dtypes"):
        try:
            versions.append((name, importlib.metadata.version(name)))
        except importlib.metadata.PackageNotFoundError:
            versions.append((name, None))
    return digest.hexdigest(), tuple(versions)


# Hashed once, at import: the code this process runs. (Hashed lazily, a file edited between the import and the
# first call would name the old program with the new source's hash.) `_export` hashes again before it writes.
_ENVIRONMENT = _source_environment()


# The jax settings that change what a trace produces (jax's own jit cache keys on them too).
_TRACE_SETTINGS = ("jax_enable_x64", "jax_default_matmul_precision", "jax_numpy_dtype_promotion", "jax_numpy_rank_promotion",
                   "jax_debug_nans", "jax_debug_infs", "jax_default_prng_impl", "jax_threefry_partitionable")


def _settings() -> tuple:
    """The trace settings now (thread-local overrides such as `jax.default_matmul_precision` included), the backend and
    $JAXTRACK_VIEW_SUBDIVISIONS (read by the line modality when a configuration builds it)."""
    return (tuple(str(getattr(jax.config, name, None)) for name in _TRACE_SETTINGS), jax.default_backend(),
            os.environ.get("JAXTRACK_VIEW_SUBDIVISIONS"))


@functools.cache
def _environment_tag() -> str:
    """8 hex digits of `_ENVIRONMENT`: the second part of a program file's name."""
    return hashlib.sha256(repr(_ENVIRONMENT).encode()).hexdigest()[:8]


# Files of the same function written by another jaxtrack source or library version are removed once they are this
# old (they can never be loaded by this version; a day's grace keeps two checkouts used in turn from evicting each
# other's programs, and bounds what a day of edits leaves behind).
STALE_AFTER_S = 86400.0


def _remove_stale(written: pathlib.Path) -> None:
    name, tag, _ = written.name.rsplit("-", 2)
    for path in written.parent.glob(f"{name}-*-*.jaxexport"):
        try:
            other_name, other_tag, _ = path.name.rsplit("-", 2)
            if other_name == name and other_tag != tag and time.time() - path.stat().st_mtime > STALE_AFTER_S:
                path.unlink()
                from ._tiered import lock_path, mark_path

                mark_path(path).unlink(missing_ok=True)  # its `jaxtrack._tiered` mark
                if time.time() - _mtime_or_now(lock_path(path)) > STALE_AFTER_S:
                    lock_path(path).unlink(missing_ok=True)  # a lock no child released
        except (OSError, ValueError):  # removed by another process meanwhile, or a name of another form
            continue
    for path in written.parent.glob(".*.jaxexport.*"):  # temporary files of writers that died
        try:
            if time.time() - path.stat().st_mtime > STALE_AFTER_S:
                path.unlink()
        except OSError:
            continue


def _mtime_or_now(path: pathlib.Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return time.time()


def _call_device(dynamic):
    """The device a call runs on: that of its first committed array (as jit places it), else the default device."""
    for x in dynamic:
        if getattr(x, "committed", False):
            return next(iter(x.devices()))
    return jax.config.jax_default_device or jax.devices()[0]


def _split(args, kwargs):
    """(treedef, is_dynamic, dynamic, static, avals) of a call's arguments: arrays traced, every other leaf static (as
    `eqx.filter_jit`); avals = (shape, canonical dtype) of the arrays."""
    leaves, treedef = jax.tree_util.tree_flatten((args, kwargs))
    is_dynamic = tuple(eqx.is_array(x) for x in leaves)
    dynamic = [x for x, d in zip(leaves, is_dynamic) if d]
    static = tuple(x for x, d in zip(leaves, is_dynamic) if not d)
    x64 = jax.config.jax_enable_x64
    return treedef, is_dynamic, dynamic, static, tuple((x.shape, _canonical(x.dtype, x64)) for x in dynamic)


# The entries whose programs have run in this process (`optimised_hlo_texts`); weak: a dropped entry leaves the set.
# Calls add from several threads (the step's programs compile and run beside each other): under a lock.
_RAN: weakref.WeakSet = weakref.WeakSet()
_RAN_LOCK = threading.Lock()


def optimised_hlo_texts() -> list[str]:
    """The optimised HLO text (XLA's `as_text()`, with its table of source lines) of every kept program that has run
    in this process. For profiling: the JAX profiler names the kernels of a program (its fusions), this text says
    which lines of Python made each (`jaxtrack.bench.profile_kernels`). Each program is lowered again for its
    abstract arguments: in a process that has just run it, jit's cache (or the on-disk compile cache) holds the
    executable; otherwise this compiles it again (minutes for the tracker's step). A program that cannot be lowered
    so is left out."""
    with _RAN_LOCK:
        entries = list(_RAN)
    texts = []
    for entry in entries:
        structs = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in entry.exported.in_avals]
        try:
            texts.append(entry.call.lower(*structs).compile().as_text())
        except Exception as error:  # noqa: BLE001  (profiling only: its kernels stay unattributed)
            warnings.warn(f"jaxtrack: no optimised text of a kept program ({type(error).__name__}: {error})",
                          RuntimeWarning, stacklevel=2)
    return texts


class _Entry:
    """One signature's program: the jitted call of the exported module and how to rebuild the output tree."""

    def __init__(self, exported, out_treedef, out_is_dynamic, out_static, device, options=None):
        # One placement for every argument (the call's device): jit would otherwise lower (and compile) the call again
        # when some inputs are committed to the device (outputs of the previous call) and others not.
        placement = jax.sharding.SingleDeviceSharding(device)
        self.exported = exported
        self.call = jax.jit(exported.call, in_shardings=placement, out_shardings=placement, **_jit_options(options))
        self.out_treedef, self.out_is_dynamic, self.out_static = out_treedef, out_is_dynamic, out_static
        self.compiled = False
        self.ran = False  # in `_RAN` (its program has run: `optimised_hlo_texts`)
        self.optimise = None  # a first tier's `jaxtrack._tiered.Request`, until its first call

    def compile(self, dynamic) -> None:
        """XLA's compile of the program for these arguments (or its load from the on-disk cache), without running it;
        the next call finds it in jit's cache. Releases the GIL while XLA works (two programs can load at once)."""
        self.call.lower(*dynamic).compile()
        self.compiled = True

    def outputs_like(self):
        """The call's output tree with numpy zeros in place of its arrays (for compiling a program that takes them)."""
        zeros = iter([np.zeros(a.shape, a.dtype) for a in self.exported.out_avals])
        static = iter(self.out_static)
        return jax.tree_util.tree_unflatten(self.out_treedef, [next(zeros) if d else next(static) for d in self.out_is_dynamic])

    def __call__(self, dynamic):
        out = iter(self.call(*dynamic))
        self.compiled = True
        if not self.ran:  # once per entry, not at every call
            with _RAN_LOCK:
                _RAN.add(self)
            self.ran = True
        static = iter(self.out_static)
        return jax.tree_util.tree_unflatten(self.out_treedef, [next(out) if d else next(static) for d in self.out_is_dynamic])


class persistent_jit:  # lower case: used like a decorator, as eqx.filter_jit
    """`eqx.filter_jit(fn)` whose traced programs are also kept on disk (see the module's docstring).

    Args:
        fn: a function of pytrees; arrays are traced, every other leaf is static (as `eqx.filter_jit`).
        tiered: in the "tiered" `compile_mode`, with the on-disk caches on, a kept program compiles quickly first
            (`CPU_COMPILER_OPTIONS`) and its build with XLA's defaults replaces it once a background process has made
            it (`jaxtrack._tiered`); a process that finds that build marked done loads it at once.
        quick: in the "tiered" `compile_mode`, a kept program's quick build only (`CPU_COMPILER_OPTIONS`): for a
            program that runs once per start, whose compile the first frame waits for and whose run time does not matter.
            (Without the on-disk folder `tiered` and `quick` programs take the plain path, `compiler_options()`.)

    Attributes:
        loaded: signatures this process found on disk; exported: signatures it traced and wrote.
    """

    def __init__(self, fn, tiered: bool = False, quick: bool = False):
        functools.update_wrapper(self, fn)  # first: it copies fn.__dict__ onto this object
        self.fn = fn
        self.name = getattr(fn, "__name__", "fn").strip("_") or "fn"
        self.qualname = f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', self.name)}"
        self._plain: dict = {}  # compile options (as a tuple) -> eqx.filter_jit(fn) compiled with them
        self.memory: dict = {}
        self.loaded = 0
        self.exported = 0
        self._lock = threading.Lock()
        self.tiered, self.quick = tiered, quick
        # (signature key without options, export folder, compile cache, cache on) -> (program path, optimised in use) or
        # None (not tiered): `_tier`
        self._tiers: dict = {}

    def plain(self, *args, **kwargs):
        """`eqx.filter_jit(fn)(*args, **kwargs)`, compiled with `compiler_options()` of jax's default backend (read at
        the call: the backend and $JAXTRACK_FUSION_EMITTERS may be set after the import). Under a transformation or
        inside a caller's jit (tracers among the arguments) with none: XLA takes options only for a top-level program
        (the caller's)."""
        options = compiler_options()
        if options is not None and any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves((args, kwargs))):
            options = None  # (XLA's defaults, the usual case, skip this walk over the arguments at every call)
        try:
            return self._plain_jit(options)(*args, **kwargs)
        except ValueError as error:  # a caller's trace whose arguments are all concrete: a nested jit after all
            if options is None or not _nested_options_error(error):
                raise
            return self._plain_jit(None)(*args, **kwargs)

    def _plain_jit(self, options):
        key = _options_key(options)
        with self._lock:  # the recovery's warm-up thread and the main thread may both ask
            jitted = self._plain.get(key)
            if jitted is None:
                jitted = self._plain[key] = eqx.filter_jit(self.fn, **_jit_options(options))
        return jitted

    def _resolve(self, args, kwargs):
        """(entry, dynamic leaves, key) of a call: entry an `_Entry` (made or loaded on first use), or `_PLAIN` when
        the call runs `eqx.filter_jit` (no folder, tracers, weak types, unhashable or unkept signatures)."""
        folder = _FOLDER[0]
        if folder is None:
            return _PLAIN, None, None
        treedef, is_dynamic, dynamic, static, avals = _split(args, kwargs)
        # Under vmap / grad / an outer jit (tracers), or with weakly typed arrays (an exported program takes and gives
        # strongly typed ones, which would promote differently than eqx.filter_jit): the plain path.
        if any(isinstance(x, jax.core.Tracer) or getattr(x, "weak_type", False) for x in dynamic):
            return _PLAIN, None, None
        device = _call_device(dynamic)
        options = compiler_options(device.platform)  # read at each call, as the plain path does: part of the key
        try:
            base = (treedef, is_dynamic, static, avals, _settings(), device)
            tiered_mode = (self.tiered or self.quick) and compile_mode(device.platform) == "tiered"
            tier = self._tier(folder, base) if tiered_mode and self.tiered else None
            if (tier is not None and not tier[1]) or (tiered_mode and self.quick):
                options = dict(CPU_COMPILER_OPTIONS)  # the first tier, or a program that runs once per start
            key = (*base, _options_key(options))
            entry = self.memory.get(key)
        except TypeError:  # an unhashable static leaf: eqx.filter_jit says what it needs
            return _PLAIN, None, None
        if entry is None:
            with self._lock:
                entry = self.memory.get(key)
                if entry is None:
                    entry = self.memory[key] = self._entry(folder, treedef, is_dynamic, static, avals, device, options)
                    # (A program not written to disk, the source changed since the import, keeps its quick build.)
                    if tier is not None and not tier[1] and entry is not _PLAIN and tier[0].exists():
                        entry.optimise = self._optimise_request(base, tier[0], entry, device)
        return entry, dynamic, key

    def _tier(self, folder: pathlib.Path, base: tuple):
        """(program path, whether its optimised build is in use) of a signature in the tiered mode, or None where it
        compiles once with XLA's defaults (no compile cache for a child to fill, no signature kept on disk). Asked once
        per signature, export folder and compile cache (`jaxtrack._tiered.mark_content`)."""
        from . import _tiered

        key = (base, folder, _tiered.mark_content(), _tiered.available())
        tier = self._tiers.get(key, _MISSING_TIER)
        if tier is _MISSING_TIER:
            treedef, is_dynamic, static, avals = base[:4]
            signature = self._signature(treedef, is_dynamic, static, avals) if key[-1] else None
            path = None if signature is None else self._path(folder, signature)
            tier = self._tiers[key] = None if path is None else (path, _tiered.is_marked(path))
        return tier

    def _optimise_request(self, base: tuple, path: pathlib.Path, quick: _Entry, device):
        """The `jaxtrack._tiered.Request` that replaces the first tier's `quick` entry by XLA's default build."""
        from . import _tiered

        def make_entry():
            return _Entry(quick.exported, quick.out_treedef, quick.out_is_dynamic, quick.out_static, device, None)

        key = (base, path.parent, _tiered.mark_content(), True)  # as `_tier` keys it

        def swap(entry):
            with self._lock:
                self.memory[(*base, _options_key(None))] = entry
                self._tiers[key] = (path, True)

        structs = tuple(jax.ShapeDtypeStruct(shape, dtype) for shape, dtype in base[3])
        return _tiered.Request(program=path, avals=base[3], make_entry=make_entry, swap=swap, structs=structs)

    def __call__(self, *args, **kwargs):
        entry, dynamic, key = self._resolve(args, kwargs)
        if entry is _PLAIN:
            return self.plain(*args, **kwargs)
        return self._run(entry, dynamic, key, args, kwargs)

    def _run(self, entry, dynamic, key, args, kwargs):
        if entry.optimise is not None:  # a first tier's first call: its optimised build starts in the background
            from . import _tiered

            request, entry.optimise = entry.optimise, None
            _tiered.request(request)
        try:
            return entry(dynamic)
        except Exception as error:  # noqa: BLE001  (e.g. a program of another platform: the plain path, for good)
            if _nested_options_error(error):  # this call only (inside a caller's jit): the entry stays for the others
                return self.plain(*args, **kwargs)
            self.memory[key] = _PLAIN
            warnings.warn(f"jaxtrack: the kept program of {self.qualname} failed ({type(error).__name__}: {error}); "
                          "traced instead", RuntimeWarning, stacklevel=3)
            return self.plain(*args, **kwargs)

    def outputs_like(self, *args, **kwargs):
        """Zeros (numpy) shaped as the call's outputs, from its entry (made now: its program traced and exported, or
        loaded), for compiling a program that takes them before this one has run; None where the call runs
        `eqx.filter_jit`."""
        entry = self._resolve(args, kwargs)[0]
        return None if entry is _PLAIN else entry.outputs_like()

    def compile(self, *args, **kwargs) -> bool:
        """Compile the call's program without running it (or load the executable from the on-disk cache), making its
        entry first if needed. Returns False, and does nothing, where the call runs `eqx.filter_jit`; also False where
        the compile fails, which is left to the call (it reports the error or falls back, as `__call__` does). XLA
        releases the GIL: `Tracker.step` compiles its two programs at once on the first frame."""
        entry, dynamic, _ = self._resolve(args, kwargs)
        if entry is _PLAIN:
            return False
        if not entry.compiled:
            try:
                entry.compile(dynamic)
            except Exception:  # noqa: BLE001  (the call compiles again and reports it, or falls back)
                return False
        return True

    def dispatches_async(self, *args, **kwargs) -> bool:
        """Whether a call with these arguments returns before its program has run (jax's asynchronous dispatch): a
        kept program does; `eqx.filter_jit` waits for the result (to report runtime errors). Makes the call's entry
        (traces or loads its program) when it has none yet, as the call would."""
        return self._resolve(args, kwargs)[0] is not _PLAIN

    def call_async(self, *args, **kwargs):
        """The call where it dispatches asynchronously (`dispatches_async`: its result comes back at once and is
        computed meanwhile), else None and nothing runs. One resolution of the arguments for both."""
        entry, dynamic, key = self._resolve(args, kwargs)
        return None if entry is _PLAIN else self._run(entry, dynamic, key, args, kwargs)

    def _signature(self, treedef, is_dynamic, static, avals) -> bytes | None:
        from .modality._registry import _MODALITIES

        # A configuration names its modalities and the traced code looks the classes up: the registry's entries of
        # known code are part of the signature; a signature that names a modality registered from other code (its
        # name among the pickled strings; a false match only costs the disk cache) is not kept.
        known = tuple(sorted((name, cls.__module__, cls.__qualname__) for name, cls in _MODALITIES.items() if _is_known(cls)))
        unknown = [name for name, cls in _MODALITIES.items() if not _is_known(cls)]
        # The shapes as one string: pickled as tuples they would share memo entries where the caller's arrays share
        # shape objects (a device array's outputs do, numpy zeros of the same shapes do not), and equal arguments
        # would name different files (`Tracker.start` compiles the first step on zeros shaped as its state).
        shapes = ";".join(f"{'x'.join(str(int(d)) for d in shape)}:{dtype}" for shape, dtype in avals)
        try:
            signature = _dumps((self.qualname, _ENVIRONMENT, _settings(), known, treedef, is_dynamic, static, shapes), fast=True)
        except Exception:  # noqa: BLE001  (not picklable, or code the signature cannot see: no disk cache for it)
            return None
        if any(name.encode() in signature for name in unknown):
            return None
        return signature

    def is_kept(self, *args, **kwargs) -> bool:
        """Whether these arguments' program is on disk (exported by this or an earlier process), without loading it;
        False where the call would run `eqx.filter_jit` (no folder, tracers, weak types, a signature not kept)."""
        folder = _FOLDER[0]
        if folder is None:
            return False
        treedef, is_dynamic, dynamic, static, avals = _split(args, kwargs)
        if any(isinstance(x, jax.core.Tracer) or getattr(x, "weak_type", False) for x in dynamic):
            return False
        signature = self._signature(treedef, is_dynamic, static, avals)
        return signature is not None and self._path(folder, signature).exists()

    def digest(self, *args, **kwargs) -> str | None:
        """The hex digest that names these arguments' program on disk (the file `<name>-<environment>-<digest>.jaxexport`),
        or None when it has no signature kept on disk (such calls run `eqx.filter_jit`)."""
        treedef, is_dynamic, _, static, avals = _split(args, kwargs)
        signature = self._signature(treedef, is_dynamic, static, avals)
        return None if signature is None else hashlib.sha256(signature).hexdigest()[:40]

    def _entry(self, folder: pathlib.Path, treedef, is_dynamic, static, avals, device, options=None):
        signature = self._signature(treedef, is_dynamic, static, avals)
        if signature is None:
            return _PLAIN
        path = self._path(folder, signature)
        entry = self._load(path, signature, device, options)
        if entry is not None:
            self.loaded += 1
            return entry
        return self._export(path, signature, treedef, is_dynamic, static, avals, device, options)

    def _path(self, folder: pathlib.Path, signature: bytes) -> pathlib.Path:
        return folder / f"{self.name}-{_environment_tag()}-{hashlib.sha256(signature).hexdigest()[:40]}.jaxexport"

    @staticmethod
    def _load(path: pathlib.Path, signature: bytes, device, options=None) -> _Entry | None:
        """The program in `path`, or None when there is none, or the file is damaged or holds another signature (it is
        exported again and replaced). A file loaded is touched: `STALE_AFTER_S` counts from its last use."""
        try:
            stored = _loads(path.read_bytes())
            if stored["signature"] != signature:
                return None
            entry = _Entry(jax.export.deserialize(stored["exported"]), *stored["out"], device, options)
        except Exception:  # noqa: BLE001  (missing, truncated, foreign, or written by another jax)
            return None
        try:
            os.utime(path)
        except OSError:
            pass
        return entry

    def _export(self, path: pathlib.Path, signature: bytes, treedef, is_dynamic, static, avals, device, options=None):
        out_structure = []

        def flat(*dynamic_leaves):
            it_dynamic, it_static = iter(dynamic_leaves), iter(static)
            args, kwargs = jax.tree_util.tree_unflatten(treedef, [next(it_dynamic) if d else next(it_static) for d in is_dynamic])
            out_leaves, out_treedef = jax.tree_util.tree_flatten(self.fn(*args, **kwargs))
            out_is_dynamic = tuple(eqx.is_array(x) for x in out_leaves)
            out_structure.append((out_treedef, out_is_dynamic, tuple(x for x, d in zip(out_leaves, out_is_dynamic) if not d)))
            return [x for x, d in zip(out_leaves, out_is_dynamic) if d]

        try:
            exported = jax.export.export(jax.jit(flat))(*[jax.ShapeDtypeStruct(shape, dtype) for shape, dtype in avals])
        except Exception as error:  # noqa: BLE001  (a program export cannot hold, e.g. a host callback)
            warnings.warn(f"jaxtrack: {self.qualname} cannot be exported ({type(error).__name__}: {error}); "
                          "it is traced in every process", RuntimeWarning, stacklevel=3)
            return _PLAIN
        entry = _Entry(exported, *out_structure[-1], device, options)
        self.exported += 1
        if _source_environment() != _ENVIRONMENT:  # the source changed on disk since the import: this is not its program
            return entry
        try:
            data = _dumps({"signature": signature, "exported": exported.serialize(), "out": out_structure[-1]})
            handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
            with os.fdopen(handle, "wb") as file:
                file.write(data)
            os.replace(temporary, path)
            _remove_stale(path)
        except Exception as error:  # noqa: BLE001  (no flatbuffers, a read-only folder: run from memory)
            warnings.warn(f"jaxtrack: the traced {self.name} could not be kept in {path.parent} ({type(error).__name__}: "
                          f"{error}); a new process traces it again", RuntimeWarning, stacklevel=3)
        return entry

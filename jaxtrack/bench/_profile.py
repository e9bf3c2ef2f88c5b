"""Where a compiled program spends its time, by line of Python: the JAX profiler's kernel times mapped to source.

Jitting the stages of a step one by one (`experiments/bench_track.py::stage_breakdown`) times code that XLA compiles
otherwise inside the whole step (fused with its neighbours, scheduled beside them on the two cores). This module
times the kernels of the program itself: `profile_kernels` runs a callable under `jax.profiler.trace`, reads each
kernel's duration from the trace (`jax.profiler.ProfileData`: one event per kernel, named by its HLO instruction and
tagged with its program's id) and attributes it, through the optimised HLO's table of stack frames (`as_text()` of a
compiled program: every instruction carries a `stack_frame_id`), to the Python lines that made it.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import pathlib
import re
import tempfile

_SECTIONS = ("FileNames", "FunctionNames", "FileLocations", "StackFrames")
# The jaxtrack package folder: its files are "jaxtrack's lines".
PACKAGE = pathlib.Path(__file__).resolve().parents[1]


@dataclasses.dataclass(frozen=True)
class SourceFrame:
    """One frame of Python: file, function and line."""

    file: str
    function: str
    line: int

    def short(self, line: bool = True) -> str:
        """`path/inside/jaxtrack.py:function:line` for the package's files (the file's name for others); without
        `:line` where `line` is False."""
        path = pathlib.Path(self.file)
        try:
            name = path.resolve().relative_to(PACKAGE).as_posix()
        except (ValueError, OSError):
            name = path.name
        return f"{name}:{self.function}:{self.line}" if line else f"{name}:{self.function}"


def _section(text: str, name: str) -> str:
    start = text.find(f"\n{name}\n")
    if start < 0:
        return ""
    start += len(name) + 2
    ends = [text.find(f"\n{other}\n", start) for other in _SECTIONS if other != name]
    ends = [e for e in ends if e >= 0]
    return text[start:min(ends)] if ends else text[start:]


# Instructions whose trace events span the kernels of the computations they run (a loop, a branch, a call): counting
# them as well would count their bodies' time twice.
CONTROL_FLOW = ("while", "conditional", "call", "async-start", "async-done", "async-update")


def instruction_frames(hlo_text: str) -> dict[str, tuple[SourceFrame, ...]]:
    """HLO instruction name → its Python stack, innermost frame first, from an optimised program's `as_text()`.

    The text ends with four tables (file names, function names, file locations, stack frames: each frame names its
    location and its caller's frame, printed as the caller's id + 1, so 1 means none) and each instruction's metadata
    names its innermost frame (`stack_frame_id`). Instructions without one are left out."""
    ids = lambda body: dict(re.findall(r'^(\d+) "(.*)"$', body, re.MULTILINE))
    files, functions = ids(_section(hlo_text, "FileNames")), ids(_section(hlo_text, "FunctionNames"))
    locations = {k: (f, g, int(line)) for k, f, g, line in re.findall(
        r"^(\d+) \{file_name_id=(\d+) function_name_id=(\d+) line=(\d+)", _section(hlo_text, "FileLocations"), re.MULTILINE)}
    frames = {k: (loc, str(int(parent) - 1)) for k, loc, parent in re.findall(
        r"^(\d+) \{file_location_id=(\d+) parent_frame_id=(\d+)", _section(hlo_text, "StackFrames"), re.MULTILINE)}

    @functools.cache
    def stack(frame_id: str) -> tuple[SourceFrame, ...]:
        out, seen = [], set()
        while frame_id in frames and frame_id not in seen:
            seen.add(frame_id)
            location, frame_id = frames[frame_id]
            if location not in locations:
                break
            f, g, line = locations[location]
            out.append(SourceFrame(files.get(f, "?"), functions.get(g, "?"), line))
        return tuple(out)

    pairs = re.findall(r"^\s*(?:ROOT )?%?([\w.\-]+) = [^\n]*?stack_frame_id=(\d+)", hlo_text, re.MULTILINE)
    return {name: stack(frame_id) for name, frame_id in pairs}


def control_flow_instructions(hlo_text: str) -> set[str]:
    """Names of the instructions in `hlo_text` whose opcode is in `CONTROL_FLOW` (the opcode follows the shape:
    `%name = SHAPE while(...)`; operands are written `%x`, so a space before the opcode tells them apart)."""
    opcodes = "|".join(re.escape(op) for op in CONTROL_FLOW)
    return set(re.findall(r"^\s*(?:ROOT )?%?([\w.\-]+) = [^\n]*? (?:" + opcodes + r")\(", hlo_text, re.MULTILINE))


@dataclasses.dataclass
class KernelProfile:
    """Kernel time of the profiled calls, by program and instruction. The events of loops, branches and calls
    themselves (`CONTROL_FLOW`) are left out: their bodies' kernels count.

    Attributes:
        ns: {(program id, HLO instruction): total nanoseconds over the profiled calls}.
        count: {(program id, HLO instruction): kernel launches}.
        frames: {(program id, HLO instruction): Python stack, innermost first} where a program's text was given.
    """

    ns: collections.Counter
    count: collections.Counter
    frames: dict

    def programs(self) -> collections.Counter:
        """Program id → its total kernel nanoseconds."""
        out = collections.Counter()
        for (program, _), ns in self.ns.items():
            out[program] += ns
        return out

    def by_line(self, choose, program=None, line: bool = True) -> collections.Counter:
        """Nanoseconds by the frame `choose(stack)` picks (a `SourceFrame` or None: "unattributed"), over every
        program or one; by its function only where `line` is False."""
        out = collections.Counter()
        for key, ns in self.ns.items():
            if program is not None and key[0] != program:
                continue
            frame = choose(self.frames.get(key, ()))
            out[frame.short(line=line) if frame is not None else "unattributed"] += ns
        return out


def innermost_in(where: str | tuple[str, ...] | None = None, exclude: tuple[str, ...] = ("_exported.py",)):
    """A `KernelProfile.by_line` chooser: the innermost frame in the jaxtrack package (`where` None) or whose file
    path contains `where` (or one of them: e.g. ("track/_step.py", "modality/_loop.py") for the step's own lines,
    which stage called the kernel), skipping files whose path contains one of `exclude` (the kept programs'
    wrapper)."""

    def inside(file: str) -> bool:
        if where is not None:
            return any(w in file for w in ((where,) if isinstance(where, str) else where))
        try:
            pathlib.Path(file).resolve().relative_to(PACKAGE)
            return True
        except (ValueError, OSError):
            return False

    def choose(stack):
        for frame in stack:
            if inside(frame.file) and not any(x in frame.file for x in exclude):
                return frame
        return None

    return choose


def read_trace(trace_dir: pathlib.Path) -> tuple[collections.Counter, collections.Counter]:
    """{(program id, instruction): ns} and launch counts of every kernel in the newest trace under `trace_dir`."""
    import jax

    files = sorted(pathlib.Path(trace_dir).rglob("*.xplane.pb"), key=lambda p: p.stat().st_mtime)
    if not files:
        raise FileNotFoundError(f"no *.xplane.pb trace under {trace_dir}")
    data = jax.profiler.ProfileData.from_file(str(files[-1]))
    ns, count = collections.Counter(), collections.Counter()
    for plane in data.planes:
        for line in plane.lines:
            for event in line.events:
                stats = {k: v for k, v in event.stats if k in ("hlo_op", "program_id")}
                if "hlo_op" in stats:
                    key = (stats.get("program_id"), stats["hlo_op"])
                    ns[key] += event.duration_ns
                    count[key] += 1
    return ns, count


def _match_programs(ns: collections.Counter, texts: list[str], share: float = 0.9) -> dict:
    """Program id → (instruction frames, control-flow instructions) of the text that holds the most of its
    instructions, where that text holds at least `share` of them (the trace names programs by id, the texts do not;
    instruction names such as `copy.6` repeat between programs, so the whole set decides). Programs without such a
    text are left out (their kernels stay unattributed)."""
    defined = [set(re.findall(r"^\s*(?:ROOT )?%?([\w.\-]+) = ", t, re.MULTILINE)) for t in texts]
    ops = collections.defaultdict(set)
    for program, op in ns:
        ops[program].add(op)
    parsed = {}  # text index → its frames and control-flow instructions, parsed once whatever matches it
    out = {}
    for program, names in ops.items():
        scores = [len(names & d) for d in defined]
        if scores and max(scores) >= share * len(names):
            best = scores.index(max(scores))
            if best not in parsed:
                parsed[best] = (instruction_frames(texts[best]), control_flow_instructions(texts[best]))
            out[program] = parsed[best]
    return out


def profile_kernels(run, texts=None, trace_dir: pathlib.Path | None = None) -> KernelProfile:
    """Run `run()` under the JAX profiler and return its kernels' times, attributed to source lines.

    Args:
        run: a callable that runs the programs to profile and waits for their results.
        texts: the optimised HLO texts of the programs (default: `jaxtrack._exported.optimised_hlo_texts()` after the
            run, every kept program that has run; pass `[jax.jit(f).lower(...).compile().as_text()]` for others).
            Kernels of a program without its text count, unattributed.
        trace_dir: where the trace goes (default: a temporary folder, removed after).
    """
    import jax

    def traced(folder):
        with jax.profiler.trace(str(folder)):
            run()
        return read_trace(folder)

    if trace_dir is None:
        with tempfile.TemporaryDirectory(prefix="jaxtrack-profile-") as folder:
            ns, count = traced(folder)
    else:
        ns, count = traced(trace_dir)
    if texts is None:
        from .._exported import optimised_hlo_texts

        texts = optimised_hlo_texts()
    programs = _match_programs(ns, list(texts))
    # A loop's, branch's or call's own event spans its body's kernels, which have events of their own: left out.
    loops = lambda key: (key[1] in programs[key[0]][1] if key[0] in programs
                         else key[1].split(".")[0] in CONTROL_FLOW)
    ns = collections.Counter({k: v for k, v in ns.items() if not loops(k)})
    count = collections.Counter({k: v for k, v in count.items() if k in ns})
    frames = {key: programs[key[0]][0].get(key[1], ()) if key[0] in programs else () for key in ns}
    return KernelProfile(ns, count, frames)

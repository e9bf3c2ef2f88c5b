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


@dataclasses.dataclass(frozen=True)
class SourceFrame:
    """One frame of Python: file, function and line."""

    file: str
    function: str
    line: int

    def short(self, package: str = "jaxtrack", line: bool = True) -> str:
        """`path/inside/package.py:function:line` (without `:line` where `line` is False)."""
        marker = f"/{package}/"
        path = self.file.split(marker, 1)[-1] if marker in self.file else pathlib.Path(self.file).name
        return f"{path}:{self.function}:{self.line}" if line else f"{path}:{self.function}"


def _section(text: str, name: str) -> str:
    start = text.find(f"\n{name}\n")
    if start < 0:
        return ""
    start += len(name) + 2
    ends = [text.find(f"\n{other}\n", start) for other in _SECTIONS if other != name]
    ends = [e for e in ends if e >= 0]
    return text[start:min(ends)] if ends else text[start:]


def instruction_frames(hlo_text: str) -> dict[str, tuple[SourceFrame, ...]]:
    """HLO instruction name → its Python stack, innermost frame first, from an optimised program's `as_text()`.

    The text ends with four tables (file names, function names, file locations, stack frames: each frame names its
    location and its caller's frame) and each instruction's metadata names its innermost frame (`stack_frame_id`).
    Instructions without one are left out."""
    ids = lambda body: dict(re.findall(r'^(\d+) "([^"]*)"', body, re.MULTILINE))
    files, functions = ids(_section(hlo_text, "FileNames")), ids(_section(hlo_text, "FunctionNames"))
    locations = {k: (f, g, int(line)) for k, f, g, line in re.findall(
        r"^(\d+) \{file_name_id=(\d+) function_name_id=(\d+) line=(\d+)", _section(hlo_text, "FileLocations"), re.MULTILINE)}
    frames = {k: (loc, parent) for k, loc, parent in re.findall(
        r"^(\d+) \{file_location_id=(\d+) parent_frame_id=(\d+)", _section(hlo_text, "StackFrames"), re.MULTILINE)}

    @functools.cache
    def stack(frame_id: str) -> tuple[SourceFrame, ...]:
        out, seen = [], set()
        while frame_id in frames and frame_id not in seen:
            seen.add(frame_id)
            location, frame_id = frames[frame_id]
            f, g, line = locations[location]
            out.append(SourceFrame(files.get(f, "?"), functions.get(g, "?"), line))
        return tuple(out)

    pairs = re.findall(r"^\s*(?:ROOT )?%?([\w.\-]+) = [^\n]*?stack_frame_id=(\d+)", hlo_text, re.MULTILINE)
    return {name: stack(frame_id) for name, frame_id in pairs}


@dataclasses.dataclass
class KernelProfile:
    """Kernel time of the profiled calls, by program and instruction.

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


def innermost_in(package_part: str, exclude: tuple[str, ...] = ("/_exported.py",)):
    """A `KernelProfile.by_line` chooser: the innermost frame whose file path contains `package_part` (for example
    "/jaxtrack/" for the package's own line, "/jaxtrack/track/_step.py" for the step's stage), skipping `exclude`."""

    def choose(stack):
        for frame in stack:
            if package_part in frame.file and not any(x in frame.file for x in exclude):
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


def _match_programs(ns: collections.Counter, texts: list[str]) -> dict:
    """Program id → the instruction frames of the text that holds the most of its instructions (the trace names
    programs by id, the texts do not; instruction names repeat between programs, so the whole set decides)."""
    parsed = [instruction_frames(t) for t in texts]
    ops = collections.defaultdict(set)
    for program, op in ns:
        ops[program].add(op)
    out = {}
    for program, names in ops.items():
        scores = [len(names & p.keys()) for p in parsed]
        if scores and max(scores) > 0:
            out[program] = parsed[scores.index(max(scores))]
    return out


def profile_kernels(run, texts=None, trace_dir: pathlib.Path | None = None) -> KernelProfile:
    """Run `run()` under the JAX profiler and return its kernels' times, attributed to source lines.

    Args:
        run: a callable that runs the programs to profile and waits for their results.
        texts: the optimised HLO texts of the programs (default: `jaxtrack._exported.optimised_hlo_texts()` after the
            run, every kept program that has run; pass `[jax.jit(f).lower(...).compile().as_text()]` for others).
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
    frames = {key: programs.get(key[0], {}).get(key[1], ()) for key in ns}
    return KernelProfile(ns, count, frames)

"""What the benchmarks share: where the TUM data is, one ``memgs`` command run and read back,
and one way to write a result.

- :func:`tum_path`: ``--tum`` when given, else ``$MEMGS_TUM``, else the fr1/rpy head in
  ``shared/data/tum/`` beside the checkout (found from this file, never a machine's own path).
- :func:`run_memgs`: ``memgs ARGS`` of this checkout in a child process (the nodes in their own
  processes, as a user runs them), its wall and CPU time, and the run summary it wrote, read by
  the orchestration's own reader.
- :func:`write_results`: a result JSON written atomically (the project's ``atomic_write``).
  Evaluation records (``eval.json`` and what wraps it) go through ``evaluation.write_json``.

Benchmarks are scripts, not a package: those in ``benchmarks/`` import this module directly, the
harnesses in ``benchmarks/harness/`` put ``benchmarks/`` on ``sys.path`` first.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from memgs_ros.orchestration.run_files import RunSummary

ROOT = Path(__file__).resolve().parents[1]  # the checkout
TUM_ENV = "MEMGS_TUM"
TUM_HEAD = "rgbd_dataset_freiburg1_rpy_head"  # the sequence the documented figures use
SHARED_TUM = ROOT.parent / "shared" / "data" / "tum" / TUM_HEAD
TUM_HELP = f"TUM folder (default: ${TUM_ENV}, else ../shared/data/tum/{TUM_HEAD} beside the checkout)"
TIMED_OUT = 124  # MemgsRun.returncode of a command killed at its timeout (as timeout(1) says it)


class TumNotFound(FileNotFoundError):
    """The TUM folder a benchmark needs is not there; the message says how to name one."""

    def __init__(self, path: Path, flag: str = "--tum DIR") -> None:
        super().__init__(f"no TUM folder at {path} (no rgb.txt): pass {flag} or set {TUM_ENV}=DIR")
        self.path = path


def tum_path(arg: str | os.PathLike[str] | None = None, *, check: bool = True, flag: str = "--tum DIR") -> Path:
    """The TUM folder to use: ``arg`` (a ``--tum`` value) when given, else ``$MEMGS_TUM``, else the
    shared fr1/rpy head beside the checkout. ``check``: raise :class:`TumNotFound` (naming ``flag``,
    the script's way to pass one) unless it holds an ``rgb.txt``; without it, a caller that skips
    or falls back on a missing folder decides."""
    env = os.environ.get(TUM_ENV, "")
    path = Path(arg) if arg else Path(env) if env else SHARED_TUM
    if check and not (path / "rgb.txt").is_file():
        raise TumNotFound(path, flag)
    return path


def tum_path_or_exit(parser: argparse.ArgumentParser, arg: str | os.PathLike[str] | None = None,
                     flag: str = "--tum DIR") -> Path:
    """:func:`tum_path`, or the parser's usage error naming both ways to set it (exit status 2)."""
    try:
        return tum_path(arg, flag=flag)
    except TumNotFound as err:
        parser.error(str(err))


def uptime() -> str:
    """``uptime``'s line (the load averages a result records beside its figures)."""
    return subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout.strip()


def write_results(path: str | os.PathLike[str], result: Any) -> Path:
    """Write ``result`` as indented JSON to ``path`` atomically (folders made as needed): a reader,
    or a run stopped part-way, sees the previous file or the whole new one. Non-finite floats stay
    NaN/Infinity, as the scripts' ``--table`` readers expect."""
    from memgs_ros.core.runtime.atomic import atomic_write

    p = Path(path)
    text = json.dumps(result, indent=2, default=str) + "\n"
    atomic_write(p, lambda f: f.write(text.encode("utf-8")))
    return p


@dataclass(frozen=True)
class MemgsRun:
    """One ``memgs`` command a benchmark ran, and what it left."""

    command: tuple[str, ...]
    returncode: int  # TIMED_OUT when it ran past its timeout and was killed
    wall_s: float  # the command's wall time, start-up included
    cpu_s: float  # user + system CPU of the command and of every process it waited for (its nodes)
    output: str  # its stdout and stderr, when captured (neither ``log`` nor ``echo``)
    summary: RunSummary | None  # OUT/summary.json of a run that ended with exit 0, else None

    @property
    def ok(self) -> bool:
        return self.returncode == 0


def run_memgs(args: Sequence[str | os.PathLike[str]], out: Path | None = None, *, log: Path | None = None,
              echo: bool = False, timeout_s: float | None = None, env: Mapping[str, str] | None = None,
              prefix: Sequence[str] = (), checkout: Path = ROOT) -> MemgsRun:
    """Run ``memgs ARGS [--out OUT]`` (``python -m memgs_ros`` of this checkout, whatever is
    installed) and read back the summary a finished run left in ``OUT``.

    log: stdout and stderr go to this file; echo: they go to the terminal, after a ``$ memgs ...``
    line; neither: captured into ``MemgsRun.output``. timeout_s: kill it then (its nodes end with it)
    and report TIMED_OUT. env: added to this process's environment. prefix: a command to run it
    under (``taskset -c 0-5``). checkout: the tree whose ``memgs_ros`` runs (another commit's
    worktree, for an A/B in one session; it runs in that folder, so give absolute paths)."""
    from memgs_ros.orchestration.run_files import SUMMARY_FILE, read_summary

    words = [str(a) for a in args] + (["--out", str(out)] if out is not None else [])
    cmd = [*prefix, sys.executable, "-m", "memgs_ros", *words]
    child_env = {**os.environ, **(env or {})}
    child_env["PYTHONPATH"] = os.pathsep.join([str(checkout), *filter(None, [child_env.get("PYTHONPATH")])])
    if echo:
        print("$ memgs " + " ".join(words), flush=True)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    with open(log, "w") if log is not None else contextlib.nullcontext() as sink:
        where: dict[str, Any] = {}  # echo: the terminal's
        if sink is not None and not echo:
            where = {"stdout": sink, "stderr": subprocess.STDOUT}
        elif not echo:
            where = {"capture_output": True}
        try:
            # ``python -m`` puts the working directory first on sys.path: run another checkout from its own.
            cwd = None if Path(checkout).resolve() == ROOT else str(checkout)
            proc = subprocess.run(cmd, env=child_env, text=True, timeout=timeout_s, check=False, cwd=cwd, **where)
            code, output = proc.returncode, (proc.stdout or "") + (proc.stderr or "")
        except subprocess.TimeoutExpired as err:
            code, output = TIMED_OUT, _text(err.stdout) + _text(err.stderr)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    done = code == 0 and out is not None and (out / SUMMARY_FILE).is_file()
    return MemgsRun(tuple(cmd), code, wall, cpu, output, read_summary(out) if done else None)


def _text(data: str | bytes | None) -> str:
    return data.decode(errors="replace") if isinstance(data, bytes) else (data or "")

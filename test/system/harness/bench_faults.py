"""Benchmark: the fault matrix. ``memgs run`` on a small synthetic room, and one fault per case.

Faults (46 cases):

- SIGKILL, SIGTERM and SIGINT to each of tracker, keyframe_sampler, mapper, merger, bag_player
  and the runner (``memgs run`` itself), at an early point (the 3rd frame acknowledged by the
  mapper) and a late one (80 % of the frames acknowledged): 36 cases. Sent from outside, as an
  operator, a supervisor or the OOM killer would.
- SIGKILL and restart by the runner's own fault injection (``--kill NODE@S``) of the mapper (it
  resumes from its checkpoint) and of the merger (it resyncs from a snapshot).
- Disk full while the merger saves: the output folder is a small tmpfs filled to the last byte
  early (stays full), when the player is done (the final save), or early and freed again late;
  or filled late up to 256 kB (room for the ids sidecar, not for the PLY: full half-way through
  a save).
  Where no tmpfs can be mounted (not root) every write of the run's files raises ENOSPC instead
  (an injected ``os.fsync`` failure, switched on and off by a flag file).
- The output folder made read-only early and late (a tmpfs remounted ``ro``; root ignores
  chmod; without root: chmod 0555). The nodes' logs live on a second mount under ``logs/``: a
  file open for writing would refuse the remount, and an error must stay readable.
- 20 % message loss on ``memgs/map/delta`` (a relay beside the graph,
  ``memgs_ros.testing.delta_relay``, drops every 5th), and a baseline without a fault.

Each case checks, after the runner ended:

- processes: every process of the run (command line naming the output folder, or
  ``MEMGS_PARENT_PID`` naming the runner) is gone within ``GONE_LIMIT_S``; any left is reported
  and then SIGKILLed;
- the map: a ``map.ply`` that exists parses with the project's reader and its ids sidecar fits;
  one that existed at the fault still exists; a merger that held Gaussians and was not
  SIGKILLed left one (unless the disk refused every save); the mapper's checkpoint loads; no
  temporary file is left behind;
- the outcome: recovered (exit 0 and a summary written by this run), ended clearly (exactly one
  ``memgs run: error:`` / ``interrupted`` line on stderr and no traceback; a SIGKILLed runner
  cannot print one, its nodes end by PR_SET_PDEATHSIG), or unclear;
- the summary (``summary.json``): written by this run and saying what happened (restarts,
  resyncs, a source played in part), or ``none`` where the run wrote none.

Prints a progress line per case, the matrix and the totals; ``--json PATH`` writes them. Exit
status 1 when a process was left behind or a map was corrupt or lost. ``test/system/test_faults.py``
runs five of the cases through this module.

    python test/system/harness/bench_faults.py                      # the whole matrix (~21 min on 2 cores)
    python test/system/harness/bench_faults.py --cases mapper,disk  # cases whose name holds a substring
"""
from __future__ import annotations

import argparse
import contextlib
import errno
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "benchmarks"))  # benchmarks/ (not a package): _common
from _common import ROOT, write_results  # noqa: E402

from memgs_ros.testing.delta_relay import LOSSY_MERGER, lossy_deltas  # noqa: E402

SPEC = "synthetic:w=128,h=96,n=40,seed=3"
# Short training, and saves and checkpoints every second, so a late fault finds both on disk.
SETTINGS = {"mapper.iterations_per_frame": 3, "mapper.final_iterations": 30, "mapper.checkpoint_period_s": 1.0,
            "merger.save_period_s": 1.0}
TARGETS = ("tracker", "keyframe_sampler", "mapper", "merger", "bag_player", "runner")
SIGNALS = (signal.SIGKILL, signal.SIGTERM, signal.SIGINT)
EARLY_FRAMES = 3  # the early point: this many frames acknowledged
LATE_FRACTION = 0.8  # the late point: this share of the frames acknowledged
GONE_LIMIT_S = 10.0  # every process of the run must be gone this long after the runner ended
RUN_TIMEOUT_S = 240.0  # the runner's own --timeout
POINT_TIMEOUT_S = 150.0  # how long to wait for a fault point
SAVE_FAIL_WAIT_S = 10.0  # after a disk fault, how long to wait for the merger's first failed save
TMPFS_MB = 32
TEMP_GLOB = ".*.tmp"  # atomic_write's temporary files
ENOSPC_ENV, FAULT_DIR_ENV = "MEMGS_FAULT_ENOSPC_FLAG", "MEMGS_FAULT_DIR"


@dataclass(frozen=True)
class Fault:
    """One case of the matrix."""

    name: str
    kind: str  # "signal", "kill_restart", "disk_full", "read_only", "delta_loss", "none"
    target: str = ""  # a node, "bag_player" or "runner"
    sig: int = 0
    at: str = "early"  # "early", "late", "done" (the mapper acknowledged every frame)
    until: str = ""  # disk_full: free the disk again at this point ("" = stays full)
    free_kb: int = 0  # disk_full: leave this much free (room for the ids sidecar, not for the PLY)


@dataclass(frozen=True)
class MapCheck:
    exists: bool
    gaussians: int = 0
    problem: str = ""  # why the file does not parse or its ids do not fit; "" when fine
    digest: str = ""  # of the PLY
    ids_digest: str = ""  # of its ids sidecar


@dataclass(frozen=True)
class CaseResult:
    case: str
    outcome: str  # "recovered", "ended clearly", "unclear", "not reached"
    exit_code: int | None
    line: str  # the runner's error / interrupted line, or what made the outcome unclear
    left_behind: tuple[str, ...]  # "pid command" of processes still there after GONE_LIMIT_S
    gone_s: float  # how long after the runner ended its last process was gone
    map: str  # "ok N", "none", or the problem
    map_ok: bool
    summary: str  # "ok: ...", "none", "n/a: ...", "wrong: ..."
    summary_ok: bool
    stray_tmp: int  # temporary files atomic_write left in the output folder
    fault_at_s: float  # seconds from the runner's start to the fault
    wall_s: float
    out_dir: str

    @property
    def clean(self) -> bool:
        return (not self.left_behind and self.map_ok and self.outcome in ("recovered", "ended clearly")
                and not self.summary.startswith("wrong"))


def all_faults() -> list[Fault]:
    cases = [Fault(f"{t}-{s.name}-{at}", "signal", t, int(s), at)
             for t in TARGETS for s in SIGNALS for at in ("early", "late")]
    cases += [
        Fault("mapper-kill_restart", "kill_restart", "mapper"),
        Fault("merger-kill_restart", "kill_restart", "merger"),
        Fault("disk_full-early", "disk_full", at="early"),
        Fault("disk_full-final_save", "disk_full", at="done"),
        Fault("disk_full-mid_save", "disk_full", at="late", free_kb=256),
        Fault("disk_full-early-freed_late", "disk_full", at="early", until="late"),
        Fault("read_only-early", "read_only", at="early"),
        Fault("read_only-late", "read_only", at="late"),
        Fault("delta_loss-20pct", "delta_loss"),
        Fault("baseline", "none"),
    ]
    return cases


# ---------------------------------------------------------------------------------- processes
def _read(path: str) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read()
    except OSError:
        return b""


def run_pids(out: Path, runner_pid: int) -> dict[int, str]:
    """{pid: command} of every live process of the run: its command line names the output folder
    (the runner's ``--out``, the nodes' ``--params-file``) or its environment names the runner as
    MEMGS_PARENT_PID (what every node the runner started carries). Zombies are left out."""
    marker = str(out.resolve()).encode()
    parent = f"MEMGS_PARENT_PID={runner_pid}".encode()
    found: dict[int, str] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == os.getpid():
            continue
        stat = _read(f"/proc/{entry}/stat")
        if not stat or stat[stat.rfind(b")") + 2:][:1] == b"Z":
            continue
        args = _read(f"/proc/{entry}/cmdline").split(b"\0")
        if any(marker in a for a in args) or parent in _read(f"/proc/{entry}/environ").split(b"\0"):
            found[int(entry)] = b" ".join(a for a in args if a).decode(errors="replace")[:160]
    return found


def node_pid(out: Path, runner_pid: int, node: str) -> int | None:
    """The pid of ``node`` (tracker, ..., bag_player) of this run, or of the runner itself."""
    if node == "runner":
        return runner_pid
    module = f"memgs_ros.nodes.{node}.node "
    return next((pid for pid, cmd in run_pids(out, runner_pid).items() if module in cmd + " "), None)


def wait_until_gone(out: Path, runner_pid: int, limit_s: float) -> tuple[float, dict[int, str]]:
    """(seconds until no process of the run was left, those still there after ``limit_s``)."""
    t0 = time.monotonic()
    while (left := run_pids(out, runner_pid)) and time.monotonic() - t0 < limit_s:
        time.sleep(0.1)
    return time.monotonic() - t0, left


# ---------------------------------------------------------------------------------- disks
def can_mount() -> bool:
    """True when this process may mount a tmpfs (root, and the kernel lets it)."""
    if os.geteuid() != 0:
        return False
    with tempfile.TemporaryDirectory() as d:
        if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", d], capture_output=True).returncode:
            return False
        subprocess.run(["umount", d], check=False)
    return True


def _mount_tmpfs(path: Path, size_mb: int) -> None:
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mb}m", "tmpfs", str(path)], check=True,
                   capture_output=True)


def _unmount(path: Path) -> None:
    if subprocess.run(["umount", str(path)], capture_output=True).returncode:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)  # busy: detach it anyway


def fill_disk(path: Path, free_kb: int = 0) -> None:
    """Write a filler file into ``path`` until the file system has no byte left, then give
    ``free_kb`` back."""
    filler = path / ".filler"
    with open(filler, "wb", buffering=0) as f:
        for chunk in (1 << 20, 1 << 12, 1):
            try:
                while True:
                    f.write(b"\0" * chunk)
            except OSError as err:
                if err.errno != errno.ENOSPC:
                    raise
    if free_kb:
        os.truncate(filler, max(0, filler.stat().st_size - free_kb * 1024))


def remount_read_only(path: Path, limit_s: float = 10.0) -> None:
    """``mount -o remount,ro``; a write in progress (a save, a checkpoint) makes it busy: retry."""
    end = time.monotonic() + limit_s
    while True:
        res = subprocess.run(["mount", "-o", "remount,ro", str(path)], capture_output=True, text=True)
        if res.returncode == 0:
            return
        if time.monotonic() > end:
            raise RuntimeError(f"could not remount {path} read-only: {res.stderr.strip()}")
        time.sleep(0.05)


_INJECT = '''"""Fault injection for bench_faults.py (no tmpfs possible): while the flag file exists, fsync of
a file in the run's output folder larger than the bytes the flag file names fails with ENOSPC, as
a full disk makes a write fail."""
import errno
import os

_flag, _dir, _fsync = os.environ.get("{flag}", ""), os.environ.get("{dir}", ""), os.fsync


def _fsync_or_full(fd):
    try:
        free = int(open(_flag).read() or 0) if _flag else None
    except (OSError, ValueError):
        free = None
    if free is not None:
        try:
            target, size = os.readlink(f"/proc/self/fd/{{int(fd)}}"), os.fstat(fd).st_size
        except (OSError, TypeError):
            target, size = "", 0
        if _dir and target.startswith(_dir) and size > free:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    return _fsync(fd)


os.fsync = _fsync_or_full
'''


class OutputFolder:
    """A case's output folder: plain, or (disk and read-only cases) a tmpfs with ``logs/`` on a
    mount of its own; without root the same faults by injection (ENOSPC) and chmod."""

    def __init__(self, path: Path, fault: Fault, mount: bool) -> None:
        self.path, self.fault = path, fault
        self.mounted: list[Path] = []
        self.env: dict[str, str] = {}
        self.path.mkdir(parents=True)
        special = fault.kind in ("disk_full", "read_only")
        if special and mount:
            _mount_tmpfs(self.path, TMPFS_MB)
            self.mounted.append(self.path)
            (self.path / "logs").mkdir()
            _mount_tmpfs(self.path / "logs", 64)
            self.mounted.append(self.path / "logs")
        elif fault.kind == "disk_full":
            inject = self.path.parent / f"{self.path.name}.inject"
            inject.mkdir()
            (inject / "sitecustomize.py").write_text(_INJECT.format(flag=ENOSPC_ENV, dir=FAULT_DIR_ENV))
            self.env = {"PYTHONPATH": os.pathsep.join(filter(None, (str(inject), os.environ.get("PYTHONPATH")))),
                        ENOSPC_ENV: str(inject / "full"), FAULT_DIR_ENV: str(self.path.resolve())}

    def break_it(self) -> None:
        if self.fault.kind == "disk_full":
            if self.mounted:
                fill_disk(self.path, self.fault.free_kb)
            else:
                Path(self.env[ENOSPC_ENV]).write_text(str(self.fault.free_kb * 1024))
        elif self.fault.kind == "read_only":
            if self.mounted:
                remount_read_only(self.path)
            else:
                self.path.chmod(0o555)

    def repair(self) -> None:
        if self.fault.kind == "disk_full":
            if self.mounted:
                (self.path / ".filler").unlink()
            else:
                Path(self.env[ENOSPC_ENV]).unlink()

    def close(self, keep: Path | None) -> None:
        """Copy what the run left into ``keep`` (the tmpfs goes), then unmount."""
        if not self.mounted:
            self.path.chmod(0o755)
            return
        if keep is not None:
            shutil.copytree(self.path, keep, ignore=shutil.ignore_patterns(".filler"), dirs_exist_ok=True)
        for m in reversed(self.mounted):
            _unmount(m)


# ---------------------------------------------------------------------------------- maps
def check_map(out: Path) -> MapCheck:
    """The map in ``out`` as the project reads it: parses, and its ids sidecar fits its rows."""
    from memgs_ros.core.map_io.ply import ids_sidecar_path, load_ply
    from memgs_ros.errors import DataError

    path = out / "map.ply"
    if not path.exists():
        return MapCheck(False)
    try:
        n = len(load_ply(path).ids)
        sidecar = ids_sidecar_path(path)
        ids = np.load(sidecar, allow_pickle=False) if sidecar.exists() else None
    except (DataError, OSError, ValueError) as err:
        return MapCheck(True, problem=f"corrupt: {str(err)[:80]}")
    if ids is None or ids.shape != (n,):
        shape = "missing" if ids is None else f"{ids.shape}"
        return MapCheck(True, n, f"ids sidecar {shape} does not fit {n} rows")
    import hashlib

    return MapCheck(True, n, digest=hashlib.sha1(path.read_bytes()).hexdigest(),
                    ids_digest=hashlib.sha1(sidecar.read_bytes()).hexdigest())


def check_checkpoint(out: Path) -> str:
    """'' when the mapper's checkpoint is absent or loads, else the problem."""
    from memgs_ros.core.mapping import checkpoint
    from memgs_ros.errors import DataError

    path = out / "mapper_checkpoint.npz"
    if not path.exists():
        return ""
    try:
        checkpoint.load(path)
    except (DataError, OSError, ValueError) as err:
        return f"checkpoint corrupt: {str(err)[:80]}"
    return ""


# ---------------------------------------------------------------------------------- watching
class Watch:
    """Reads the run's node stats on its own domain and namespace (a peer node of this process)."""

    def __init__(self, domain: int, namespace: str) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from std_msgs.msg import Header

        from memgs_ros.ros import qos
        from memgs_ros.ros.diagnostics import stats_values

        self._rclpy = rclpy
        self.ctx = rclpy.Context()
        # No signal handlers: this process's Ctrl-C is its own, and cases may watch from threads.
        rclpy.init(context=self.ctx, domain_id=domain, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
        self.node = rclpy.create_node("fault_bench_watch", namespace=namespace, context=self.ctx)
        self.stats: dict[str, dict[str, str]] = {}
        for name in ("player", "merger", "mapper"):
            self.node.create_subscription(DiagnosticArray, f"memgs/{name}/stats",
                                          lambda m, n=name: self.stats.setdefault(n, {}).update(stats_values(m)),
                                          qos.reliable(5))
        # The mapper acknowledges each frame in lockstep: a count exact to the frame, where the
        # player's 1 Hz stats lag by up to a second (six frames).
        self.acked: set[tuple[int, int]] = set()
        self.node.create_subscription(Header, "memgs/frame_ack",
                                      lambda m: self.acked.add((m.stamp.sec, m.stamp.nanosec)), qos.reliable(100))
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)

    def stat(self, node: str, key: str) -> float:
        try:
            return float(self.stats.get(node, {}).get(key, 0))
        except ValueError:
            return 0.0

    def reached(self, point: str) -> bool:
        done = max(len(self.acked), self.stat("player", "frames_published"))
        total = self.stat("player", "frames_total")
        if point == "early":
            return done >= EARLY_FRAMES
        if point == "late":
            return total > 0 and done >= LATE_FRACTION * total
        return total > 0 and done >= total

    def wait_for(self, point: str, runner: subprocess.Popen, timeout_s: float,
                 also: Callable[[], bool] | None = None) -> bool:
        """Spin until the run reaches ``point`` (and ``also`` holds); False when the runner ended
        or time ran out first."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and runner.poll() is None:
            self.executor.spin_once(timeout_sec=0.05)
            if self.reached(point) and (also is None or also()):
                return True
        return False

    def until(self, cond: Callable[[], bool], runner: subprocess.Popen, timeout_s: float) -> bool:
        """Spin until ``cond()`` holds; False when the runner ended or time ran out first."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and runner.poll() is None:
            self.executor.spin_once(timeout_sec=0.05)
            if cond():
                return True
        return False

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.ctx)


# ---------------------------------------------------------------------------------- a case
def _runner_command(out: Path, domain: int, namespace: str, fault: Fault, spec: str) -> list[str]:
    settings = dict(SETTINGS)
    if fault.kind == "delta_loss":
        # 4 deltas a second: the 5th, dropped, is mid-run (a gap the merger must resync), not the
        # last one of a short run, which the mapper's final snapshot repairs without a resync.
        settings.update({"mapper.delta_rate_hz": 4.0, **LOSSY_MERGER})  # the loss: the relay (run_case)
    cmd = [sys.executable, "-m", "memgs_ros", "run", "--bag", spec, "--config", "synthetic", "--out", str(out),
           "--domain-id", str(domain), "--namespace", namespace, "--timeout", str(RUN_TIMEOUT_S)]
    for key, value in settings.items():
        cmd += ["--set", f"{key}={value}"]
    if fault.kind == "kill_restart":
        cmd += ["--kill", f"{fault.target}@2"]  # seconds into the replay (5-7 s long)
    return cmd


def crashed_nodes(logs: Path) -> list[str]:
    """The node logs (killed lives too) holding a Python traceback: a node that crashed."""
    return sorted(p.stem for p in logs.glob("*.log") if "Traceback (most recent call last)" in
                  p.read_text(errors="replace"))


def _outcome(fault: Fault, code: int | None, stderr: str, crashed: list[str], summary_written: bool,
             ) -> tuple[str, str]:
    """(outcome, the line that says it) from the runner's exit status, its stderr and the node logs."""
    lines = [ln for ln in stderr.splitlines() if ln.startswith(("memgs run: error:", "memgs run: interrupted"))]
    if code is None:
        return "unclear", "the runner did not end (killed by the benchmark)"
    if "Traceback" in stderr or crashed:
        where = f"in the log of {', '.join(crashed)}" if crashed else "on stderr"
        return "unclear", f"a traceback {where}: " + (lines[0] if lines else f"exit {code}")[:100]
    if code == 0:
        return ("recovered", "exit 0") if summary_written else ("unclear", "exit 0 without a summary")
    if fault.target == "runner" and fault.sig == signal.SIGKILL and code == -signal.SIGKILL:
        return "ended clearly", "runner SIGKILLed (no line possible; nodes end by PR_SET_PDEATHSIG)"
    if code < 0:  # the runner itself died of a signal nobody sent it (an abort in native code)
        return "unclear", f"the runner died of {signal.Signals(-code).name}" + (f" after: {lines[0]}" if lines else "")
    if len(lines) == 1:
        return "ended clearly", lines[0]
    return "unclear", f"exit {code} with {len(lines)} error lines"


def player_finished(logs: Path) -> bool:
    """True when the bag player logged the end of its source ("done: N frames ...")."""
    try:
        return "]: done: " in (logs / "bag_player.log").read_text(errors="replace")
    except OSError:
        return False


def _summary_verdict(fault: Fault, out: Path, started: float, code: int | None, frames_total: int,
                     ) -> tuple[str, bool, bool]:
    """(what the summary says, whether that is what happened, whether this run wrote it)."""
    path = out / "summary.json"
    try:
        written = path.stat().st_mtime >= started
        s = json.loads(path.read_text()) if written else None
    except (OSError, ValueError):
        written, s = False, None
    if s is None:
        if fault.target == "runner" and fault.sig == signal.SIGKILL:
            return "n/a: runner SIGKILLed", True, False
        return "none", False, False
    said = (f"restarts={s.get('restarts')} resyncs={s.get('merger_resyncs')} identical={s.get('replica_identical')} "
            f"played={s.get('frames_played')}/{frames_total} complete={s.get('source_complete')}")
    if code != 0:  # RunSummary has no field for it yet: an "error" holding the runner's line would say it
        error = s.get("error")
        if isinstance(error, str) and error:
            return f"ok: error={error[:60]}", True, True
        return f"wrong: exit {code} but {said}", False, True
    if fault.kind == "kill_restart":
        ok = s.get("restarts") == {fault.target: 1} and s.get("replica_identical") is True
    elif fault.kind == "delta_loss":
        ok = s.get("merger_resyncs", 0) >= 1 and s.get("replica_identical") is True
    elif fault.kind == "none":
        ok = not s.get("restarts") and s.get("replica_identical") is True and s.get("source_complete") is True
    elif fault.kind == "signal" and fault.target == "bag_player":
        # A player stopped part-way did not play the whole source; one signalled while it lingered
        # after its last frame (1 Hz stats lag behind) did.
        ok = s.get("source_complete") is player_finished(out / "logs")
    elif fault.kind == "signal":
        ok = bool(s.get("restarts", {}).get(fault.target))
    else:  # a disk that refused saves for a while: the summary has no field for failed saves
        return f"silent: {said}", False, True
    return ("ok: " if ok else "wrong: ") + said, ok, True


def run_case(fault: Fault, work: Path, index: int, mount: bool, keep: bool = False, spec: str = SPEC,
             ) -> CaseResult:
    """Run ``memgs run`` on ``spec`` with one fault and check what it left; the case's folder is
    removed when every check passed, unless ``keep``."""
    case_dir = work / f"{index:02d}-{fault.name}"
    case_dir.mkdir(parents=True)
    out = case_dir / "out"
    folder = OutputFolder(out, fault, mount)
    domain = random.Random(f"{os.getpid()}-{index}-{time.time()}").randrange(1, 233)
    namespace = f"/faults_{os.getpid()}_{index}"
    env = dict(os.environ, PYTHONUNBUFFERED="1", **folder.env)
    links = contextlib.ExitStack()  # the lossy link beside the graph, up before the runner starts it
    if fault.kind == "delta_loss":
        links.enter_context(lossy_deltas(domain, namespace, every=5))
    started = time.time()
    t0 = time.monotonic()
    stdout, stderr = open(case_dir / "runner.out", "wb"), open(case_dir / "runner.err", "wb")  # noqa: SIM115
    runner = subprocess.Popen(_runner_command(out, domain, namespace, fault, spec), stdout=stdout, stderr=stderr,
                              env=env, cwd=ROOT, start_new_session=True)  # a Ctrl-C here is not the runner's
    watch = Watch(domain, namespace)
    fault_at, before, merger_held, reached, killed_merger = float("nan"), MapCheck(False), 0, True, False
    try:
        if fault.kind in ("signal", "disk_full", "read_only"):
            # A late disk fault is about keeping the map saved before it: wait until one with
            # Gaussians is on disk (saved each second; a short run reached 80 % of its frames
            # before the merger's first map with content was saved, and kept an empty one).
            keeps = fault.kind in ("disk_full", "read_only") and fault.at != "early"
            reached = watch.wait_for(fault.at, runner, POINT_TIMEOUT_S,
                                     also=(lambda: check_map(out).gaussians > 0) if keeps else None)
            if reached:
                before = check_map(out)
                merger_held = int(watch.stat("merger", "gaussians"))
                fault_at = time.monotonic() - t0
                if fault.kind == "signal":
                    pid = node_pid(out, runner.pid, fault.target)
                    if pid is None:
                        reached = False
                    else:
                        os.kill(pid, fault.sig)
                        killed_merger = fault.target == "merger" and fault.sig == signal.SIGKILL
                else:
                    failed = watch.stat("merger", "problem.save_failed")
                    folder.break_it()
                    # What is on disk once it refuses writes. A save that slipped in just before counts,
                    # also one whose files were written before the disk filled and renamed after (a
                    # niced merger on a busy machine): its saves are one at a time, so once one has
                    # failed none is in flight.
                    watch.until(lambda: watch.stat("merger", "problem.save_failed") > failed, runner, SAVE_FAIL_WAIT_S)
                    before = check_map(out)
                    if fault.until and watch.wait_for(fault.until, runner, POINT_TIMEOUT_S):
                        folder.repair()
        # Spin while waiting, so the watch node never holds up the run's DDS traffic.
        end = time.monotonic() + RUN_TIMEOUT_S
        while runner.poll() is None and time.monotonic() < end:
            watch.executor.spin_once(timeout_sec=0.1)
        code = runner.poll()
        if code is None:
            runner.kill()  # its nodes end with it (PR_SET_PDEATHSIG)
            runner.wait()
        frames_total = int(watch.stat("player", "frames_total"))
    finally:
        watch.close()
        links.close()
        if runner.poll() is None:
            runner.kill()
            runner.wait()
        stdout.close()
        stderr.close()
    gone_s, left = wait_until_gone(out, runner.pid, GONE_LIMIT_S)
    for pid in left:  # leave nothing for the next case
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    wall = time.monotonic() - t0

    after = check_map(out)
    problems = [p for p in (after.problem, check_checkpoint(out)) if p]
    if before.exists and not after.exists:
        problems.append("lost: a map.ply existed at the fault and is gone")
    refused = fault.kind in ("disk_full", "read_only") and not fault.until
    if merger_held and not after.exists and not killed_merger and not refused:
        problems.append(f"lost: the merger held {merger_held} Gaussians and no map.ply was saved")
    if refused and before.exists and (after.digest, after.ids_digest) != (before.digest, before.ids_digest):
        # Every save after the fault failed: both files must be the last complete save's. A new
        # sidecar beside the old PLY gives the map other Gaussians' ids (or none, when the counts differ).
        changed = [n for n, a, b in (("PLY", after.digest, before.digest), ("ids", after.ids_digest,
                                                                              before.ids_digest)) if a != b]
        problems.append(f"{' and '.join(changed)} changed although every save after the fault failed")
    stray = len(list(out.glob(TEMP_GLOB)))
    map_text = "; ".join(problems) if problems else (f"ok {after.gaussians}" if after.exists else "none")
    err_text = (case_dir / "runner.err").read_text(errors="replace")
    summary, summary_ok, written = _summary_verdict(fault, out, started, code, frames_total)
    outcome, line = _outcome(fault, code, err_text, crashed_nodes(out / "logs"), written)
    if not reached:
        outcome, line = "not reached", f"the run ended before the fault point '{fault.at}'"
    folder.close(case_dir / "kept" if folder.mounted else None)
    result = CaseResult(fault.name, outcome, code, line, tuple(f"{p} {c}" for p, c in left), round(gone_s, 1),
                        map_text, not problems, summary, summary_ok, stray, round(fault_at, 1), round(wall, 1),
                        str(case_dir))
    if not keep and result.clean:
        shutil.rmtree(case_dir, ignore_errors=True)
    return result


# ---------------------------------------------------------------------------------- the matrix
@dataclass(frozen=True)
class Totals:
    cases: int
    left_behind: int  # processes left behind (must be 0)
    bad_maps: int  # corrupt or lost maps (must be 0)
    recovered: int
    ended_clearly: int
    unclear: int
    not_reached: int
    summaries_saying: int  # summaries that say what happened (n/a counted)
    summaries_missing: int
    stray_tmp: int
    wall_s: float
    mount: bool
    extra: dict[str, str] = field(default_factory=dict)


def totals(results: list[CaseResult], wall_s: float, mount: bool) -> Totals:
    return Totals(
        cases=len(results), left_behind=sum(len(r.left_behind) for r in results),
        bad_maps=sum(not r.map_ok for r in results),
        recovered=sum(r.outcome == "recovered" for r in results),
        ended_clearly=sum(r.outcome == "ended clearly" for r in results),
        unclear=sum(r.outcome == "unclear" for r in results),
        not_reached=sum(r.outcome == "not reached" for r in results),
        summaries_saying=sum(r.summary_ok for r in results),
        summaries_missing=sum(r.summary == "none" for r in results),
        stray_tmp=sum(r.stray_tmp for r in results), wall_s=round(wall_s, 1), mount=mount)


def format_table(results: list[CaseResult], t: Totals) -> str:
    rows = [("case", "outcome", "exit", "left", "gone s", "map", "summary", "fault s", "wall s", "line")]
    rows += [(r.case, r.outcome, str(r.exit_code), str(len(r.left_behind)), f"{r.gone_s:.1f}", r.map[:40],
              r.summary.split(":")[0], f"{r.fault_at_s:.1f}", f"{r.wall_s:.1f}", r.line[:90]) for r in results]
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]) - 1)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(row, widths)) + "  " + row[-1] for row in rows]
    lines.insert(1, "-" * len(lines[0]))
    lines += [
        "",
        f"cases tried                     {t.cases}",
        f"processes left behind           {t.left_behind}   (must be 0)",
        f"corrupt or lost maps            {t.bad_maps}   (must be 0)",
        f"recovered                       {t.recovered}",
        f"ended clearly                   {t.ended_clearly}",
        f"unclear                         {t.unclear}",
        f"fault point not reached         {t.not_reached}",
        f"summaries saying what happened  {t.summaries_saying} of {t.cases} ({t.summaries_missing} runs wrote none)",
        f"temporary files left            {t.stray_tmp}",
        f"disk faults by                  {'tmpfs mounts' if t.mount else 'injected ENOSPC and chmod (no mount)'}",
        f"wall time                       {t.wall_s:.0f} s",
    ]
    return "\n".join(lines)


def select(faults: list[Fault], patterns: str | None) -> list[Fault]:
    if not patterns:
        return faults
    wanted = [p.strip() for p in patterns.split(",") if p.strip()]
    return [f for f in faults if any(p in f.name for p in wanted)]


def run_matrix(faults: list[Fault], work: Path, mount: bool, keep: bool = False,
               progress: Callable[[str], None] | None = None, lanes: int = 1, spec: str = SPEC,
               ) -> list[CaseResult]:
    """Every case, in order; ``lanes`` > 1 runs that many at once (each on its own domain,
    namespace and folder): shorter in all, but the runs share the cores, so slower each."""
    from concurrent.futures import ThreadPoolExecutor

    def one(i: int, fault: Fault) -> CaseResult:
        if progress is not None:
            progress(f"[{i}/{len(faults)}] {fault.name} ...")
        r = run_case(fault, work, i, mount, keep, spec)
        if progress is not None:
            progress(f"[{i}/{len(faults)}] {fault.name}: {r.outcome}, exit {r.exit_code}, left {len(r.left_behind)}, "
                     f"map {r.map}, summary {r.summary.split(':')[0]} ({r.wall_s:.0f} s)")
        return r

    with ThreadPoolExecutor(max_workers=max(1, lanes)) as pool:
        return list(pool.map(one, range(1, len(faults) + 1), faults))


@contextlib.contextmanager
def work_dir(path: Path | None) -> Iterator[Path]:
    if path is not None:
        path.mkdir(parents=True, exist_ok=True)
        yield path
        return
    with tempfile.TemporaryDirectory(prefix="memgs_faults_") as d:
        yield Path(d)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default=None, help="comma-separated substrings: run the cases whose name holds one")
    ap.add_argument("--json", type=Path, default=None, help="write the matrix and the totals here")
    ap.add_argument("--work", type=Path, default=None,
                    help="keep each case's folder here (default: a temporary folder; failing cases are kept)")
    ap.add_argument("--keep", action="store_true", help="keep every case's folder, not only failing ones")
    ap.add_argument("--no-mount", action="store_true", help="inject ENOSPC and chmod instead of tmpfs mounts")
    ap.add_argument("--lanes", type=int, default=1, help="cases run at once (default 1: timings comparable)")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    ap.add_argument("--table", type=Path, default=None, metavar="JSON", help="print the matrix of a saved run and exit")
    args = ap.parse_args(argv)
    if args.table is not None:
        saved = json.loads(args.table.read_text())
        print(format_table([CaseResult(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in c.items()})
                            for c in saved["cases"]], Totals(**saved["totals"])))
        return 0
    faults = select(all_faults(), args.cases)
    if args.list or not faults:
        print("\n".join(f.name for f in faults) or f"no case matches {args.cases!r}")
        return 0 if faults else 2
    mount = not args.no_mount and can_mount()
    t0 = time.monotonic()
    with work_dir(args.work) as work:
        results = run_matrix(faults, work, mount, args.keep, lambda s: print(s, file=sys.stderr, flush=True),
                             args.lanes)
        t = totals(results, time.monotonic() - t0, mount)
        print(format_table(results, t))
        kept = [r.out_dir for r in results if Path(r.out_dir).exists()]
        if kept and args.work is None:
            print(f"(case folders are in a temporary folder, removed now: pass --work to keep {len(kept)})")
    if args.json is not None:
        write_results(args.json, {"spec": SPEC, "settings": SETTINGS, "totals": asdict(t),
                                  "cases": [asdict(r) for r in results]})
    return 0 if t.left_behind == 0 and t.bad_maps == 0 else 1


if __name__ == "__main__":
    sys.exit(main())

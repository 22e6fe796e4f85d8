"""Process-level CPU tuning for torch work on small, shared machines.

Nothing here runs at import: entry points (CLI commands, node mains, benchmarks) call
:func:`configure_cpu_runtime` once, before heavy work. Two measured effects on the 2-core VMs
this package targets (reference section 11):

- glibc hands big freed blocks back to the OS and faulting the pages in again costs ~2-3 us
  per 4 KB page; keeping freed memory in the heap (``mallopt`` M_MMAP_THRESHOLD /
  M_TRIM_THRESHOLD) made one rasterizer version 3x faster. The price is that the process's
  RSS stays at its high-water mark.
- When other processes share the cores, OpenMP teams stall (a parallel op waits for a
  scheduler tick). One torch intra-op thread plus a few Python threads, each taking whole
  chunks of work (torch releases the GIL inside ops), degrades far more gracefully. The
  rasterizer's compositor switches to that mode when torch runs single-threaded.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

_log = logging.getLogger(__name__)

# glibc <malloc.h> parameter numbers.
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8
# malloc arenas per process (glibc's default is 8 per core): threads that allocate and free
# big blocks in arenas of their own keep them out of each other's reach, so RSS grows
MALLOC_ARENAS = 2
# glibc refuses mmap thresholds above HEAP_MAX_SIZE / 2 (32 MiB on 64-bit); blocks up to that
# size are then served from, and returned to, the heap.
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
TRIM_THRESHOLD_BYTES = 1024 * 1024 * 1024


@dataclass(frozen=True)
class CpuRuntime:
    """What :func:`configure_cpu_runtime` managed to set."""

    torch_threads: int
    heap_kept: bool


def keep_freed_memory() -> bool:
    """Ask glibc malloc to keep freed blocks (<= 32 MiB) instead of returning them to the OS,
    in at most ``MALLOC_ARENAS`` arenas (node processes also get MALLOC_ARENA_MAX from the CLI).

    Returns False (and changes nothing) where the C library is not glibc.
    """
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    ok = mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1
    ok = mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1 and ok
    ok = mallopt(_M_ARENA_MAX, MALLOC_ARENAS) == 1 and ok  # for threads started from now on
    return ok


def release_free_memory() -> bool:
    """Hand free heap pages of every malloc arena back to the OS (glibc ``malloc_trim(0)``).

    A long-running node calls this now and then (NodeStats: every 30 s) so that its resident
    memory tracks what it uses, not the heap's high-water mark that ``keep_freed_memory`` and
    fragmentation leave behind; the pages are faulted in again on demand (~3 us per 4 KB).
    Returns False where the C library has no ``malloc_trim``.
    """
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        trim = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):
        return False
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    trim(0)
    return True


def configure_cpu_runtime(torch_threads: int = 1, keep_heap: bool = True) -> CpuRuntime:
    """Tune this process for CPU tensor work; call once from an entry point.

    torch_threads: torch intra-op threads (1 = let the rasterizer use Python threads per chunk);
    keep_heap: apply :func:`keep_freed_memory`. Returns what was applied.
    """
    import torch  # here, so that release_free_memory's users (every node) need not import torch

    if torch_threads < 1:
        raise ValueError(f"torch_threads must be >= 1, got {torch_threads}")
    torch.set_num_threads(torch_threads)
    kept = keep_freed_memory() if keep_heap else False
    if keep_heap and not kept:
        _log.info("mallopt unavailable (not glibc?): freed memory goes back to the OS")
    return CpuRuntime(torch_threads=torch.get_num_threads(), heap_kept=kept)


@lru_cache(maxsize=1)
def numba_available() -> bool:
    """True when numba imports and MEMGS_DISABLE_NUMBA is unset or 0: the one switch of every
    compiled fast path (rasterizer, tracker kernels); their plain twins run otherwise."""
    if os.environ.get("MEMGS_DISABLE_NUMBA", "") not in ("", "0"):
        return False
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


# The runner names itself to the nodes it starts; a node then asks the kernel to end it with
# the runner (see die_with_parent).
PARENT_PID_ENV = "MEMGS_PARENT_PID"
_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with_parent(parent_pid: int, sig: int = 15) -> bool:
    """Ask the kernel to send ``sig`` (default SIGTERM) to this process when its parent ends,
    however it ends (SIGKILL included), so that a node the runner started never outlives it.

    The kernel sends it when the parent *thread* that forked this process exits: the runner
    starts its nodes from its main thread. Returns False when the parent is already gone
    (``parent_pid`` is no longer the parent: the caller should exit) and True otherwise,
    also where prctl does not exist (not Linux: nothing is armed then).
    """
    name = ctypes.util.find_library("c")
    if name is not None:
        try:
            prctl = ctypes.CDLL(name, use_errno=True).prctl
        except (OSError, AttributeError):
            prctl = None
        if prctl is not None:
            prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]
            prctl.restype = ctypes.c_int
            if prctl(_PR_SET_PDEATHSIG, sig, 0, 0, 0) != 0:
                _log.warning("prctl(PR_SET_PDEATHSIG) failed: errno %d", ctypes.get_errno())
    # The parent may have died between fork and prctl: then nothing will ever be sent.
    return os.getppid() == parent_pid


def lower_priority(niceness: int) -> int:
    """Raise the niceness of every thread of this process to at least ``niceness`` (0..19); the
    niceness now in force on the calling thread.

    Linux keeps a niceness per thread and a new thread inherits its creator's, so this walks
    /proc/self/task: the DDS threads rclpy started before the node existed are lowered too, and
    the threads the node starts later (a training worker, torch's pool) inherit it. Background
    nodes (mapper, keyframe sampler, merger) call it so that the tracker, at 0, wins the cores
    whenever both want them: tracking is the real-time job and mapping takes what is left. A
    process may always lower its own priority; raising it back needs CAP_SYS_NICE, so a value
    below the current one changes nothing.
    """
    if not 0 <= niceness <= 19:
        raise ValueError(f"niceness must be in 0..19, got {niceness}")
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:  # not Linux: the calling thread (and the threads it starts) only
        tids = [0]
    for tid in tids:
        try:
            if os.getpriority(os.PRIO_PROCESS, tid) < niceness:
                os.setpriority(os.PRIO_PROCESS, tid, niceness)
        except OSError:  # the thread ended meanwhile
            continue
    _lower_autogroup(niceness)
    return os.getpriority(os.PRIO_PROCESS, 0)


AUTOGROUP = Path("/proc/self/autogroup")


def _lower_autogroup(niceness: int) -> None:
    """With autogroup scheduling (``kernel.sched_autogroup_enabled``, on in most desktop and
    Debian kernels) the CPU is shared fairly between sessions first and a thread's niceness
    counts only inside its own session: a mapper in a session of its own (``memgs run`` starts
    every node with ``setsid``) took as much CPU as the tracker whatever its niceness. So a
    process that leads its own session lowers its session's weight too. One that does not (a
    node in a terminal, or beside its siblings under ``ros2 launch``) leaves it alone: that
    would lower every process of the session, the tracker's too."""
    try:
        if os.getsid(0) != os.getpid():
            return
        current = int(AUTOGROUP.read_text().split("nice")[1])
        if current < niceness:
            AUTOGROUP.write_text(f"{niceness}\n")
    except (OSError, ValueError, IndexError):  # no autogroup here (disabled, not Linux, a cgroup-only kernel)
        return

"""Process-level memory helpers: freed heap memory really goes back to the OS."""
from __future__ import annotations

import ctypes.util
import sys
from pathlib import Path

import numpy as np
import pytest

from memgs_ros.core.runtime.cpu import release_free_memory


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20


@pytest.mark.skipif(not sys.platform.startswith("linux") or ctypes.util.find_library("c") is None,
                    reason="malloc_trim is glibc's")
def test_release_free_memory_returns_fragmented_heap_pages() -> None:
    # 2000 blocks of 80 KB live on the heap (under any mmap threshold); freeing every other one
    # leaves holes glibc does not hand back by itself, since the heap's top is still in use.
    blocks = [np.ones(10_000) for _ in range(2000)]
    del blocks[::2]
    before = _rss_mb()
    assert release_free_memory()
    after = _rss_mb()
    assert before - after > 40, (before, after)  # ~80 MB of holes
    assert float(sum(b[0] for b in blocks)) == 1000.0  # the live half is intact


def test_lower_priority_reaches_every_thread_and_their_children() -> None:
    """In a child process (the test's own niceness stays): threads started before the call are
    lowered too, threads started after inherit it, and a lower value never raises the priority."""
    import subprocess
    import sys

    code = (
        "import os, threading\n"
        "from memgs_ros.core.runtime.cpu import lower_priority\n"
        "ev = threading.Event(); got = {}\n"
        "def before():\n"
        "    ev.wait(); got['before'] = os.getpriority(os.PRIO_PROCESS, 0)\n"
        "t = threading.Thread(target=before); t.start()\n"
        "assert lower_priority(7) == 7\n"
        "assert lower_priority(3) == 7\n"
        "ev.set(); t.join()\n"
        "t2 = threading.Thread(target=lambda: got.update(after=os.getpriority(os.PRIO_PROCESS, 0))); t2.start(); t2.join()\n"
        "print(got['before'], got['after'])\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["7", "7"]


@pytest.mark.skipif(not Path("/proc/self/autogroup").exists(), reason="no autogroup scheduling in this kernel")
def test_lower_priority_lowers_the_autogroup_of_a_session_leader_only() -> None:
    """With autogroup scheduling a thread's niceness counts only inside its session: a node in a
    session of its own (as memgs run starts them) lowers its session's weight too; a process in
    someone else's session (this test's) leaves that session's weight alone."""
    import subprocess
    import sys

    code = ("from pathlib import Path\n"
            "from memgs_ros.core.runtime.cpu import lower_priority\n"
            "lower_priority(9)\n"
            "print(Path('/proc/self/autogroup').read_text().strip())\n")
    ours = Path("/proc/self/autogroup").read_text()
    if "nice" not in ours:  # empty where the process sits in the root group (CI's container): none applies
        pytest.skip("/proc/self/autogroup is empty: this process is in no autogroup")
    leader = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                            start_new_session=True)
    assert leader.returncode == 0, leader.stderr
    if "nice" not in leader.stdout:
        pytest.skip("a new session gets no autogroup here (/proc/self/autogroup is empty in it)")
    assert leader.stdout.split("nice")[1].strip() == "9"
    member = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert member.returncode == 0, member.stderr
    assert Path("/proc/self/autogroup").read_text() == ours  # the session it shares is untouched
    assert member.stdout.strip() == ours.strip()


def test_parallel_map_keeps_job_order_reuses_its_threads_and_runs_nested_calls_inline() -> None:
    import threading

    from memgs_ros.core.runtime.pool import parallel_map

    names: set[str] = set()

    def job(i: int) -> int:
        names.add(threading.current_thread().name)
        inner = parallel_map(lambda k: k * 10, [1, 2, 3], 2)  # inline on a pool thread: no self-wait
        return i * 2 + sum(inner)

    first = parallel_map(job, list(range(9)), 2)
    assert first == [i * 2 + 60 for i in range(9)]
    seen = set(names)
    assert all(n.startswith("memgs-kernels") for n in seen) and 1 <= len(seen) <= 2
    assert parallel_map(job, list(range(9)), 2) == first
    assert len(names) <= 4 and all(n.startswith("memgs-kernels") for n in names)  # one pool per process


def test_parallel_map_raises_a_jobs_error_after_the_other_jobs_ran() -> None:
    from memgs_ros.core.runtime.pool import parallel_map

    done: list[int] = []

    def job(i: int) -> int:
        if i == 3:
            raise ValueError("job 3")
        done.append(i)
        return i

    with pytest.raises(ValueError, match="job 3"):
        parallel_map(job, list(range(8)), 2)
    assert sorted(done) == [0, 1, 2, 4, 5, 6, 7]  # the other runner drained the rest

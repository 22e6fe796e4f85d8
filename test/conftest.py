"""Shared test fixtures. Tests never read ../shared: every input is generated here."""
from __future__ import annotations

import os
import random
import signal

# A suite started in the background (`cmd &` in a script, nohup) inherits SIGINT ignored, and so
# would every runner and node it starts: the tests of Ctrl-C would then test nothing and fail. A
# handled SIGINT is reset to the default in each child it starts, where Python maps it to
# KeyboardInterrupt as it does for a user's Ctrl-C.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

# Before numpy/torch load their thread pools: two shared cores (see memgs_ros/orchestration/pipeline.py).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

# A stats key that a node's telemetry record does not name raises here (a robot's node counts it
# as problem.stats_key instead): every node the tests start, in process or as a child, inherits it.
os.environ["MEMGS_STRICT_STATS"] = "1"

import pytest

try:
    import torch

    # Two shared cores: one intra-op thread is far steadier than two fighting (reference sec. 11).
    torch.set_num_threads(1)
except ImportError:  # pragma: no cover - torch is a hard dependency; keep collection readable
    pass


@pytest.fixture(scope="session")
def colcon_prefix(tmp_path_factory: pytest.TempPathFactory):  # -> pathlib.Path
    """colcon build the package once per session; the install prefix (see colcon_install.py)."""
    from colcon_install import build

    return build(tmp_path_factory.mktemp("colcon_ws"))


def own_domain_ids(n: int) -> list[int]:
    """``n`` distinct random DDS domain ids in 100-199, from this pytest worker's share of that
    range: the suite runs on several workers (pytest-xdist, README), and two tests running at once
    must never draw the same domain. A namespace of its own (where a test makes one) guards against
    another suite on the same host."""
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")  # gw0, gw1, ...
    index = int(worker[2:]) if worker[2:].isdigit() else 0
    span = 100 // max(1, min(count, 100))
    low = 100 + (index % max(1, min(count, 100))) * span
    return random.Random(os.getpid() ^ id(object())).sample(range(low, low + span), n)


def own_domain_id() -> int:
    """One domain id of this worker's share (:func:`own_domain_ids`)."""
    return own_domain_ids(1)[0]


@pytest.fixture
def ros_domain_id() -> int:
    """A DDS domain id of its own for each test that starts nodes, so parallel runs never hear each other."""
    return own_domain_id()


@pytest.fixture
def context(ros_domain_id: int):  # -> rclpy.Context
    """A private rclpy context on the test's own domain, for nodes run in-process."""
    rclpy = pytest.importorskip("rclpy", reason="the ROS extra is not installed")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_domain_id)
    yield ctx
    rclpy.try_shutdown(context=ctx)


@pytest.fixture
def numba_off(monkeypatch: pytest.MonkeyPatch):  # -> Iterator[None]
    """MEMGS_DISABLE_NUMBA=1 for one test: the plain-torch twins of every compiled path run (the
    branches a GPU takes). numba_available() is read once per process, so its cache is cleared
    on the way in and, with the variable restored, on the way out."""
    from memgs_ros.core.runtime import cpu as runtime

    monkeypatch.setenv("MEMGS_DISABLE_NUMBA", "1")
    runtime.numba_available.cache_clear()
    yield
    monkeypatch.undo()
    runtime.numba_available.cache_clear()


KINDS = ("unit", "integration", "system")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Each test carries its folder's kind as a marker (``-m unit``, ``-m "not system"``):
    test/unit (one process, no DDS), test/integration (one process, real DDS), test/system
    (several processes: the graph's nodes, the runner, colcon, two hosts)."""
    for item in items:
        kind = item.path.parent.name
        if kind in KINDS:
            item.add_marker(getattr(pytest.mark, kind))

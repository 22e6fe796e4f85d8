"""Test support for the tracker's compiled kernels (not a test module): the pinhole camera and
baseline their synthetic problems use, and the skip where numba is off."""
from __future__ import annotations

import numpy as np
import pytest

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
BF = 500.0 * 0.08  # fx times an 8 cm virtual baseline


def needs_numba() -> None:
    """Skip the calling test where numba is missing or disabled (MEMGS_DISABLE_NUMBA)."""
    pytest.importorskip("numba")
    from memgs_ros.core.runtime.cpu import numba_available

    if not numba_available():
        pytest.skip("numba is disabled here (MEMGS_DISABLE_NUMBA)")

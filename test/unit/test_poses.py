"""core.geometry.poses: the numpy rotation conversions against scipy's, the reference."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from memgs_ros.core.geometry.poses import quat_xyzw_to_rotmat, rotmat_to_quat_xyzw, rotmat_to_rotvec


def _rotations() -> np.ndarray:
    """[N, 3, 3]: random rotations plus the cases Shepperd's method branches on: identity, half
    turns about each axis, near half turns and near identity."""
    special = [np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
    special += [Rotation.from_rotvec(v).as_matrix() for v in
                ([np.pi - 1e-9, 0, 0], [0, np.pi - 1e-7, 1e-7], [1e-10, -2e-10, 0], [0, 0, 1e-5])]
    return np.concatenate([Rotation.random(500, random_state=3).as_matrix(), np.array(special)])


def test_quaternions_match_scipy_with_w_non_negative() -> None:
    R = _rotations()
    ref = Rotation.from_matrix(R).as_quat()
    ref = np.where(ref[:, 3:4] < 0, -ref, ref)
    q = rotmat_to_quat_xyzw(R)
    assert q.shape == (len(R), 4) and np.all(q[:, 3] >= 0)
    # A half turn has w = 0, where q and -q are both the answer.
    err = np.minimum(np.abs(q - ref).max(1), np.abs(q + ref).max(1))
    assert err.max() < 1e-12
    one = np.array([rotmat_to_quat_xyzw(r) for r in R])  # the one-matrix path: the same numbers
    np.testing.assert_allclose(one, q, atol=1e-15)
    assert rotmat_to_quat_xyzw(R.reshape(2, -1, 3, 3)).shape == (2, len(R) // 2, 4)


def test_rotation_vectors_match_scipy() -> None:
    R = _rotations()
    ref = Rotation.from_matrix(R).as_rotvec()
    v = rotmat_to_rotvec(R)
    half = np.isclose(np.linalg.norm(ref, axis=1), np.pi)  # +-pi axis: either sign is right
    np.testing.assert_allclose(v[~half], ref[~half], atol=1e-12)
    np.testing.assert_allclose(np.abs(v[half]), np.abs(ref[half]), atol=1e-12)
    np.testing.assert_allclose(np.array([rotmat_to_rotvec(r) for r in R]), v, atol=1e-12)


def test_a_matrix_slightly_off_so3_gives_a_unit_quaternion() -> None:
    R = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix() * (1 + 1e-6)
    q = rotmat_to_quat_xyzw(R)
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-15)
    np.testing.assert_allclose(q, Rotation.from_rotvec([0.3, -0.2, 0.1]).as_quat(), atol=1e-6)


def test_quaternion_to_matrix_matches_scipy() -> None:
    """numpy's conversion (no scipy on a node's executor) against scipy's, unit and unnormalised,
    batched and single; a zero quaternion refused as scipy refuses it."""
    rng = np.random.default_rng(3)
    q = rng.normal(size=(50, 4)) * rng.uniform(0.1, 5.0, size=(50, 1))
    assert np.array_equal(quat_xyzw_to_rotmat(q), Rotation.from_quat(q).as_matrix())  # bit for bit: maps replay alike
    assert np.array_equal(quat_xyzw_to_rotmat(q[7]), Rotation.from_quat(q[7]).as_matrix())
    assert quat_xyzw_to_rotmat(q.reshape(5, 10, 4)).shape == (5, 10, 3, 3)
    with pytest.raises(ValueError):
        quat_xyzw_to_rotmat(np.zeros(4))

"""Quaternions from rotations (``app.domain.frames``): one at a time and many at once give the
rotation back, with w ≥ 0, in every branch of Shepperd's method."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.domain.frames import (
    make_pose,
    pose_to_xyz_quat_xyzw,
    poses_to_xyz_quat_xyzw,
    quat_xyzw_from_rotation,
    quat_xyzw_from_rotations,
    rotation_about_x,
    rotation_about_y,
    rotation_about_z,
    rotation_from_quat_xyzw,
    so3_exp,
)


@pytest.mark.parametrize(
    ("R", "expected"),
    [
        (np.eye(3), [0.0, 0.0, 0.0, 1.0]),  # trace largest
        (rotation_about_x(math.pi), [1.0, 0.0, 0.0, 0.0]),  # x² largest
        (rotation_about_y(math.pi), [0.0, 1.0, 0.0, 0.0]),  # y² largest
        (rotation_about_z(math.pi), [0.0, 0.0, 1.0, 0.0]),  # z² largest
        (rotation_about_z(math.pi / 2), [0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)]),
        (rotation_about_x(-math.pi / 2), [-math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)]),
    ],
    ids=["identity", "x-half-turn", "y-half-turn", "z-half-turn", "z-quarter", "x-minus-quarter"],
)
def test_hand_worked_rotations(R: np.ndarray, expected: list[float]) -> None:
    np.testing.assert_allclose(quat_xyzw_from_rotation(R), expected, atol=1e-15)


def test_many_at_once_give_each_rotation_back_with_w_not_negative() -> None:
    rng = np.random.default_rng(3)
    rotation_vectors = rng.normal(size=(500, 3))
    rotation_vectors *= (rng.uniform(0, math.pi, 500) / np.linalg.norm(rotation_vectors, axis=1))[
        :, None
    ]
    R = so3_exp(rotation_vectors)
    quats = quat_xyzw_from_rotations(R)
    assert quats.shape == (500, 4)
    np.testing.assert_allclose(np.linalg.norm(quats, axis=1), 1.0, atol=1e-15)
    assert (quats[:, 3] >= 0).all()
    back = np.array([rotation_from_quat_xyzw(q) for q in quats])
    np.testing.assert_allclose(back, R, atol=1e-14)
    # each one alone gives the same quaternion
    np.testing.assert_allclose([quat_xyzw_from_rotation(r) for r in R], quats, atol=0)


def test_poses_as_rows_are_each_pose_as_a_row() -> None:
    rng = np.random.default_rng(4)
    poses = np.array(
        [make_pose(so3_exp(rng.normal(size=3)), rng.normal(size=3)) for _ in range(50)]
    )
    rows = poses_to_xyz_quat_xyzw(poses)
    assert rows.shape == (50, 7)
    np.testing.assert_allclose(rows, [pose_to_xyz_quat_xyzw(T) for T in poses], atol=0)
    np.testing.assert_array_equal(rows[:, :3], poses[:, :3, 3])

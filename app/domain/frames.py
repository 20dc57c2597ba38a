"""Rigid transforms as 4×4 numpy arrays, and the app's frame conventions.

A pose of frame B in frame A is written ``A_T_B`` (a 4×4 homogeneous matrix); compose only when the
inner names match: ``world_T_tag = world_T_phone @ phone_T_tag``. Rotations are ``A_R_B`` (3×3),
translations ``A_t_B`` (3,). Quaternions carry their component order in their name: ``quat_xyzw``
(the app's and ROS's order) or ``quat_wxyz`` (gtsam's constructor order).

Conventions of the iPhone app (docs/architecture.md §2):

- ARKit world: right-handed, +y up (gravity-aligned). Phone frame: x right, y up, looking along −z.
- ``tag_pose`` is ``camera_T_tag`` in the OpenCV camera convention (x right, y down, z forward), so
  ``phone_T_tag = PHONE_T_CAMERA_CV @ camera_T_tag``.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: ARKit phone frame (y up, −z forward) from the OpenCV camera frame (y down, +z forward).
# fmt: off
PHONE_T_CAMERA_CV: FloatArray = np.diag([1.0, -1.0, -1.0, 1.0])
# fmt: on

#: Largest ‖RᵀR − I‖ (max abs entry) accepted as a rotation; float32 data sits near 1e-6.
ORTHONORMAL_TOLERANCE = 1e-2


def pose_from_column_major(values: npt.ArrayLike) -> FloatArray:
    """4×4 pose from 16 values flattened column by column (ARKit's ``simd_float4x4`` order)."""
    return np.asarray(values, dtype=np.float64).reshape(4, 4).T.copy()


def pose_from_row_major(values: npt.ArrayLike) -> FloatArray:
    """4×4 pose from 16 values flattened row by row."""
    return np.asarray(values, dtype=np.float64).reshape(4, 4).copy()


def make_pose(A_R_B: npt.ArrayLike, A_t_B: npt.ArrayLike) -> FloatArray:
    """``A_T_B`` from a 3×3 rotation and a translation (3,)."""
    A_T_B = np.eye(4)
    A_T_B[:3, :3] = np.asarray(A_R_B, dtype=np.float64)
    A_T_B[:3, 3] = np.asarray(A_t_B, dtype=np.float64)
    return A_T_B


def se3_inverse(A_T_B: FloatArray) -> FloatArray:
    """``B_T_A`` from ``A_T_B``; works on (4, 4) or stacked (..., 4, 4) poses."""
    A_R_B = A_T_B[..., :3, :3]
    B_R_A = np.swapaxes(A_R_B, -1, -2)
    B_T_A = np.zeros_like(A_T_B)
    B_T_A[..., :3, :3] = B_R_A
    B_T_A[..., :3, 3] = -np.einsum("...ij,...j->...i", B_R_A, A_T_B[..., :3, 3])
    B_T_A[..., 3, 3] = 1.0
    return B_T_A


def relative_se3(world_T_a: FloatArray, world_T_b: FloatArray) -> FloatArray:
    """``a_T_b = world_T_a⁻¹ · world_T_b``."""
    return se3_inverse(world_T_a) @ world_T_b


def rigidity_defect(T: FloatArray) -> str | None:
    """Why ``T`` is not a rigid transform (a readable reason), or None when it is one."""
    if T.shape != (4, 4):
        return f"expected a 4x4 matrix, got shape {T.shape}"
    if not np.all(np.isfinite(T)):
        return "contains a non-finite number"
    last_row = np.array([0.0, 0.0, 0.0, 1.0])
    # np.allclose's test (|a − b| ≤ atol + rtol·|b|), written out: allclose overflows on 1e302.
    if np.any(np.abs(T[3] - last_row) > 1e-3 + 1e-5 * last_row):
        shown = ", ".join(f"{v:.6g}" for v in T[3])
        return f"last row is [{shown}], expected [0, 0, 0, 1]"
    R = T[:3, :3]
    if np.max(np.abs(R)) > 1.0 + ORTHONORMAL_TOLERANCE:  # no rotation has an entry above 1
        return f"rotation not orthonormal (entry {float(np.max(np.abs(R))):.3g} exceeds 1)"
    defect = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if defect > ORTHONORMAL_TOLERANCE:
        return f"rotation not orthonormal (max |RᵀR − I| = {defect:.3g})"
    if np.linalg.det(R) < 0:
        return "rotation is a reflection (determinant < 0)"
    return None


def nearest_rotation(M: FloatArray) -> FloatArray:
    """The rotation closest to ``M`` in the Frobenius norm (SVD projection onto SO(3))."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))])
    return np.asarray(U @ D @ Vt, dtype=np.float64)


def orthonormalized(T: FloatArray) -> FloatArray:
    """``T`` with its rotation projected onto SO(3) and its last row set to [0, 0, 0, 1]."""
    out = T.copy()
    out[:3, :3] = nearest_rotation(T[:3, :3])
    out[3] = [0.0, 0.0, 0.0, 1.0]
    return out


def orthonormalized_stack(poses: FloatArray) -> FloatArray:
    """:func:`orthonormalized` of each of the (N, 4, 4) ``poses`` at once (bit for bit the same:
    numpy runs the same LAPACK call on each 3×3)."""
    out = poses.copy()
    if not poses.shape[0]:
        return out
    U, _, Vt = np.linalg.svd(poses[:, :3, :3])
    D = np.zeros((poses.shape[0], 3, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = np.sign(np.linalg.det(U @ Vt))
    out[:, :3, :3] = U @ D @ Vt
    out[:, 3] = [0.0, 0.0, 0.0, 1.0]
    return out


def rotation_from_quat_xyzw(quat_xyzw: npt.ArrayLike) -> FloatArray:
    """3×3 rotation from a quaternion in (x, y, z, w) order; normalizes it first."""
    x, y, z, w = np.asarray(quat_xyzw, dtype=np.float64) / np.linalg.norm(quat_xyzw)
    # fmt: off
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w),     2 * (x * z + y * w)],
        [2 * (x * y + z * w),     1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w),     2 * (y * z + x * w),     1 - 2 * (x * x + y * y)],
    ])
    # fmt: on


def quat_xyzw_from_rotation(R: FloatArray) -> FloatArray:
    """Unit quaternion (x, y, z, w) with w ≥ 0 from a 3×3 rotation (Shepperd's method)."""
    quat_xyzw: FloatArray = quat_xyzw_from_rotations(np.asarray(R, dtype=np.float64)[None])[0]
    return quat_xyzw


def quat_xyzw_from_rotations(R: FloatArray) -> FloatArray:
    """(M, 4) unit quaternions (x, y, z, w), w ≥ 0, from (M, 3, 3) rotations (Shepperd's method:
    of 4w², 4x², 4y², 4z² the largest is divided by, for a well-conditioned division)."""
    m00, m11, m22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    trace = m00 + m11 + m22
    squares = np.stack(
        [1 + trace, 1 + 2 * m00 - trace, 1 + 2 * m11 - trace, 1 + 2 * m22 - trace], 1
    )
    case = np.argmax(squares, axis=1)
    s = 2.0 * np.sqrt(np.maximum(squares[np.arange(R.shape[0]), case], 1e-300))
    r21_12, r02_20, r10_01 = (
        R[:, 2, 1] - R[:, 1, 2],
        R[:, 0, 2] - R[:, 2, 0],
        R[:, 1, 0] - R[:, 0, 1],
    )
    r01_10, r02_20p, r12_21 = (
        R[:, 0, 1] + R[:, 1, 0],
        R[:, 0, 2] + R[:, 2, 0],
        R[:, 1, 2] + R[:, 2, 1],
    )
    # fmt: off
    candidates = np.stack([
        np.stack([r21_12 / s,  r02_20 / s,  r10_01 / s,  s / 4], 1),
        np.stack([s / 4,       r01_10 / s,  r02_20p / s, r21_12 / s], 1),
        np.stack([r01_10 / s,  s / 4,       r12_21 / s,  r02_20 / s], 1),
        np.stack([r02_20p / s, r12_21 / s,  s / 4,       r10_01 / s], 1),
    ], 1)
    # fmt: on
    quat = candidates[np.arange(R.shape[0]), case]
    quat /= np.linalg.norm(quat, axis=1)[:, None]
    return np.asarray(np.where(quat[:, 3:] < 0, -quat, quat), dtype=np.float64)


def rotation_about_x(angle_rad: float) -> FloatArray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rotation_about_y(angle_rad: float) -> FloatArray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rotation_about_z(angle_rad: float) -> FloatArray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_angle_rad(R: FloatArray) -> float:
    """Angle of the rotation ``R`` in [0, π]."""
    cos_angle = (float(np.trace(R)) - 1.0) / 2.0
    return math.acos(min(1.0, max(-1.0, cos_angle)))


def skew(v: FloatArray) -> FloatArray:
    """(..., 3, 3) cross-product matrices ``[v]×`` of (..., 3) vectors: ``[v]× u = v × u``."""
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def so3_exp(rotation_vector: FloatArray) -> FloatArray:
    """(..., 3, 3) rotations from (..., 3) rotation vectors (Rodrigues); exactly I for zero."""
    angle = np.linalg.norm(rotation_vector, axis=-1)[..., None, None]
    K = skew(rotation_vector)
    small = angle < 1e-8
    safe = np.where(small, 1.0, angle)
    a = np.where(small, 1.0, np.sin(safe) / safe)
    b = np.where(small, 0.5, (1.0 - np.cos(safe)) / safe**2)
    return np.asarray(np.eye(3) + a * K + b * (K @ K), dtype=np.float64)


def so3_log(R: FloatArray) -> FloatArray:
    """(..., 3) rotation vectors (angle in [0, π] times the unit axis) of (..., 3, 3) rotations;
    the inverse of :func:`so3_exp`. Near π, where ``R − Rᵀ`` vanishes, the axis comes from the
    symmetric part instead: ``(R + Rᵀ)/2 = cos θ I + (1 − cos θ) axis axisᵀ``."""
    cos_angle = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos_angle)
    vee = 0.5 * np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        axis=-1,
    )  # sin(angle) · axis
    sin_angle = np.sin(angle)
    general = np.where(
        angle[..., None] < 1e-6,
        vee * (1.0 + angle[..., None] ** 2 / 6.0),  # angle / sin(angle) ≈ 1 + angle²/6
        vee * (angle / np.where(sin_angle == 0.0, 1.0, sin_angle))[..., None],
    )
    symmetric = 0.5 * (R + np.swapaxes(R, -1, -2)) - cos_angle[..., None, None] * np.eye(3)
    outer = symmetric / np.maximum(1.0 - cos_angle, 1e-12)[..., None, None]  # axis axisᵀ
    column = np.argmax(np.diagonal(outer, axis1=-2, axis2=-1), axis=-1)
    axis = np.take_along_axis(outer, column[..., None, None], axis=-1)[..., 0]
    axis /= np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-300)  # 0 away from π
    sign = np.where(np.sum(axis * vee, axis=-1) < 0.0, -1.0, 1.0)
    near_pi = angle[..., None] > math.pi - 1e-3
    return np.asarray(np.where(near_pi, axis * (sign * angle)[..., None], general))


def pose_to_xyz_quat_xyzw(T: FloatArray) -> list[float]:
    """``[x, y, z, qx, qy, qz, qw]`` from a 4×4 pose (the ground-truth JSON form)."""
    return [*T[:3, 3].tolist(), *quat_xyzw_from_rotation(T[:3, :3]).tolist()]


def poses_to_xyz_quat_xyzw(T: FloatArray) -> FloatArray:
    """(M, 7) rows ``[x, y, z, qx, qy, qz, qw]`` of (M, 4, 4) poses: :func:`pose_to_xyz_quat_xyzw`
    of many at once (a map's trajectory)."""
    T = np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)
    return np.concatenate([T[:, :3, 3], quat_xyzw_from_rotations(T[:, :3, :3])], axis=1)


def pose_from_xyz_quat_xyzw(values: npt.ArrayLike) -> FloatArray:
    """4×4 pose from ``[x, y, z, qx, qy, qz, qw]``."""
    v = np.asarray(values, dtype=np.float64)
    return make_pose(rotation_from_quat_xyzw(v[3:7]), v[:3])


# --------------------------------------------------------------------------- tags seen by a camera

#: Tag-frame (x, y) signs of corners 0..3 (architecture §2): (−,−), (+,−), (+,+), (−,+) times s/2.
TAG_CORNER_SIGNS: FloatArray = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
#: Smallest depth divided by in a projection, m (a point on the image plane projects far away).
MIN_PROJECTION_DEPTH_M = 1e-9


def tag_corners_in_tag_frame(size_m: npt.ArrayLike) -> FloatArray:
    """(..., 4, 3) corners 0..3 of tags of side ``size_m`` (a scalar or (...,) array), tag frame."""
    half_m = np.asarray(size_m, dtype=np.float64)[..., None, None] / 2.0
    corners = np.zeros((*half_m.shape[:-2], 4, 3))
    corners[..., :2] = TAG_CORNER_SIGNS * half_m
    return corners


def tag_corners_in_camera(camera_T_tag: FloatArray, size_m: npt.ArrayLike) -> FloatArray:
    """(M, 4, 3) corners of tags of side ``size_m`` (scalar or (M,)) posed at ``camera_T_tag``."""
    corners_tag = tag_corners_in_tag_frame(size_m)
    camera_R_tag = camera_T_tag[:, :3, :3]
    p_camera = corners_tag @ np.swapaxes(camera_R_tag, -1, -2) + camera_T_tag[:, None, :3, 3]
    return np.asarray(p_camera, dtype=np.float64)


def project_pinhole_px(p_camera: FloatArray, intrinsics: npt.ArrayLike) -> FloatArray:
    """(..., 2) pixels ``u = fx·X/Z + cx, v = fy·Y/Z + cy`` of (..., 3) OpenCV-camera points.

    ``intrinsics`` (fx, fy, cx, cy) in px, shape (4,) or broadcastable to ``p_camera``'s leading
    dimensions plus 4 (e.g. (M, 1, 4) for (M, 4, 3) points).
    """
    fx, fy, cx, cy = np.moveaxis(np.asarray(intrinsics, dtype=np.float64), -1, 0)
    depth = p_camera[..., 2]
    depth = np.where(np.abs(depth) < MIN_PROJECTION_DEPTH_M, MIN_PROJECTION_DEPTH_M, depth)
    u = fx * p_camera[..., 0] / depth + cx
    v = fy * p_camera[..., 1] / depth + cy
    return np.stack([u, v], axis=-1)

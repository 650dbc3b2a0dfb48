"""Rotations and rigid transforms as numpy arrays (3x3 and 4x4), with GTSAM's tangent convention.

Quaternions appear only at the boundary and always say their order (``_xyzw``).
"""
from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """The 3x3 matrix ``[v]_x`` with ``[v]_x w = v x w`` (written out: the graph's factors call it per evaluation)."""
    x, y, z = np.asarray(v, dtype=float).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def skew_batch(v: np.ndarray) -> np.ndarray:
    """``[v]_x`` of each row of (n, 3) ``v``: (n, 3, 3)."""
    v = np.asarray(v, dtype=float).reshape(-1, 3)
    W = np.zeros((len(v), 3, 3))
    W[:, 0, 1], W[:, 0, 2], W[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    W[:, 1, 0], W[:, 2, 0], W[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return W


def R_from_rotvec(omega: np.ndarray) -> np.ndarray:
    """SO(3) exponential of an axis-angle vector (radians)."""
    from scipy.spatial.transform import Rotation  # here: scipy.spatial takes 0.3 s to import
    return Rotation.from_rotvec(np.asarray(omega, dtype=float)).as_matrix()


def rotvec_from_R(R: np.ndarray) -> np.ndarray:
    """SO(3) logarithm: the axis-angle vector (radians) of a rotation matrix."""
    from scipy.spatial.transform import Rotation  # here: scipy.spatial takes 0.3 s to import
    return Rotation.from_matrix(np.asarray(R, dtype=float)).as_rotvec()


def rotation_angle(R: np.ndarray) -> float:
    """Angle (radians) of a rotation matrix, in [0, pi]."""
    from scipy.spatial.transform import Rotation  # here: scipy.spatial takes 0.3 s to import
    return float(Rotation.from_matrix(np.asarray(R, dtype=float)).magnitude())


def rotation_error(R_est: np.ndarray, R_true: np.ndarray) -> float:
    """Angle (radians) of ``R_est R_true^T``."""
    return rotation_angle(np.asarray(R_est) @ np.asarray(R_true).T)


def quat_xyzw_from_R(R: np.ndarray) -> np.ndarray:
    """Unit quaternion, scalar last, with non-negative w."""
    from scipy.spatial.transform import Rotation  # here: scipy.spatial takes 0.3 s to import
    q = Rotation.from_matrix(R).as_quat()  # scipy: scalar last
    return q if q[3] >= 0 else -q


def R_from_quat_xyzw(q: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation  # here: scipy.spatial takes 0.3 s to import
    return Rotation.from_quat(np.asarray(q, dtype=float)).as_matrix()


def rpy_from_R(R: np.ndarray) -> np.ndarray:
    """``[roll, pitch, yaw]`` (radians) with ``R = Rz(yaw) Ry(pitch) Rx(roll)``: URDF's ``rpy`` and the
    ``yaw pitch roll`` of ROS's ``static_transform_publisher`` (fixed axes x, y, z in that order). At pitch +-90
    degrees (a camera looking along the LiDAR's x axis, the usual mounting, is there to rounding) roll and yaw turn
    about one axis: the yaw is set to 0 and the roll holds the turn, still exactly ``R`` (scipy's warning of it is
    not passed on)."""
    import warnings

    from scipy.spatial.transform import Rotation  # here: scipy.spatial takes 0.3 s to import
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Gimbal lock detected")
        return Rotation.from_matrix(np.asarray(R, dtype=float)).as_euler("xyz")


def R_from_rpy(rpy: np.ndarray) -> np.ndarray:
    """Inverse of ``rpy_from_R``."""
    from scipy.spatial.transform import Rotation  # here: scipy.spatial takes 0.3 s to import
    return Rotation.from_euler("xyz", np.asarray(rpy, dtype=float)).as_matrix()


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation drawn uniformly from SO(3)."""
    from scipy.spatial.transform import Rotation  # here: scipy.spatial takes 0.3 s to import
    return Rotation.random(random_state=rng).as_matrix()


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation closest to M in Frobenius norm (SVD projection, det fixed to +1); M may be a stack."""
    U, _, Vt = np.linalg.svd(M)
    U = U.copy()
    U[..., :, 2] *= np.sign(np.linalg.det(U @ Vt))[..., None]
    return U @ Vt


# --- rigid transforms -----------------------------------------------------------------------------

def T_from_Rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def T_inverse(T: np.ndarray) -> np.ndarray:
    """``T_b_a`` from ``T_a_b``."""
    R, t = T[:3, :3], T[:3, 3]
    return T_from_Rt(R.T, -R.T @ t)


def transform_points(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Map an (N, 3) array of points from frame b into frame a."""
    return np.asarray(points_b) @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def _so3_left_jacobian(omega: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(omega)
    W = skew(omega)
    if theta < 1e-8:
        return np.eye(3) + 0.5 * W
    a = (1.0 - np.cos(theta)) / theta**2
    b = (theta - np.sin(theta)) / theta**3
    return np.eye(3) + a * W + b * W @ W


def T_exp(xi: np.ndarray) -> np.ndarray:
    """SE(3) exponential of ``xi = [omega; v]`` (GTSAM's ``Pose3.Expmap``)."""
    R, t = exp_batch(xi)
    return T_from_Rt(R[0], t[0])


def T_log(T: np.ndarray) -> np.ndarray:
    """SE(3) logarithm, inverse of :func:`T_exp` (GTSAM's ``Pose3.Logmap``)."""
    omega = rotvec_from_R(T[:3, :3])
    v = np.linalg.solve(_so3_left_jacobian(omega), T[:3, 3])
    return np.concatenate([omega, v])


def exp_batch(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SE(3) exponential of each row of (n, 6) ``xi = [omega; v]``: rotations (n, 3, 3), translations (n, 3)."""
    xi = np.asarray(xi, dtype=float).reshape(-1, 6)
    omega, v = xi[:, :3], xi[:, 3:]
    th2 = np.sum(omega**2, axis=1)
    th = np.sqrt(th2)
    small = th < 1e-4
    safe = np.where(small, 1.0, th)
    # sin(t)/t, (1 - cos t)/t^2, (t - sin t)/t^3 with their Taylor series near 0.
    s1 = np.where(small, 1.0 - th2 / 6.0, np.sin(safe) / safe)
    a = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    b = np.where(small, 1.0 / 6.0 - th2 / 120.0, (safe - np.sin(safe)) / safe**3)
    W = skew_batch(omega)
    WW = W @ W
    eye = np.eye(3)
    R = eye + s1[:, None, None] * W + a[:, None, None] * WW
    J = eye + a[:, None, None] * W + b[:, None, None] * WW
    return R, np.einsum("nij,nj->ni", J, v)


# Rotations within this angle of a half turn (rad) take scipy's logarithm: the axis read from the skew part is
# lost there.
_NEAR_HALF_TURN = 0.5


def _rotvec_batch(R: np.ndarray) -> np.ndarray:
    """The axis-angle vectors of rotations (n, 3, 3): from the skew part and the trace (``atan2``, accurate near
    the identity, where samples about an estimate lie; a fifth of scipy's time), scipy's beyond
    ``pi - _NEAR_HALF_TURN``."""
    v = 0.5 * np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    s = np.linalg.norm(v, axis=1)  # sin(theta)
    c = 0.5 * (R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2] - 1.0)  # cos(theta)
    theta = np.arctan2(s, c)
    factor = np.where(s < 1e-8, 1.0 + theta**2 / 6.0, theta / np.where(s < 1e-8, 1.0, s))
    omega = factor[:, None] * v
    far = theta > np.pi - _NEAR_HALF_TURN
    if far.any():
        from scipy.spatial.transform import Rotation  # here: scipy.spatial takes 0.3 s to import

        omega[far] = Rotation.from_matrix(R[far]).as_rotvec()
    return omega


def log_batch(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """SE(3) logarithm of each pose (rotations (n, 3, 3), translations (n, 3)): rows ``[omega; v]`` (n, 6), the
    inverse of :func:`exp_batch` (GTSAM's ``Pose3.Logmap``)."""
    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    omega = _rotvec_batch(R)
    th2 = np.sum(omega**2, axis=1)
    th = np.sqrt(th2)
    small = th < 1e-4
    safe = np.where(small, 1.0, th)
    # J^-1 = I - W/2 + c W^2, c = 1/t^2 - (1 + cos t) / (2 t sin t), with its Taylor series near 0.
    c = np.where(small, 1.0 / 12.0 + th2 / 720.0, 1.0 / safe**2 - (1.0 + np.cos(safe)) / (2.0 * safe * np.sin(safe)))
    W = skew_batch(omega)
    J_inv = np.eye(3) - 0.5 * W + c[:, None, None] * (W @ W)
    return np.hstack([omega, np.einsum("nij,nj->ni", J_inv, np.asarray(t, dtype=float).reshape(-1, 3))])


def retract_batch(T_hat: np.ndarray, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``T_hat Exp(xi)`` for each row of (n, 6) ``xi``: rotations (n, 3, 3) and translations (n, 3)."""
    dR, dt = exp_batch(xi)
    return T_hat[:3, :3] @ dR, T_hat[:3, 3] + dt @ T_hat[:3, :3].T


def between_batch(Ra: np.ndarray, ta: np.ndarray, Rb: np.ndarray, tb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``T_a^-1 T_b`` for each pair of poses ``(Ra, ta)``, ``(Rb, tb)`` (rotations (n, 3, 3), translations (n, 3)):
    b's pose in a's frame, stacked."""
    return np.einsum("nji,njk->nik", Ra, Rb), np.einsum("nji,nj->ni", Ra, tb - ta)


def local_batch(T_hat: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The rows ``xi`` with ``T_hat Exp(xi) = (R, t)`` for each pose (rotations (n, 3, 3), translations (n, 3)):
    :func:`T_local` of a stack, the inverse of :func:`retract_batch`."""
    Rh, th = T_hat[:3, :3], T_hat[:3, 3]
    return log_batch(np.einsum("ji,njk->nik", Rh, R), (t - th) @ Rh)


def retangent_batch(T_from: np.ndarray, xi: np.ndarray, T_to: np.ndarray) -> np.ndarray:
    """Right tangents at ``T_from`` carried to ``T_to``: the rows ``x`` with ``T_to Exp(x) = T_from Exp(xi)`` (one
    minimum's samples in another's tangent)."""
    return local_batch(T_to, *retract_batch(T_from, xi))


def T_retract(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """Right perturbation ``T Exp(xi)``, the tangent convention of every covariance in lidarcam."""
    return T @ T_exp(xi)


def T_local(T_hat: np.ndarray, T: np.ndarray) -> np.ndarray:
    """The ``xi`` with ``T = T_hat Exp(xi)``."""
    return T_log(T_inverse(T_hat) @ T)


def T_align(points_from: np.ndarray, points_to: np.ndarray) -> np.ndarray:
    """The rigid transform ``T_to_from`` (det +1) that best maps ``points_from`` onto ``points_to``
    (least squares; Kabsch). Needs 3 non-collinear points for a unique answer. Stacks of point sets
    (..., N, 3) give a stack of transforms."""
    A, B = np.asarray(points_from, dtype=float), np.asarray(points_to, dtype=float)
    ca, cb = A.mean(-2, keepdims=True), B.mean(-2, keepdims=True)
    R = nearest_rotation(np.swapaxes(B - cb, -1, -2) @ (A - ca))
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = cb[..., 0, :] - (R @ np.swapaxes(ca, -1, -2))[..., 0]
    T[..., 3, 3] = 1.0
    return T

"""The planar method's closed form (Wei et al. 2015, eqs. 2-5; MATH.md section 1).

Rotation: ``n_ci = R n_li`` for every board, solved by orthogonal Procrustes on
``K = sum_i n_ci n_li^T`` with the determinant fixed to +1. Translation: ``n_ci . t = d_ci - d_li``,
stacked and solved by least squares; it is determined only when the camera normals span 3D.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geometry.planes import Plane
from geometry.rotations import T_from_Rt, nearest_rotation

from ..errors import DegenerateLayoutError

# Smallest singular value of N_c / sqrt(m) (the RMS normal component along the weakest direction)
# below which translation along that direction is treated as undetermined.
MIN_NORMAL_SPREAD = 0.05
# The limit when the closed form only starts the factor graph: between the two, the layout is weak (the
# planar method's boards all tilted one way, spread about 0.02) but the full model still determines it.
WEAK_NORMAL_SPREAD = 0.01
# 2D: board normals (with the segment ends, also the outward normals of the board sides they end on) whose spread
# is below this lie in one plane: translation across it is unobservable, refused at once. Between this and
# MIN_NORMAL_SPREAD the layout is weak but is tried: the factor graph's own observability test decides.
MIN_SCAN_NORMAL_SPREAD = 0.01

_AXIS_WORDS = ("camera x (right)", "camera y (down)", "camera z (forward)")
_AXIS_ADVICE = (
    "add a board turned about the vertical axis so that it faces left or right",
    "add a board tilted about the horizontal axis, its top towards or away from the camera",
    "add a board facing the camera",
)


@dataclass(frozen=True, eq=False)
class ClosedFormSolution:
    T_camera_lidar: np.ndarray
    normal_singular_values: np.ndarray  # of N_c / sqrt(m), descending
    weakest_direction_camera: np.ndarray

    @property
    def condition_number(self) -> float:
        s = self.normal_singular_values
        return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


def describe_direction(v: np.ndarray) -> tuple[str, str]:
    """Words for a camera-frame direction: its dominant axis, and the board pose that constrains it."""
    k = int(np.argmax(np.abs(v)))
    return _AXIS_WORDS[k], _AXIS_ADVICE[k]


def normal_spread(normals_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Singular values of ``N_c / sqrt(m)`` (descending) and the weakest direction (camera frame)."""
    N = np.asarray(normals_camera, dtype=float).reshape(-1, 3)
    _, s, Vt = np.linalg.svd(N / np.sqrt(len(N)), full_matrices=True)
    s = np.concatenate([s, np.zeros(3 - len(s))])
    return s, Vt[-1]


def solve_closed_form(camera_planes: list[Plane], lidar_planes: list[Plane], allow_weak: bool = False
                      ) -> ClosedFormSolution:
    """``T_camera_lidar`` from corresponding board planes (both in canonical, distance >= 0 form).

    Normals spread less than ``MIN_NORMAL_SPREAD`` along some direction raise
    :class:`DegenerateLayoutError`; with ``allow_weak`` (the answer only starts a refinement, which
    measures the full model's information itself) the limit is ``WEAK_NORMAL_SPREAD``.
    """
    m = len(camera_planes)
    if m != len(lidar_planes):
        raise ValueError(f"Expected as many LiDAR planes as camera planes, got {len(lidar_planes)} and {m}")
    if m < 3:
        raise DegenerateLayoutError(
            f"only {m} usable frame(s); the closed form needs at least 3 boards whose normals span 3D",
            hint="record more board poses, tilted in different directions")
    Nc = np.array([p.normal for p in camera_planes])
    Nl = np.array([p.normal for p in lidar_planes])
    s, weak = normal_spread(Nc)
    if s[-1] < (WEAK_NORMAL_SPREAD if allow_weak else MIN_NORMAL_SPREAD):
        axis, advice = describe_direction(weak)
        raise DegenerateLayoutError(
            f"the {m} board normals do not span 3D (spread {s[-1]:.3f} along {axis}, "
            f"direction {np.round(weak, 2).tolist()}), so translation along it is undetermined",
            hint=advice)
    R = nearest_rotation(Nc.T @ Nl)
    delta = np.array([pc.distance - pl.distance for pc, pl in zip(camera_planes, lidar_planes)])
    t = np.linalg.lstsq(Nc, delta, rcond=None)[0]
    return ClosedFormSolution(T_from_Rt(R, t), s, weak)


# A LiDAR whose points are mirrored (a left-handed frame: one axis negated, or two swapped, by a driver or a
# converter) has boards that no rotation lays on the camera's, yet a reflection does. Said only where both are
# plain: the reflection leaves its median board's normal within MIRROR_FIT_DEG, and the best rotation its median
# one beyond MIRROR_MISFIT_DEG (on simulated HDL-64E and VLP-16 sets mirrored or with x and y swapped: 0.1-0.2
# against 11-38 deg; correct sets the other way round). The median lets a wrong board or two through.
MIRROR_FIT_DEG, MIRROR_MISFIT_DEG = 2.0, 5.0
# What a mirror fit means and what to do, in every refusal of one (still poses, a moving board).
MIRROR_CAUSE = "its points are in a left-handed frame, one axis negated or two swapped, or the images are mirrored"
MIRROR_HINT = ("write the points in the LiDAR's own right-handed frame (x forward, y left, z up), and the images as "
               "the camera sees them (no driver's flip)")


def mirrored(camera_planes: list[Plane], lidar_planes: list[Plane]) -> tuple[float, float] | None:
    """``(rotation_deg, reflection_deg)``, the median angle left between the boards' camera normals and their LiDAR
    normals under the best rotation and under the best reflection, where the LiDAR's boards fit the camera's
    through a reflection and not a rotation (its points are in a left-handed frame, :func:`is_mirror_fit`); None
    otherwise, or with fewer than 3 boards."""
    if len(camera_planes) < 3:
        return None
    fit = turned_and_reflected_deg(camera_planes, lidar_planes)
    return fit if is_mirror_fit(*fit) else None


def is_mirror_fit(rotation_deg: float, reflection_deg: float, misfit_deg: float = MIRROR_MISFIT_DEG) -> bool:
    """Whether boards whose normals a rotation leaves ``rotation_deg`` apart (the median) and a reflection
    ``reflection_deg`` fit through a mirror: the reflection within ``MIRROR_FIT_DEG``, the rotation beyond
    ``misfit_deg``."""
    return reflection_deg <= MIRROR_FIT_DEG and rotation_deg >= misfit_deg


def turned_and_reflected_deg(camera_planes: list[Plane], lidar_planes: list[Plane]) -> tuple[float, float]:
    """The median angle (deg) left between the boards' camera normals and their LiDAR normals under the best
    rotation, and under the best reflection (the nearest orthogonal matrix of determinant -1)."""
    Nc = np.array([p.normal for p in camera_planes])
    Nl = np.array([p.normal for p in lidar_planes])
    K, flip = Nc.T @ Nl, np.diag([1.0, 1.0, -1.0])

    def median_deg(M: np.ndarray) -> float:
        return float(np.degrees(np.median(np.arccos(np.clip(np.sum(Nc * (Nl @ M.T), axis=1), -1.0, 1.0)))))

    return median_deg(nearest_rotation(K)), median_deg(nearest_rotation(K @ flip) @ flip)


# The boards :func:`distance_scale` needs: a scale and a translation correction (4 unknowns), with 2 dof to spare.
MIN_SCALE_PLANES = 6


def distance_scale(T_camera_lidar: np.ndarray, camera_planes: list[Plane], lidar_planes: list[Plane]
                   ) -> tuple[float, float] | None:
    """How far the camera's board distances scale against the LiDAR's under ``T_camera_lidar``: ``(s, sd)`` with
    the camera's distance ``d_c = (1 + s) d_l`` (``d_l`` the LiDAR plane's distance in the camera), a translation
    correction fitted with it by least squares, ``sd`` from the residuals' scatter; None with fewer than
    ``MIN_SCALE_PLANES`` planes.

    A LiDAR times its ranges to a few parts per million, so a percent-level ``s`` is the camera's: a wrong
    ``board.square_size`` or focal length scales every board's distance by that share (``pipeline.verdict``)."""
    if len(camera_planes) < MIN_SCALE_PLANES:
        return None
    R, t = T_camera_lidar[:3, :3], T_camera_lidar[:3, 3]
    rows, rhs = [], []
    for pc, pl in zip(camera_planes, lidar_planes):
        n = R @ pl.normal
        d_l = pl.distance + n @ t  # the LiDAR's plane in the camera's frame
        rows.append(np.append(pc.normal, d_l))
        rhs.append(pc.distance - d_l)
    A, b = np.array(rows), np.array(rhs)
    x, *_ = np.linalg.lstsq(A, b, rcond=None)
    r = b - A @ x
    s2 = float(r @ r) / (len(b) - 4)
    AtA = A.T @ A
    if np.linalg.cond(AtA) > 1e12:
        return None
    return float(x[3]), float(np.sqrt(max(s2 * np.linalg.inv(AtA)[3, 3], 0.0)))


def segment_distance_scale(T_camera_lidar: np.ndarray, camera_planes: list[Plane], segments: list[np.ndarray]
                           ) -> tuple[float, float] | None:
    """As :func:`distance_scale` for a 2D scanner, whose boards are segments (each a (2, 3) array of its ends in
    the LiDAR's frame) on the camera's planes: the scale fitted with a rotation and translation correction (a
    segment's two ends leave the rotation free), ``sd`` from the residuals' scatter; None with fewer than 5
    boards."""
    if len(camera_planes) < 5:
        return None
    R, t = T_camera_lidar[:3, :3], T_camera_lidar[:3, 3]
    rows, rhs = [], []
    for pc, ends in zip(camera_planes, segments):
        m = R.T @ pc.normal
        for p in np.asarray(ends, dtype=float):
            # n . (R Exp(w) p + t + v) = d (1 - s), to first order in (w, v, s)
            rows.append(np.concatenate([np.cross(p, m), pc.normal, [pc.distance]]))
            rhs.append(pc.distance - pc.normal @ (R @ p + t))
    A, b = np.array(rows), np.array(rhs)
    AtA = A.T @ A
    if np.linalg.cond(AtA) > 1e12:
        return None
    x = np.linalg.solve(AtA, A.T @ b)
    r = b - A @ x
    s2 = float(r @ r) / (len(b) - 7)
    return float(x[6]), float(np.sqrt(max(s2 * np.linalg.inv(AtA)[6, 6], 0.0)))

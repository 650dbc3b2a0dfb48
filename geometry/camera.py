"""Camera models: OpenCV's radial-tangential pinhole and its fisheye (Kannala-Brandt) model.

Camera frame: x right, y down, z forward (OpenCV). Pixels ``(u, v)`` with the origin at the top-left
pixel's centre, as OpenCV uses them.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

PINHOLE = "pinhole"
FISHEYE = "fisheye"
_DIST_LENGTHS = {PINHOLE: (4, 5, 8, 12, 14), FISHEYE: (4,)}
_PROJECT_BLOCK = 1 << 16  # points per OpenCV projection call (bounds the Jacobian it computes alongside)


def _undistort_points(pts: np.ndarray, K: np.ndarray, dist: np.ndarray, criteria: tuple) -> np.ndarray:
    """``undistortPoints`` with its iterations' criteria: OpenCV 4 names that form ``undistortPointsIter``, OpenCV 5
    gives ``undistortPoints`` the argument (and has no ``undistortPointsIter``)."""
    if hasattr(cv2, "undistortPointsIter"):
        return cv2.undistortPointsIter(pts, K, dist, None, None, criteria)
    return cv2.undistortPoints(pts, K, dist, None, None, None, criteria)


@dataclass(frozen=True, eq=False)
class CameraModel:
    """Intrinsics of one camera. ``dist`` is ``[k1, k2, p1, p2, k3...]`` (pinhole) or ``[k1..k4]`` (fisheye)."""

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    model: str = PINHOLE
    source: str = field(default="given")
    # Standard deviations of [fx, fy, cx, cy, dist...] when the intrinsics were estimated or stated (else None).
    param_std: np.ndarray | None = None
    # Their full covariance when known (refined intrinsics are strongly correlated; None: independent).
    param_covariance: np.ndarray | None = None

    def __post_init__(self):
        K = np.asarray(self.K, dtype=float)
        dist = np.asarray(self.dist if self.dist is not None else [], dtype=float).ravel()
        if self.model not in _DIST_LENGTHS:
            raise ValueError(f"Expected camera model 'pinhole' or 'fisheye', got {self.model!r}")
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"Expected K to be a finite 3x3 matrix with positive focal lengths, got {K.tolist()}")
        if np.abs(K[2] - [0.0, 0.0, 1.0]).max() > 1e-9 or abs(K[1, 0]) > 1e-9:
            transposed = np.abs(K[:, 2] - [0.0, 0.0, 1.0]).max() <= 1e-9 and K[2, 0] > 0
            raise ValueError(f"Expected K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}"
                             + (" (transposed?)" if transposed else ""))
        if not np.all(np.isfinite(dist)):
            raise ValueError(f"Expected finite distortion coefficients, got {dist.tolist()}")
        if dist.size == 0:
            dist = np.zeros(4 if self.model == FISHEYE else 5)
        if dist.size not in _DIST_LENGTHS[self.model]:
            raise ValueError(
                f"Expected {self.model} dist of length {' or '.join(map(str, _DIST_LENGTHS[self.model]))}, "
                f"got {dist.size}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"Expected positive image size, got {self.width}x{self.height}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    def project(self, points_c: np.ndarray) -> np.ndarray:
        """Pixels of (N, 3) camera-frame points; rows behind the camera (z <= 0) are NaN."""
        P = np.asarray(points_c, dtype=float).reshape(-1, 3)
        uv = np.full((len(P), 2), np.nan)
        front = P[:, 2] > 1e-9
        if front.any():
            obj = P[front].reshape(-1, 1, 3)
            zero = np.zeros(3)
            # OpenCV's binding always computes the projection's Jacobian too (2 rows of 10-20 doubles per
            # point): in blocks, a sweep of millions of points needs tens of MB for it, not gigabytes.
            project = cv2.fisheye.projectPoints if self.model == FISHEYE else cv2.projectPoints
            uv[front] = np.concatenate([project(obj[lo:lo + _PROJECT_BLOCK], zero, zero, self.K, self.dist)[0]
                                        for lo in range(0, len(obj), _PROJECT_BLOCK)]).reshape(-1, 2)
        return uv

    def project_jacobian(self, points_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels of (N, 3) camera-frame points in front of the camera, and ``d uv / d point`` (N, 2, 3)."""
        return self.project_jacobians(points_c)[:2]

    def project_jacobians(self, points_c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixels of (N, 3) camera-frame points in front of the camera, ``d uv / d point`` (N, 2, 3) and
        ``d uv / d params`` (N, 2, P) by :attr:`params` ``[fx, fy, cx, cy, dist...]``."""
        P = np.asarray(points_c, dtype=float).reshape(-1, 1, 3)
        zero = np.zeros(3)
        if self.model == FISHEYE:
            img, jac = cv2.fisheye.projectPoints(P, zero, zero, self.K, self.dist)
            dpoint, dparams = jac[:, 11:14], jac[:, 0:8]  # columns: f(2), c(2), k(4), rvec(3), tvec(3), alpha
        else:
            img, jac = cv2.projectPoints(P, zero, zero, self.K, self.dist)
            dpoint, dparams = jac[:, 3:6], jac[:, 6:10 + self.dist.size]  # rvec(3), tvec(3), f(2), c(2), dist
        # With zero rotation and translation, the derivative by tvec is the derivative by the point.
        return img.reshape(-1, 2), dpoint.reshape(-1, 2, 3), dparams.reshape(-1, 2, 4 + self.dist.size)

    def normalized_from_pixels(self, uv: np.ndarray) -> np.ndarray:
        """Undistorted normalized coordinates ``(x/z, y/z)`` of (N, 2) pixels (the inverse of :meth:`project`)."""
        pts = np.asarray(uv, dtype=float).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
        if self.model == FISHEYE:
            out = cv2.fisheye.undistortPoints(pts, self.K, self.dist, criteria=crit)
        else:
            out = _undistort_points(pts, self.K, self.dist, crit)
        return out.reshape(-1, 2)

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Unit viewing rays (camera frame) through (N, 2) pixels."""
        xy = self.normalized_from_pixels(uv)
        r = np.column_stack([xy, np.ones(len(xy))])
        return r / np.linalg.norm(r, axis=1, keepdims=True)

    def principal_point_offset(self) -> np.ndarray:
        """How far the principal point lies from the image's centre, as shares of its width and height (2,): a few
        hundredths for a camera's own intrinsics, a half or a quarter for a K of twice or half the images' size."""
        size = np.array([self.width, self.height], float)
        return np.abs(self.K[:2, 2] - (size - 1) / 2) / size

    def in_image(self, uv: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        with np.errstate(invalid="ignore"):
            return ((uv[:, 0] >= margin_px) & (uv[:, 0] <= self.width - 1 - margin_px)
                    & (uv[:, 1] >= margin_px) & (uv[:, 1] <= self.height - 1 - margin_px))

    def sees(self, points_c: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """Which (N, 3) camera-frame points the camera images: in front of it, projected inside the image,
        and truly there. A distortion polynomial folds back far outside its calibrated field, so a point well
        outside the field of view can project into the image; such a point's pixel does not undistort back to
        its own direction and is not seen."""
        P = np.asarray(points_c, dtype=float).reshape(-1, 3)
        uv = self.project(P)
        ok = self.in_image(uv, margin_px)
        if ok.any():
            back = self.normalized_from_pixels(uv[ok])
            ok[np.nonzero(ok)[0]] = np.linalg.norm(back - P[ok, :2] / P[ok, 2:], axis=1) < 1e-4
        return ok

    def field_angle(self) -> float:
        """The widest angle (rad) from the optical axis of the rays through the image's border: beyond it the
        camera images nothing (a point there that projects into the image is the distortion folding back)."""
        u, v = np.linspace(0, self.width - 1, 33), np.linspace(0, self.height - 1, 25)
        border = np.vstack([np.column_stack([u, np.zeros_like(u)]), np.column_stack([u, np.full_like(u, v[-1])]),
                            np.column_stack([np.zeros_like(v), v]), np.column_stack([np.full_like(v, u[-1]), v])])
        return float(np.max(np.arccos(np.clip(self.rays(border)[:, 2], -1.0, 1.0))))

    @property
    def params(self) -> np.ndarray:
        """``[fx, fy, cx, cy, dist...]``."""
        return np.concatenate([[self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]], self.dist])

    def with_params(self, params: np.ndarray) -> "CameraModel":
        """The same model with ``[fx, fy, cx, cy, dist...]`` replaced (skew kept)."""
        p = np.asarray(params, dtype=float)
        K = self.K.copy()
        K[0, 0], K[1, 1], K[0, 2], K[1, 2] = p[:4]
        return CameraModel(K, p[4:], self.width, self.height, self.model, self.source, self.param_std,
                           self.param_covariance)

    def param_steps(self, scale: float = 1.0) -> list[np.ndarray]:
        """One standard deviation of the parameters (times ``scale``) along each principal direction of their
        covariance, or along each parameter alone where only their standard deviations are known; none without
        either. The first-order propagation of uncertain intrinsics moves them by these."""
        if self.param_covariance is not None:
            ev, V = np.linalg.eigh(0.5 * (self.param_covariance + self.param_covariance.T))
            return [scale * np.sqrt(max(lam, 0.0)) * v for lam, v in zip(ev, V.T)]
        if self.param_std is None:
            return []
        return [scale * sd * np.eye(len(self.param_std))[k] for k, sd in enumerate(self.param_std)
                if np.isfinite(sd) and sd > 0]

    def as_dict(self) -> dict:
        d = {"model": self.model, "width": self.width, "height": self.height,
             "K": self.K.tolist(), "dist": self.dist.tolist(), "source": self.source}
        if self.param_std is not None:
            d["param_std"] = self.param_std.tolist()
            d["param_order"] = "fx fy cx cy " + " ".join(f"d{k}" for k in range(self.dist.size))
        return d

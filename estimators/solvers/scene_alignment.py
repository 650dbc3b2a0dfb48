"""The scene as a witness of an extrinsic: the LiDAR's depth contours laid on the camera's image edges.

Each frame (``SceneView``) holds the LiDAR's contour returns (``lidar.depth_edges``) that the camera can see from
its own centre (``visible_from_camera``: a z-buffer of the whole sweep seen from the camera, under the extrinsic
given), and the image's edges (``camera.edge_map``). A contour return is where its ring crosses an object's
silhouette: it says where along the ring the silhouette lies, not where along the silhouette the ring lies (a
vertical edge seen by level rings fixes no height). So its residual is its distance along its ring's direction
in the image to the nearest edge square enough to that direction (``ring_directions``; the edge's normal within
``MIN_TRANSVERSE`` of it, ``transverse_edges``): the offset across that edge divided by the cosine between the
edge's normal and the ring, and the truncation where it has no such edge within it (or lies beyond the nearest
one's end, ``FOOT_PX``) or leaves the image. (Measured to the nearest edge pixel in any direction, returns were
pulled along silhouettes towards the ends of their image edges, a stand's foot the grey of the floor having
none, and onto edges the rings run along, a wall meeting the floor: on simulated offices with the board left
out the scene's estimate leant 0.5-0.9 degrees about the camera's x axis and 20-45 mm along its y.)
``align_scene`` minimises the residuals' sum of squares over the extrinsic's six tangent directions
(``T Exp(xi)``, the project's convention) by Levenberg-Marquardt with the Jacobian in closed form (the edge's
normal over that cosine times the projection's derivative, ``CameraModel.project_jacobian``).

Residuals are neither independent (a contour is many returns, an image edge many of its residuals) nor Gaussian
(a truncated distance), and the frames of a still rig are not independent either: each one sees the same walls,
doors and furniture, with the same errors. The independent units are the scene's structures, so the residuals
are pooled by where they land in the image (``BLOCKS`` cells, every frame's residuals in a cell together): the
covariance is the block sandwich ``H^-1 (sum_b g_b g_b^T) H^-1 n / (n - 1)`` with ``H = J^T J`` and ``g_b`` block
b's gradient at the optimum. One error the blocks do not see: where a contour's silhouette lies within the
LiDAR's azimuth step (the contour return is put half a step out, ``lidar.depth_edges``, the silhouette anywhere in
that step) is one draw for every ring that fires at a vertical edge at one azimuth, and for every frame of a still
rig; such a structure (``structures``) can span many blocks and hold most of the returns (one wall edge held 148
of a simulated office's 238 and set its estimate). Each structure's draw, a turn about the LiDAR's spin axis of
variance step^2 / 12, is added to the sandwich's meat (``structure_information``). The covariance needs no noise
level and is noisy with few blocks: the test against a given extrinsic (``consistency``) reads the squared
distance as Hotelling's (``F = d2 (n - k) / (k (n - 1))``, ``F(k, n - k)``, n blocks), over the ``k`` directions
the scene constrains (standard deviations within ``CONSTRAINED``). The cost can have several minima about as low
(``scene_minima`` seeks them from 13 starts): the scatter of those the blocks cannot tell from the estimate
(``minima_scatter``) is what its covariance does not see. A check's estimate is the minimum sought from the given
extrinsic unless another fits the scene significantly better over the blocks (``nearest_decided``,
``better_fit``): the lowest RMS alone rewards a minimum that drags contours without an image edge of their own onto
the ends of others' edges.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares

from geometry.camera import CameraModel
from geometry.rotations import T_inverse, T_log, T_retract, transform_points
from geometry.vectors import row_norms

from ..camera.edge_map import EdgeMap
from ..errors import DegenerateLayoutError
from . import chi_square as chi2

# A direction counts as constrained by the scene when its standard deviation is within these (rad, m).
CONSTRAINED = (np.radians(1.0), 0.10)
# A change along one camera axis that the check flags only beyond this many times ``CONSTRAINED`` is along a
# direction the scene leaves free (``smallest_flagged``).
FREE_BEYOND = 10.0
# The starts of ``scene_minima`` about the given extrinsic (deg about, m along each camera axis); a minimum within
# this share of the best's RMS residual and beyond its covariance's 0.999 region (chi-square, 6 dof) is a rival.
START_DEG, START_M = 1.0, 0.05
RIVAL_RMS, RIVAL_D2 = 0.01, 22.46
# A check's estimate is the minimum sought from the given extrinsic unless another fits the scene better at this
# one-sided level (``nearest_decided``).
BETTER_ALPHA = 0.05
# The later solves' truncations of the edge fields (px), each from the one before.
STAGES_PX = (6.0,)
# The information's smallest eigenvalue at or below this share of its largest leaves a direction free: inverted, a
# few contour returns' information (12 of a recorded Ouster scene's, beyond 8 m: a ratio of 1e-15) gave a
# "covariance" with negative variances. The recorded sets' whole scenes lie at 4e-5 (VLP-16) and 7e-4 (Ouster), a
# third of the VLP-16's image (52 returns) at 4e-6.
SINGULAR_INFORMATION = 1e-10
# The image cut into this many cells (across, down) for the covariance's blocks.
BLOCKS = (8, 6)
# An edge pixel serves a contour return when its normal lies within this cosine of the return's ring direction
# in the image (the silhouette within 37 degrees of square to the ring): a range jump along a ring marks a
# silhouette that crosses it, and an edge the ring runs along is not one.
MIN_TRANSVERSE = 0.8
# A contour return's nearest edge pixel measures it only where the return lies across the edge from it: its foot on
# the edge's tangent line within FOOT_PX plus FOOT_SLOPE of its distance of the pixel (the nearest pixel by
# OpenCV's 5x5 mask, and its normal, are a little off: 99% within that on straight and slanted edges); beyond an
# edge's end the return has no edge.
FOOT_PX, FOOT_SLOPE = 1.5, 0.2
# Turned this far about the LiDAR's z axis (rad), a return gives its ring's direction in the image.
RING_STEP_RAD = 1e-3
# Contour returns of one structure lie within this distance from the spin axis of a neighbour of it (m).
STRUCTURE_RANGE_M = 0.3
# The z-buffer's cell (px) and how far behind the nearest return in its cell a contour return may lie (m).
ZBUFFER_CELL_PX, ZBUFFER_MARGIN_M = 4, 0.2


@dataclass(frozen=True, eq=False)
class SceneView:
    """One frame: its name, the contour returns the camera sees (LiDAR frame, (N, 3)), the image's edges square
    enough to the rings (``camera.edge_map.EdgeMap``: ``transverse_edges``), and the residuals' truncation (px)."""

    name: str
    points: np.ndarray
    edges: EdgeMap
    truncate_px: float = 0.0  # the residuals' truncation: no edge within it, or off the image
    azimuth_step: float = 0.0  # the sweep's azimuth step (rad; 0: unknown, no structure term)
    # The plain distance to the nearest edge instead (any direction, up to an edge's end): a broad basin for a
    # start several degrees off (a targetless calibration's first stage), biased near the answer.
    chamfer: bool = False


def ring_directions(T: np.ndarray, points: np.ndarray, camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """Where ``points`` (LiDAR frame) project under ``T`` and their rings' unit directions there (each point
    turned by ``RING_STEP_RAD`` about the LiDAR's z axis): ``(uv (N, 2), d (N, 2))``, NaN where a point does not
    project."""
    P = np.asarray(points, float).reshape(-1, 3)
    c, s = np.cos(RING_STEP_RAD), np.sin(RING_STEP_RAD)
    turned = np.column_stack([c * P[:, 0] - s * P[:, 1], s * P[:, 0] + c * P[:, 1], P[:, 2]])
    uv = camera.project(transform_points(T, P))
    d = camera.project(transform_points(T, turned)) - uv
    with np.errstate(invalid="ignore", divide="ignore"):
        d /= np.linalg.norm(d, axis=1, keepdims=True)
    return uv, d


def transverse_edges(edges: np.ndarray, normals: np.ndarray, T: np.ndarray, camera: CameraModel,
                     depth_m: float = 5.0, cell_px: int = 16) -> np.ndarray:
    """Which edge pixels (``edges`` (M, 2), their unit ``normals``) lie square enough (``MIN_TRANSVERSE``) to the
    LiDAR's rings under ``T``: the ring's direction from the point ``depth_m`` along the viewing ray through the
    centre of the pixel's ``cell_px`` cell (the direction changes slowly across the image and barely with the
    depth). A bool per edge pixel."""
    if len(edges) == 0:
        return np.zeros(0, bool)
    cells = np.floor(np.asarray(edges, float) / cell_px).astype(np.int64)
    wide = int(cells[:, 0].max()) + 1
    unique, which = np.unique(cells[:, 1] * wide + cells[:, 0], return_inverse=True)
    centres = (np.column_stack([unique % wide, unique // wide]) + 0.5) * cell_px
    _, d = ring_directions(T, transform_points(T_inverse(T), camera.rays(centres) * depth_m), camera)
    return np.abs(np.sum(normals * d[which.reshape(-1)], axis=1)) >= MIN_TRANSVERSE


def beam_steps(sweep: np.ndarray, ring: np.ndarray) -> tuple[float, float]:
    """The sweep's median azimuth step within a ring and median elevation step between rings (rad)."""
    P = np.asarray(sweep, float).reshape(-1, 3)
    az = np.arctan2(P[:, 1], P[:, 0])
    el = np.arctan2(P[:, 2], np.hypot(P[:, 0], P[:, 1]))
    steps, levels = [], []
    for beam in np.unique(ring):
        on = ring == beam
        if on.sum() >= 3:
            steps.append(np.median(np.diff(np.sort(az[on]))))
            levels.append(np.median(el[on]))
    d_az = float(np.median(steps)) if steps else 0.0
    d_el = float(np.median(np.diff(np.sort(levels)))) if len(levels) > 1 else 0.0
    return d_az, d_el


def structures(views: list[SceneView]) -> np.ndarray:
    """Which contour returns share one draw of where their silhouette lies within the azimuth step (module
    docstring): those at one azimuth (within half a step of a neighbour) and distance from the spin axis (within
    ``STRUCTURE_RANGE_M`` of a neighbour), every ring's and every frame's together. A label per return of the
    views, in order; a view without a step (``azimuth_step`` 0) has each return alone."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    P = np.concatenate([v.points for v in views]) if views else np.zeros((0, 3))
    step = np.concatenate([np.full(len(v.points), v.azimuth_step) for v in views]) if views else np.zeros(0)
    n = len(P)
    if n == 0:
        return np.zeros(0, np.int64)
    az = np.arctan2(P[:, 1], P[:, 0])
    az = np.angle(np.exp(1j * (az - np.angle(np.mean(np.exp(1j * az))))))  # about the returns' mean: no wrap
    X = np.column_stack([az / np.where(step > 0, step, 1.0), np.linalg.norm(P[:, :2], axis=1)
                         / (2 * STRUCTURE_RANGE_M)])
    X[step <= 0, 0] = 10.0 * np.flatnonzero(step <= 0)  # no step known: each alone
    pairs = cKDTree(X).query_pairs(0.5, p=np.inf, output_type="ndarray")
    A = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(A, directed=False)[1]


def structure_information(views: list[SceneView], J: np.ndarray) -> np.ndarray:
    """The shared draws' share of the gradient's covariance (6x6, the meat of ``H^-1 M H^-1``): per structure
    (:func:`structures`) the residuals' derivative by its turn about the LiDAR's spin axis (``J[:, 2]``: the
    tangent's rotation about the LiDAR's z), of variance step^2 / 12, mapped through the Jacobian ``J`` (the
    views' returns stacked)."""
    labels = structures(views)
    if not len(labels):
        return np.zeros((6, 6))
    sd = np.concatenate([np.full(len(v.points), v.azimuth_step / np.sqrt(12.0)) for v in views])
    a = np.zeros((int(labels.max()) + 1, 6))
    np.add.at(a, labels, J * (J[:, 2] * sd)[:, None])
    return a.T @ a


def beam_spacing_px(sweep: np.ndarray, ring: np.ndarray, camera: CameraModel,
                    steps: tuple[float, float] | None = None) -> tuple[float, float]:
    """How far apart the sweep's returns lie in the image (px, across and down): :func:`beam_steps` (``steps``,
    when taken already) times the camera's focal lengths."""
    d_az, d_el = beam_steps(sweep, ring) if steps is None else steps
    return d_az * camera.K[0, 0], d_el * camera.K[1, 1]


def visible_from_camera(points: np.ndarray, sweep: np.ndarray, T_camera_lidar: np.ndarray, camera: CameraModel,
                        cell_px: int = ZBUFFER_CELL_PX, margin_m: float = ZBUFFER_MARGIN_M,
                        spacing_px: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Which of ``points`` (LiDAR frame) the camera sees from its own centre: in front, in the image, and no
    farther than ``margin_m`` behind the nearest return of the whole ``sweep`` near its z-buffer cell: each return
    covers the cells within 1.5 times the returns' spacing in the image (``spacing_px``, across and down:
    :func:`beam_spacing_px`), so that a surface whose sparse returns leave cells between them still hides what
    lies behind it."""
    def cells(P):
        pc = transform_points(T_camera_lidar, P)
        uv = camera.project(pc)
        ok = np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & \
            (uv[:, 0] < camera.width) & (uv[:, 1] < camera.height)
        cu, cv = np.zeros(len(P), np.int64), np.zeros(len(P), np.int64)
        cu[ok] = (uv[ok, 0] // cell_px).astype(np.int64)
        cv[ok] = (uv[ok, 1] // cell_px).astype(np.int64)
        return ok, cu, cv, row_norms(pc)

    from scipy.ndimage import minimum_filter

    nu = camera.width // cell_px + 1
    zbuf = np.full((camera.height // cell_px + 1) * nu, np.inf)
    ok, cu, cv, depth = cells(np.asarray(sweep, float).reshape(-1, 3))
    np.minimum.at(zbuf, cv[ok] * nu + cu[ok], depth[ok])
    size = tuple(int(np.clip(2 * np.ceil(1.5 * sp / cell_px / 2) + 1, 1, 31)) for sp in spacing_px[::-1])
    zbuf = minimum_filter(zbuf.reshape(-1, nu), size=size, mode="nearest").ravel()
    ok, cu, cv, depth = cells(np.asarray(points, float).reshape(-1, 3))
    seen = np.zeros(len(ok), bool)
    seen[ok] = depth[ok] <= zbuf[cv[ok] * nu + cu[ok]] + margin_m
    return seen


def view_residuals(T: np.ndarray, view: SceneView, camera: CameraModel, jacobian: bool = True
                   ) -> tuple[np.ndarray, np.ndarray | None]:
    """One frame's residuals under ``T`` (each contour return's distance along its ring to its edge, px; the
    truncation where it has none or leaves the image) and their Jacobian by ``T``'s right tangent (N, 6), or
    None."""
    return stacked_residuals(T, [view], camera, jacobian)[0]


@dataclass(frozen=True, eq=False)
class SceneFit:
    """The scene's estimate near a start: ``T_camera_lidar``, its frame-block sandwich covariance (6x6, the
    project's tangent), the Gauss-Newton information ``hessian`` (J^T J, px^-2 units), the frames and contour
    returns used, the image blocks of the covariance, the RMS residual (px) at the start and at the end, and the
    step from the start (tangent)."""

    T_camera_lidar: np.ndarray
    covariance: np.ndarray
    hessian: np.ndarray
    frames: int
    points: int
    blocks: int
    rms_start_px: float
    rms_px: float
    moved: np.ndarray
    converged: bool
    start: int = 0  # which of ``scene_minima``'s starts it was sought from (0: the given extrinsic)


def stacked_residuals(T: np.ndarray, views: list[SceneView], camera: CameraModel, jacobian: bool = True
                      ) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """Every view's :func:`view_residuals` under ``T``, as a list of (residuals, Jacobian or None): the frames'
    returns projected together (one projection, one Jacobian product), each measured on its own edges."""
    sizes = [len(v.points) for v in views]
    P = np.concatenate([v.points for v in views]) if views else np.zeros((0, 3))
    uv, d = ring_directions(T, P, camera)
    r = np.concatenate([np.full(n, v.truncate_px) for n, v in zip(sizes, views)]) if views else np.zeros(0)
    slope = np.zeros((len(P), 2))  # the residual's derivative by the pixel: the normal over its cosine
    ok = np.zeros(len(P), bool)
    start = 0
    for n, v in zip(sizes, views):
        sl = slice(start, start + n)
        start += n
        h, w = v.edges.nearest.shape
        at, dd = uv[sl], d[sl]
        inside = np.all(np.isfinite(at), axis=1) & np.all(np.isfinite(dd), axis=1) & (at[:, 0] >= 0) & \
            (at[:, 1] >= 0) & (at[:, 0] <= w - 1) & (at[:, 1] <= h - 1)
        k = np.flatnonzero(inside)
        pu, pv = np.rint(at[k, 0]).astype(np.int64), np.rint(at[k, 1]).astype(np.int64)
        e = v.edges.nearest[pv, pu]
        has = (e >= 0) & (v.edges.distance[pv, pu] <= v.truncate_px)
        k, e = k[has], e[has]
        nrm, off = v.edges.normals[e], at[k] - v.edges.edges[e]
        if v.chamfer:
            dist = np.hypot(off[:, 0], off[:, 1])
            r[sl][k] = dist
            slope[sl][k] = off / np.maximum(dist, 1e-9)[:, None]
            ok[sl][k] = dist > 0
            continue
        cos = np.sum(nrm * dd[k], axis=1)
        foot = np.abs(nrm[:, 0] * off[:, 1] - nrm[:, 1] * off[:, 0])
        across = (np.abs(cos) >= MIN_TRANSVERSE) & (foot <= FOOT_PX + FOOT_SLOPE * np.hypot(off[:, 0], off[:, 1]))
        k, nrm, off, cos = k[across], nrm[across], off[across], cos[across]
        along = np.sum(nrm * off, axis=1) / cos
        near = np.abs(along) < v.truncate_px
        k = k[near]
        r[sl][k] = along[near]
        slope[sl][k] = nrm[near] / cos[near, None]
        ok[sl][k] = True
    J = None
    if jacobian:
        J = np.zeros((len(P), 6))
        if ok.any():
            pc = transform_points(T, P[ok])
            _, duv = camera.project_jacobian(pc)  # the projection's derivative by the camera-frame point
            R = T[:3, :3]
            p = P[ok]
            # d p_c / d xi for T Exp(xi) p: rotation -R [p]x, translation R.
            skew = np.zeros((len(p), 3, 3))
            skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -p[:, 2], p[:, 1], -p[:, 0]
            skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = p[:, 2], -p[:, 1], p[:, 0]
            dp = np.concatenate([-R @ skew, np.broadcast_to(R, (len(p), 3, 3))], axis=2)  # (n, 3, 6)
            J[ok] = np.einsum("ni,nij,njk->nk", slope[ok], np.nan_to_num(duv), dp)
    bounds = np.cumsum([0, *sizes])
    return [(r[a:b], None if J is None else J[a:b]) for a, b in zip(bounds[:-1], bounds[1:])]


def rms_px(T: np.ndarray, views: list[SceneView], camera: CameraModel) -> float:
    """The views' RMS residual under ``T`` (px)."""
    r = np.concatenate([r for r, _ in stacked_residuals(T, views, camera, False)])
    return float(np.sqrt(np.mean(r ** 2)))


def narrowed(view: SceneView, truncate_px: float) -> SceneView:
    """The view with its residuals truncated nearer (``truncate_px``)."""
    return replace(view, truncate_px=min(truncate_px, view.truncate_px))


def narrowest(views: list[SceneView]) -> list[SceneView]:
    """The views narrowed to the last of ``STAGES_PX``: the field on which minima are compared over the blocks."""
    return [narrowed(v, STAGES_PX[-1]) for v in views] if STAGES_PX else views


def align_scene(views: list[SceneView], camera: CameraModel, T_start: np.ndarray, max_evaluations: int = 60,
                stages: list | None = None, narrow_from_start: bool = True, decided: bool = False) -> SceneFit:
    """The extrinsic that lays the contour returns on the image edges best near ``T_start`` (module docstring):
    solved with the views' fields as given, then again from there with them truncated at ``STAGES_PX`` (a contour
    that has no edge of its own then stops being pulled by another's a little further away); and with the
    narrowest fields alone from ``T_start`` too (the wide field's minimum can lie beyond the narrow one's near
    the start: its pull from contours with no edge of their own is a bias). The fit and its covariance are the
    narrowest stage's lower one; with ``decided`` (a check's start: its estimate is the minimum nearest the given
    extrinsic) the narrowest field's from the start unless the wide path's fits significantly better
    (``better_fit``; on a simulated VLP-16 office the wide path's lower RMS lay 78 mm from the truth along the
    optical axis, not significantly better over the blocks). ``stages``: the views narrowed for each of
    ``STAGES_PX``, when made already; ``narrow_from_start`` False: the wide field's path alone, for a start meant
    to explore.
    A :class:`DegenerateLayoutError` with fewer than two frames or no contour in view."""
    stages = stages if stages is not None else [[narrowed(v, px) for v in views] for px in STAGES_PX]
    fit = align_once(views, camera, T_start, max_evaluations)
    converged = fit.converged
    for narrow in stages:
        fit = align_once(narrow, camera, fit.T_camera_lidar, max_evaluations)
        converged = converged and fit.converged
    if stages and narrow_from_start:
        try:
            near = align_once(stages[-1], camera, T_start, max_evaluations)
        except DegenerateLayoutError:  # no contour within the narrowest truncation of its edge from there
            near = None
        # decided: as in ``nearest_decided`` (a lower RMS alone also rewards contours dragged onto others' edge
        # ends); otherwise the lower (a targetless search, whose estimate is the lowest minimum)
        if near is not None and (near.rms_px < fit.rms_px
                                 or decided and better_fit(near, fit, stages[-1], camera, T_start) >= BETTER_ALPHA):
            fit, converged = near, near.converged
    # at the start on the narrowest truncation too, so that the two compare
    return replace(fit, rms_start_px=rms_px(T_start, stages[-1] if stages else views, camera),
                   moved=T_log(T_inverse(T_start) @ fit.T_camera_lidar), converged=converged)


def scene_minima(views: list[SceneView], camera: CameraModel, T_given: np.ndarray,
                 narrow_from_every_start: bool = False, decided: bool = False) -> list[SceneFit]:
    """The scene's estimates from ``T_given`` and from it turned by ``START_DEG`` about, and moved by ``START_M``
    along, each of the camera's axes (13 starts; one from which too few contours meet their edges to solve is
    dropped), lowest RMS residual first: a cost with one minimum near the given
    extrinsic gives them all alike; one that leaves the extrinsic undetermined scatters them. The narrowest field
    alone is also solved from ``T_given`` (``align_scene``), and from every start with
    ``narrow_from_every_start`` (a targetless start's neighbourhood: the wide field's minimum can lie tens of
    millimetres from the narrow one's, and only a start near the latter finds it). ``decided``: ``T_given``'s
    minimum chosen as a check's (``align_scene``)."""
    from geometry.rotations import R_from_rotvec, T_from_Rt

    starts = [T_given]
    for k in range(3):
        for sign in (1.0, -1.0):
            e = np.zeros(3)
            e[k] = sign
            starts.append(T_from_Rt(R_from_rotvec(np.radians(START_DEG) * e), np.zeros(3)) @ T_given)
            starts.append(T_from_Rt(np.eye(3), START_M * e) @ T_given)
    stages = [[narrowed(v, px) for v in views] for px in STAGES_PX]
    fits = []
    for i, T in enumerate(starts):
        try:
            fits.append(replace(align_scene(views, camera, T, stages=stages,
                                            narrow_from_start=narrow_from_every_start or T is T_given,
                                            decided=decided and T is T_given), start=i))
        except DegenerateLayoutError:
            if T is T_given:
                raise
            # a start from which too few contours meet their edges to solve: it finds no minimum
    return sorted(fits, key=lambda f: f.rms_px)


def block_costs(T: np.ndarray, views: list[SceneView], camera: CameraModel, T_blocks: np.ndarray) -> np.ndarray:
    """Each image block's sum of squared residuals under ``T`` (``BLOCKS`` cells, every frame's together), each
    return put in the block where it lands under ``T_blocks`` (one assignment for every candidate compared)."""
    acc = np.zeros(BLOCKS[0] * BLOCKS[1])
    for view, (r, _) in zip(views, stacked_residuals(T, views, camera, False)):
        uv = np.nan_to_num(camera.project(transform_points(T_blocks, view.points)), nan=-1.0)
        np.add.at(acc, image_block(uv, camera), r ** 2)
    return acc


def image_block(uv: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Which of the ``BLOCKS`` cells each pixel ``uv`` (N, 2; finite) lies in, row by row (those off the image in
    the nearest)."""
    nu, nv = BLOCKS
    cu = np.clip((uv[:, 0] * nu // camera.width).astype(int), 0, nu - 1)
    cv = np.clip((uv[:, 1] * nv // camera.height).astype(int), 0, nv - 1)
    return cv * nu + cu


def better_fit(a: SceneFit, b: SceneFit, views: list[SceneView], camera: CameraModel, T_blocks: np.ndarray
               ) -> float:
    """The one-sided p-value that ``b`` fits the scene better than ``a``: Student's paired t over the image
    blocks (the scene's independent units, as in the covariance) of their summed squared residuals
    (``block_costs``, ``views`` at the fits' truncation). A lower RMS alone also rewards a minimum that drags
    contours with no image edge of their own (a silhouette the colour of what lies behind it) onto the end of a
    neighbour's edge: fewer truncated residuals, a better fit of nothing."""
    ca, cb = (block_costs(f.T_camera_lidar, views, camera, T_blocks) for f in (a, b))
    d = (ca - cb)[(ca > 0) | (cb > 0)]
    if len(d) < 2 or np.ptp(d) == 0:  # no spread to weigh the difference by: only a uniform gain decides
        return 0.0 if len(d) and d[0] > 0 else 1.0
    t = d.mean() / (d.std(ddof=1) / np.sqrt(len(d)))
    return float(chi2.t_sf(t, len(d) - 1))


def nearest_decided(fits: list[SceneFit], views: list[SceneView], camera: CameraModel, T_given: np.ndarray,
                    alpha: float = BETTER_ALPHA) -> list[SceneFit]:
    """``fits`` (``scene_minima``'s) reordered so that the first is the scene's estimate for a check of
    ``T_given``: the minimum sought from it, unless the lowest fits the scene significantly better (``better_fit``
    below ``alpha``); the others after it, lowest first. Taking the lowest minimum always, the check flagged 6 of
    119 true extrinsics of simulated scenes at its 1% level (seeds 100-139), 4 of them VLP-16 offices whose
    estimate a contour without an image edge of its own had led 0.2-0.6 degrees off."""
    near = next((f for f in fits if f.start == 0), fits[0])
    if near is fits[0]:
        return fits
    stage = narrowest(views)
    if better_fit(near, fits[0], stage, camera, T_given) < alpha:
        return fits
    return [near] + [f for f in fits if f is not near]


def rival_minima(fits: list[SceneFit]) -> list[SceneFit]:
    """The minima other than the estimate (``fits[0]``) that fit as well or better, or within ``RIVAL_RMS`` of its
    RMS residual, and lie beyond its covariance's 0.999 region (6 dof): where there are any, the estimate's
    covariance is not the scene's uncertainty."""
    best = fits[0]
    out = []
    for f in fits[1:]:
        xi = T_log(T_inverse(best.T_camera_lidar) @ f.T_camera_lidar)
        if f.rms_px <= best.rms_px * (1 + RIVAL_RMS) and xi @ np.linalg.solve(best.covariance, xi) > RIVAL_D2:
            out.append(f)
    return out


def align_once(views: list[SceneView], camera: CameraModel, T_start: np.ndarray, max_evaluations: int) -> SceneFit:
    """One Levenberg-Marquardt solve on the views' fields as they are, from ``T_start``, with its block
    covariance."""
    views = [v for v in views if len(v.points)]
    n_points = sum(len(v.points) for v in views)
    if len(views) < 2 or n_points == 0:
        raise DegenerateLayoutError(f"the scene gives {len(views)} frame(s) with LiDAR contours in view",
                                    hint="give more frames, with objects at several distances in view of both")
    scale = np.sqrt(n_points)

    last: dict = {}

    def both(x):  # MINPACK asks for the Jacobian at the point whose residuals it has just had: made once
        if last.get("x") is None or not np.array_equal(last["x"], x):
            parts = stacked_residuals(T_retract(T_start, x), views, camera)
            last.update(x=np.array(x), r=np.concatenate([r for r, _ in parts]) / scale,
                        J=np.concatenate([J for _, J in parts]) / scale)
        return last

    def fun(x):
        return both(x)["r"]

    def jac(x):
        return both(x)["J"]

    sol = least_squares(fun, np.zeros(6), jac=jac, method="lm", x_scale=np.r_[0.01, 0.01, 0.01, 0.05, 0.05, 0.05],
                        xtol=1e-6, max_nfev=max_evaluations)
    T = T_retract(T_start, sol.x)
    parts = stacked_residuals(T, views, camera)
    H = sum(J.T @ J for _, J in parts)
    g = block_gradients(T, views, parts, camera)
    n = len(g)
    if n < 2:
        raise DegenerateLayoutError(f"the scene's contours meet their edges in {n} image block(s): too few to "
                                    "weigh them", hint="give frames with objects at several distances in view of both")
    lam, V = np.linalg.eigh(0.5 * (H + H.T))
    if not lam[0] > SINGULAR_INFORMATION * lam[-1]:
        raise DegenerateLayoutError("the scene's contours leave a direction of the extrinsic free (a singular "
                                    "information)", hint="give frames with objects at several distances in view of "
                                                         "both")
    Hi = (V / lam) @ V.T
    meat = g.T @ g * n / (n - 1) + structure_information(views, np.concatenate([J for _, J in parts]))
    cov = Hi @ meat @ Hi
    r0 = fun(np.zeros(6)) * scale
    r1 = np.concatenate([r for r, _ in parts])
    return SceneFit(T, 0.5 * (cov + cov.T), H, len(views), n_points, n, float(np.sqrt(np.mean(r0 ** 2))),
                    float(np.sqrt(np.mean(r1 ** 2))), sol.x.copy(), bool(sol.success))


def block_gradients(T: np.ndarray, views: list[SceneView], parts: list, camera: CameraModel) -> np.ndarray:
    """Each image block's share of the gradient, every frame's residuals in the block pooled ((blocks, 6), the
    blocks holding a residual with a slope)."""
    nu, nv = BLOCKS
    acc = np.zeros((nu * nv, 6))
    used = np.zeros(nu * nv, bool)
    for view, (r, J) in zip(views, parts):
        uv = camera.project(transform_points(T, view.points))
        ok = np.all(np.isfinite(uv), axis=1) & np.any(J != 0, axis=1)
        b = image_block(uv[ok], camera)
        np.add.at(acc, b, J[ok] * r[ok, None])
        used[b] = True
    return acc[used]


def constrained_directions(covariance: np.ndarray, limits: tuple[float, float] = CONSTRAINED
                           ) -> tuple[np.ndarray, np.ndarray]:
    """The covariance's principal directions in units of ``limits`` (rotation rad, translation m): those whose
    standard deviation stays within one unit are the scene's constrained ones. ``(vectors (6, k), variances (k,))``
    in those units."""
    s = np.r_[np.full(3, 1.0 / limits[0]), np.full(3, 1.0 / limits[1])]
    C = s[:, None] * covariance * s[None, :]
    lam, V = np.linalg.eigh(0.5 * (C + C.T))
    keep = (lam > 0) & (lam <= 1.0)
    return V[:, keep], lam[keep]


def minima_scatter(fits: list[SceneFit], views: list[SceneView], camera: CameraModel, T_blocks: np.ndarray
                   ) -> np.ndarray:
    """The second moment (6x6, the estimate's tangent) about the estimate (``fits[0]``) of the minima the scene
    cannot tell from it: those the estimate does not fit significantly better over the image's blocks
    (``better_fit`` at ``BETTER_ALPHA``, ``views`` narrowed to the last of ``STAGES_PX``, blocks under
    ``T_blocks``). How far the scene's cost leaves its own minimum undecided, which the estimate's covariance (its
    curvature and its blocks) does not see. Counting only the minima within ``RIVAL_RMS`` of its RMS residual, as
    before, the estimates sought 0.2 degrees and 2 cm off the truth of simulated scenes had NEES means up to 12.6
    and up to 20% beyond the 99% point (seeds 100-139): a minimum 1-5% higher in RMS is often no worse over the
    blocks."""
    best = fits[0]
    stage = narrowest(views)
    xis = [np.zeros(6)] + [T_log(T_inverse(best.T_camera_lidar) @ f.T_camera_lidar) for f in fits[1:]
                           if better_fit(f, best, stage, camera, T_blocks) >= BETTER_ALPHA]
    return sum(np.outer(x, x) for x in xis) / len(xis)


def constrained_distance(covariance: np.ndarray, xi: np.ndarray, limits: tuple[float, float] = CONSTRAINED
                         ) -> tuple[float, int]:
    """The squared distance of the difference ``xi`` (tangent) under ``covariance`` over the directions it
    constrains (:func:`constrained_directions`), and how many those are."""
    V, lam = constrained_directions(covariance, limits)
    s = np.r_[np.full(3, 1.0 / limits[0]), np.full(3, 1.0 / limits[1])]
    z = V.T @ (s * xi)
    return float(np.sum(z ** 2 / lam)), int(V.shape[1])


def smallest_flagged(covariance: np.ndarray, T_given: np.ndarray, blocks: int, alpha: float,
                     limits: tuple[float, float] = CONSTRAINED) -> np.ndarray | None:
    """How sensitive :func:`consistency`'s test is along each of the camera's axes: the turn about (rad) and the move
    along (m) each axis of ``T_given`` (``Exp(d) T_given``, ``d`` one axis's turn or move in the camera's frame) at
    which the test reaches its level ``alpha`` were the scene's estimate where ``T_given`` is, under ``covariance``
    (the test's) over ``blocks`` blocks; (6,), inf along an axis the scene leaves free (a size beyond
    ``FREE_BEYOND`` times ``limits``); None where the test is undetermined. The difference such a change makes,
    ``Log(T_given^-1 Exp(d) T_given) = Ad(T_given^-1) d``, is linear in its size, and its squared distance
    quadratic: each axis's size is the square root of the critical squared distance over that of a unit change. A
    larger change is flagged more often than not, a smaller one less; where the scene's estimate lies off the given
    extrinsic, changes towards it are flagged later. A change along one axis alone: one that turns and moves
    together along the directions the scene confuses is flagged later still."""
    from .factor_graph import adjoint

    V, _ = constrained_directions(covariance, limits)
    k, n = int(V.shape[1]), int(blocks)
    if k == 0 or n <= k:
        return None
    d2_crit = float(chi2.f_isf(alpha, k, n - k)) * k * (n - 1) / (n - k)
    A = adjoint(T_inverse(T_given))
    unit = np.array([constrained_distance(covariance, A @ e, limits)[0] for e in np.eye(6)])
    size = np.sqrt(d2_crit / np.maximum(unit, 1e-300))
    # beyond ten times the constrained limits a size is the rounding of a free direction into the others
    return np.where(size <= FREE_BEYOND * np.repeat(limits, 3), size, np.inf)


def consistency(fit: SceneFit, T_given: np.ndarray, limits: tuple[float, float] = CONSTRAINED,
                covariance: np.ndarray | None = None) -> dict:
    """Whether ``T_given`` agrees with the scene's estimate: the squared distance over the constrained directions
    (``d2``, ``dof`` = k), Hotelling's ``F`` on ``(k, n - k)`` and its tail probability ``p_value``; ``None``
    values when the scene constrains no direction or has too few blocks (n <= k). ``covariance``: the one to
    test against (default the fit's)."""
    xi = T_log(T_inverse(fit.T_camera_lidar) @ T_given)
    d2, k = constrained_distance(fit.covariance if covariance is None else covariance, xi, limits)
    n = fit.blocks
    out = {"difference_tangent": xi.tolist(), "dof": int(k), "blocks": int(n), "d2": None, "F": None,
           "p_value": None}
    if k == 0 or n <= k:
        return out
    F = d2 * (n - k) / (k * (n - 1))
    out.update(d2=d2, F=F, p_value=float(chi2.fdtrc(k, n - k, F)))
    return out

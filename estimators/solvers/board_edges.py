"""The board's edges as measurements: where each LiDAR ring (or a 2D scan's line) leaves the board.

Planes fix the translation only along the boards' normals; when the normals are weakly spread (boards in front
of the rig, tilted a little) the in-plane directions rest on little. Each ring that crosses a board stops at the
board's outline, whose place on the board the camera knows (the board's pose and its size, ``BoardModel``).

Measurement (per ring end). Along a ring the beams fire at a fixed azimuth step ``delta``; the board's edge lies
between the last return on the board (azimuth ``phi``) and the next firing, which missed it. With the edge's
azimuth uniform on that interval, and the beam's centre able to fall off the board by a little while its
footprint still returns from it (``BEAM_SD_RAD``, in any direction across the beam: in elevation as much as in
azimuth), the edge is taken at the interval's middle, ``phi +- delta / 2``, with the uniform's variance
``delta^2 / 12`` along the ring and the footprint's ``BEAM_SD_RAD^2`` across the beam, both mapped to metres
across the side it crosses (a ring running nearly along the top or the bottom side crosses it by its elevation).
The two moments are what a Gaussian keeps of that interval. An end that is not the board's edge (a holder's
hand, a stand, a return lost at the edge) lies inside the outline, far out in those units: inward, the ends'
likelihood is a mixture of that Gaussian and a uniform up to ``MAX_END_OFFSET_M`` inside (share
``HIDDEN_END_SHARE``), so such an end stops pulling; outward, where no hidden end can lie, a Huber loss
(``EDGE_HUBER``) bounds the pull of a stray return (:func:`end_loss`). A 2D scan's board segment is one ring:
its two ends are the same measurement, and the same factor serves both LiDARs.

Residual (per end): the mid-beam's ray cut with the board's plane, in the board's frame, and its signed
distance outward of the side of the outline it crosses (``sides``: x = 0, x = w, y = 0, y = h), less two
nuisances: the dataset's outline (``graph_keys.outline_key``, one per dataset and LiDAR: the growth of the x and
the y sides, as a beam footprint or mixed returns make the LiDAR's board look larger than the given size, and the
outline's offset from where the dataset puts it; priors 0 +- ``GROWTH_PRIOR_SD_M`` and ``OFFSET_PRIOR_SD_M``) and
the frame's outline shift (``graph_keys.edge_shift_key``, 0 +- the boards' in-plane scatter, estimated by the
refinement).
Its Jacobians by the extrinsic and the board pose (right tangents, ``T Exp(xi)``, ``xi = [rot; trans]``):
with ``q = R (s b) + t`` the cut in the board frame (``R, t`` of ``T_board_lidar``), ``P`` the projection
along the ray onto the board's plane and ``w = P^T [a; 0]`` (``a`` the side's outward normal),

    d r / d xi_extrinsic = [p x u, u]   (u = R^T w, p = s b the cut in the LiDAR frame),
    d r / d xi_board     = [w x q, -w].

Sides are assigned once, under the estimate from the planes (the side the ring's direction of travel leaves
by); ends near a corner of the outline, rings that graze a side, and ends far from any side are not used.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import gtsam
import numpy as np

from geometry.board import BoardModel
from geometry.planes import cut_with_board

# Beam footprint (rad, 1 sd of where the beam's centre can be while the board still returns it): a few mrad of
# divergence in spinning LiDARs (VLP-16 3 mrad full width, OS1 about 3 mrad), of which a return's centre counts
# about a quarter either side.
BEAM_SD_RAD = 7.5e-4
# Huber threshold (in standard deviations of an end's position) beyond which the pull of an end beyond its side
# stops growing (:func:`end_loss`).
EDGE_HUBER = 2.5
# Share of ends that are not their side's but were hidden before it (a hand, a stand, a return lost at the edge),
# anywhere up to MAX_END_OFFSET_M inside (:func:`end_loss`).
HIDDEN_END_SHARE = 0.05
# The edge growth's prior (m): the footprint at 10 m, or a board a centimetre off its given size.
GROWTH_PRIOR_SD_M = 0.01
# Ends closer than this (m) to a corner of the outline along their side are not used (which side is crossed
# is then not clear).
CORNER_MARGIN_M = 0.02
# Ends further than this (m) from their side under the planes' estimate are not edges (a hand, a clamp).
MAX_END_OFFSET_M = 0.15
# A ring that meets its side at less than this sine of the angle grazes it and is not used.
MIN_CROSSING_SINE = 0.3
MIN_RING_POINTS = 4
# The pattern's offset on the board from where the dataset puts it (m): printing and mounting, a few mm.
OFFSET_PRIOR_SD_M = 0.01
# The board's outline against the dataset's (``graph_keys.outline_key``), one per dataset and LiDAR: ``[growth of
# the x = 0, w sides, of the y = 0, h sides, the outline's offset along the board's x, y]`` (m).

# Outward normals and offsets of the outline's sides in the board frame: x = 0, x = w, y = 0, y = h.
SIDE_NORMALS = np.array([[-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0]])


@dataclass(frozen=True)
class EdgeCrossings:
    """One frame's ring ends used as edges: per end the unit mid-beam (LiDAR frame), the side crossed (0-3:
    x = 0, x = w, y = 0, y = h of the board's outline), its ring, and the standard deviation (m) of its
    position across that side."""

    beams: np.ndarray
    sides: np.ndarray
    rings: np.ndarray
    sd_m: np.ndarray

    @property
    def size(self) -> int:
        return len(self.sides)


def side_offsets(board: BoardModel, sides: np.ndarray) -> np.ndarray:
    w, h = board.extent
    return np.array([0.0, w, 0.0, h])[sides]


def _azimuth(points: np.ndarray) -> np.ndarray:
    return np.arctan2(points[:, 1], points[:, 0])


def _unwrapped(phi: np.ndarray, centre: float | None = None) -> np.ndarray:
    """Azimuths unwrapped about ``centre`` (default: their median; one board never spans half a turn)."""
    centre = float(np.median(phi)) if centre is None else centre
    return centre + np.angle(np.exp(1j * (phi - centre)))


def _ring_extremes(points: np.ndarray, rings: np.ndarray):
    """Per ring with ``MIN_RING_POINTS`` returns and a positive step: ``(ring, its returns' indices, their unwrapped
    azimuths, step, [(index of its first return, -1), (of its last, +1)])`` (step: the median azimuth spacing)."""
    for r in np.unique(rings):
        at = np.flatnonzero(rings == r)
        if len(at) < MIN_RING_POINTS:
            continue
        phi = _unwrapped(_azimuth(points[at]))
        order = np.argsort(phi)
        step = float(np.median(np.diff(phi[order])))
        if step > 0:
            yield int(r), at, phi, step, ((order[0], -1.0), (order[-1], 1.0))


def open_ends(points: np.ndarray, rings: np.ndarray, others: np.ndarray, other_rings: np.ndarray) -> np.ndarray:
    """Per point of a board (``points``, ``rings``): whether it is its ring's first or last return and the ring's
    next firing beyond it (half to one and a half azimuth steps on) returned among ``others`` (their rings
    ``other_rings``): the sweep's returns in the board's plane band that were not taken as the board's. Such a ring
    goes on in the board's plane: its end is where a cut was made (the board's window, where a range offset spreads
    the returns wider than the board; a trim), or a hand or a wall in the plane goes on from the board, not where
    the beams leave the board. :func:`ring_ends` leaves these out."""
    out = np.zeros(len(points), dtype=bool)
    for r, at, phi, step, extremes in _ring_extremes(points, rings):
        theirs = others[other_rings == r]
        if not len(theirs):
            continue
        beyond = _unwrapped(_azimuth(theirs), float(np.median(phi)))
        for k, sign in extremes:
            gap = sign * (beyond - phi[k]) / step
            out[at[k]] = bool(np.any((gap > 0.5) & (gap < 1.5)))
    return out


def ring_ends(points: np.ndarray, rings: np.ndarray, open_at: np.ndarray | None = None
              ) -> list[tuple[int, np.ndarray, float]]:
    """Each ring's two ends on the board, as ``(ring, mid-beam, step)``: the unit beam half an azimuth step
    beyond the ring's last return at each end (the step: the median spacing of the ring's returns). Ends at a
    return that ``open_at`` marks (:func:`open_ends`) are left out: the ring goes on in the board's plane there."""
    out = []
    for r, at, phi, step, extremes in _ring_extremes(points, rings):
        for k, sign in extremes:
            if open_at is not None and open_at[at[k]]:
                continue
            p = points[at[k]]
            el = np.arctan2(p[2], np.hypot(p[0], p[1]))
            a = phi[k] + sign * 0.5 * step
            out.append((r, np.array([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.sin(el)]), sign * step))
    return out


# The returns' azimuth noise is measured from the second differences of their sorted azimuths only while it stays
# under this share of the azimuth step; beyond it the sort reorders neighbouring returns and hides it.
MAX_MEASURED_JITTER = 0.1


@dataclass(frozen=True)
class EndNoise:
    """What blurs a ring's end beyond its azimuth step, across the beam: an angle (the footprint and the azimuths'
    own jitter, rad) and a distance (returns whose positional noise is not along their beam, m)."""

    beam_sd_rad: float = BEAM_SD_RAD
    position_sd_m: float = 0.0


def end_noise(scans: list[tuple[np.ndarray, np.ndarray]]) -> EndNoise:
    """The ends' noise across the beam, from ``scans`` (each a board's points and their rings). Along a ring the
    beams fire a fixed step apart and a return lies on its beam, noisy in range only: then the second differences
    of successive returns' azimuths (where neither gap skips a beam) measure the azimuths' jitter alone (variance
    ``6 sd^2``, by the median absolute deviation), zero for exact angles, and it adds to the footprint
    (``BEAM_SD_RAD``). Where that jitter reaches ``MAX_MEASURED_JITTER`` of the step, the returns are off their
    beams by about their spacing (points with noise in every direction, a scan de-skewed or converted with noise):
    their noise is then taken as isotropic, its size the returns' scatter across the board's line (or plane)."""
    second, steps, scatter = [], [], []
    for points, rings in scans:
        for r in np.unique(rings):
            P = points[rings == r]
            d = np.diff(np.sort(_unwrapped(_azimuth(P))))
            if len(d) < 4:
                continue
            step = float(np.median(d))
            if not step > 0:
                continue
            steps.append(step)
            regular = (np.abs(d[:-1] / step - 1.0) < 0.5) & (np.abs(d[1:] / step - 1.0) < 0.5)
            second.append(np.diff(d)[regular])
        scatter.append(_scatter(points))
    second = np.concatenate(second) if second else np.zeros(0)
    if len(second) < 10:
        return EndNoise()
    jitter = float(1.4826 * np.median(np.abs(second - np.median(second))) / np.sqrt(6.0))
    if jitter < MAX_MEASURED_JITTER * float(np.median(steps)):
        return EndNoise(float(np.hypot(BEAM_SD_RAD, jitter)))
    return EndNoise(BEAM_SD_RAD, float(np.median(scatter)))


def _scatter(points: np.ndarray) -> float:
    """The RMS distance (m) of a board's points from their best line (a scan line: z = 0) or plane."""
    P = points[:, :2] if np.allclose(points[:, 2], 0.0) else points
    Q = P - P.mean(0)
    return float(np.sqrt(max(np.linalg.eigvalsh(Q.T @ Q / max(len(Q) - len(P[0]), 1))[0], 0.0)))


def crossings(points: np.ndarray, rings: np.ndarray, T_board_lidar: np.ndarray, board: BoardModel,
              beam_sd_rad: float = BEAM_SD_RAD, max_offset_m: float = MAX_END_OFFSET_M, position_sd_m: float = 0.0,
              ends: list | None = None) -> EdgeCrossings:
    """The ring ends of one frame's board points that cross the board's outline (module docstring), with
    sides assigned under ``T_board_lidar``; ends further than ``max_offset_m`` from their side are not used.
    ``beam_sd_rad`` and ``position_sd_m``: the ends' noise across the beam (:class:`EndNoise`); ``ends``: the
    points' :func:`ring_ends` when found already."""
    ends = ring_ends(points, rings) if ends is None else ends
    w, h = board.extent
    if not ends:
        return EdgeCrossings(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0))
    # Every end at once (this runs in every search for the ends).
    ring = np.array([e[0] for e in ends], dtype=np.int64)
    beam = np.array([e[1] for e in ends], dtype=float)
    step = np.array([e[2] for e in ends], dtype=float)
    q, s, Rb = cut_with_board(T_board_lidar, beam)
    # The cut's motion in the board's plane per radian of azimuth (the beam turning about the LiDAR's z).
    db = np.column_stack([-beam[:, 1], beam[:, 0], np.zeros(len(beam))]) * np.sign(step)[:, None]
    v = (db @ T_board_lidar[:3, :3].T) * s[:, None]
    rz = np.where(np.abs(Rb[:, 2]) < 1e-9, 1e-9, Rb[:, 2])  # a beam parallel to the board: cut far away
    dq = v - Rb * (v[:, 2] / rz)[:, None]  # projected along each beam onto the board's plane
    travel = dq[:, :2] / np.maximum(np.linalg.norm(dq[:, :2], axis=1), 1e-12)[:, None]
    cosines = travel @ SIDE_NORMALS.T  # (K, 4)
    # The side it leaves by: outward along its travel, the nearest such.
    offsets = q[:, :2] @ SIDE_NORMALS.T - np.array([0.0, w, 0.0, h])
    ok = cosines > MIN_CROSSING_SINE
    side = np.argmin(np.where(ok, np.abs(offsets), np.inf), axis=1)
    k = np.arange(len(side))
    along = np.where(side < 2, q[:, 1], q[:, 0])
    length = np.where(side < 2, h, w)
    keep = ((s > 0) & ok.any(axis=1) & (np.abs(offsets[k, side]) <= max_offset_m)
            & (CORNER_MARGIN_M < along) & (along < length - CORNER_MARGIN_M))
    rate = np.abs(np.einsum("ij,ij->i", SIDE_NORMALS[side], dq[:, :2]))  # m across the side per radian of azimuth
    wv = _outward_along_beams(side, Rb)
    across = ((s * beam_sd_rad) ** 2 + position_sd_m**2) * (np.einsum("ij,ij->i", wv, wv)
                                                           - np.einsum("ij,ij->i", wv, Rb) ** 2)
    sd = np.sqrt((rate * step) ** 2 / 12.0 + across)
    return EdgeCrossings(beam[keep].reshape(-1, 3), side[keep].astype(np.int64), ring[keep], sd[keep])


def _outward_along_beams(sides: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """``w = P^T a`` per end (K, 3): ``a`` its side's outward normal (board frame), ``P`` the projection along its
    beam ``Rb`` (board frame) onto the board's plane; ``w . dq`` moves the end outward for a cut moved by ``dq``."""
    a3 = np.column_stack([SIDE_NORMALS[sides], np.zeros(len(sides))])
    return a3 - np.outer(np.einsum("ij,ij->i", a3, Rb) / Rb[:, 2], [0.0, 0.0, 1.0])


def edge_residuals(T_camera_lidar: np.ndarray, T_camera_board: np.ndarray, edges: EdgeCrossings,
                   board: BoardModel, growth_m=(0.0, 0.0), shift_m=(0.0, 0.0), jacobian: bool = True,
                   deviation=None) -> tuple:
    """Each end's signed distance (m) outward of its side, less the edge growth of its sides (``growth_m``: of
    the x = 0, w and the y = 0, h sides) and the frame's outline shift (``shift_m``, board axes) (K,), and its
    Jacobians by the extrinsic (K, 6) and the board pose (K, 6) (the growth's and the shift's:
    :func:`nuisance_jacobians`). With the board's plane as the LiDAR sees it deviating from the camera's
    (``deviation``, :func:`deviation_prior`), the ends lie on that plane, and a fourth element is returned: the
    residuals' Jacobian by the deviation (K, 3)."""
    R_cb = T_camera_board[:3, :3]  # the board's pose inverted as a rigid motion (this runs in every solve)
    T_bl = np.eye(4)
    T_bl[:3, :3] = R_cb.T @ T_camera_lidar[:3, :3]
    T_bl[:3, 3] = R_cb.T @ (T_camera_lidar[:3, 3] - T_camera_board[:3, 3])
    q, s, Rb = cut_with_board(T_bl, edges.beams)
    a = SIDE_NORMALS[edges.sides]
    r = (a[:, 0] * (q[:, 0] - shift_m[0]) + a[:, 1] * (q[:, 1] - shift_m[1]) - side_offsets(board, edges.sides)
         - np.asarray(growth_m)[edges.sides // 2])
    w = _outward_along_beams(edges.sides, Rb) if jacobian or deviation is not None else None  # P^T a
    H_d = None
    if deviation is not None:
        # The end on the plane moved by delta along the board's z: its cut moves by delta Rb / Rb_z, outward by
        # delta (a . Rb_xy) / Rb_z = -delta w_z; delta = d + tilt . (q - the board's centre).
        c = 0.5 * np.asarray(board.extent, dtype=float)
        H_d = -w[:, 2:3] * np.column_stack([np.ones(len(r)), q[:, :2] - c])
        r = r + H_d @ np.asarray(deviation, dtype=float)
    if not jacobian:
        return (r, None, None) if H_d is None else (r, None, None, H_d)
    u = w @ T_bl[:3, :3]
    p = edges.beams * s[:, None]
    H_x = np.hstack([_cross(p, u), u])
    H_b = np.hstack([_cross(w, q), -w])
    return (r, H_x, H_b) if H_d is None else (r, H_x, H_b, H_d)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products (K, 3), without ``np.cross``'s overhead on small arrays."""
    return np.column_stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]])


def nuisance_jacobians(edges: EdgeCrossings) -> tuple[np.ndarray, np.ndarray]:
    """The residuals' Jacobians (K, 2) by the growth (x and y sides) and by the frame's outline shift (the
    outline's offset has the shift's)."""
    H_g = np.zeros((edges.size, 2))
    H_g[np.arange(edges.size), edges.sides // 2] = -1.0
    return H_g, -SIDE_NORMALS[edges.sides]


def end_loss(r: np.ndarray, sd: np.ndarray, k: float = EDGE_HUBER, hidden: float = HIDDEN_END_SHARE
             ) -> tuple[np.ndarray, np.ndarray]:
    """Each end's whitened residual ``e`` with ``e^2 / 2`` its negative log-likelihood (relative to an end on its
    side), and ``de / dr``, for outward distances ``r`` (m) with standard deviations ``sd`` (module docstring).

    Inward (``r < 0``), an end is its side's with share ``1 - hidden`` (Gaussian) or was hidden before the edge
    (a hand, a stand, a return lost) and lies anywhere up to ``MAX_END_OFFSET_M`` inside (uniform, share
    ``hidden``): the loss is bounded, and an end far inside stops pulling. Outward, a hidden end cannot lie, so
    the loss stays Gaussian out to ``k`` standard deviations and grows linearly beyond (Huber: a stray return
    beyond the board, or a footprint the growth does not hold)."""
    r, sd = np.broadcast_arrays(np.asarray(r, dtype=float), np.asarray(sd, dtype=float))
    z = r / sd
    e, de = np.empty_like(z), np.empty_like(z)
    out = z >= 0
    # Huber outward: rho = z^2 / 2 within k, k |z| - k^2 / 2 beyond.
    zo = z[out]
    far = zo > k
    e[out] = np.where(far, np.sqrt(np.maximum(2 * k * zo - k * k, 0.0)), zo)
    de[out] = np.where(far, k / np.maximum(e[out], 1e-300), 1.0) / sd[out]
    # Gaussian and uniform inward.
    zi, si = z[~out], sd[~out]
    log_u = np.log(hidden / MAX_END_OFFSET_M)
    log_g = np.log1p(-hidden) - 0.5 * zi**2 - np.log(si * np.sqrt(2 * np.pi))
    log_g0 = np.log1p(-hidden) - np.log(si * np.sqrt(2 * np.pi))
    log_mix = np.logaddexp(log_g, log_u)
    rho = np.maximum(np.logaddexp(log_g0, log_u) - log_mix, 0.0)
    resp = np.exp(log_g - log_mix)  # the share of the edge's component at this end
    ei = -np.sqrt(2 * rho)
    small = np.abs(ei) < 1e-8
    e[~out] = ei
    de[~out] = np.where(small, np.sqrt(resp), resp * zi / np.where(small, -1.0, ei)) / si
    return e, de


def _edge_error(edges, board, scale, keys, this, values, H):
    T = values.atPose3(keys[0]).matrix()
    Tb = values.atPose3(keys[1]).matrix()
    shift, outline = values.atVector(keys[2]), values.atVector(keys[3])
    deviation = values.atVector(keys[4]) if len(keys) > 4 else None
    r, H_x, H_b, *H_d = edge_residuals(T, Tb, edges, board, outline[:2], shift + outline[2:], H is not None,
                                       deviation)
    e, f = end_loss(r, scale * edges.sd_m)
    if H is not None:
        H_g, H_s = nuisance_jacobians(edges)
        H[0] = H_x * f[:, None]
        H[1] = H_b * f[:, None]
        H[2] = H_s * f[:, None]
        H[3] = np.hstack([H_g, H_s]) * f[:, None]
        if H_d:
            H[4] = H_d[0] * f[:, None]
    return e


def edge_factor(key_extrinsic: int, key_board: int, key_shift: int, edges: EdgeCrossings, board: BoardModel,
                scale: float, key_outline: int, key_deviation: int | None = None) -> gtsam.CustomFactor:
    """One frame's ends as a GTSAM factor on the extrinsic, the board pose, the frame's outline shift, the
    dataset's outline (``key_outline``) and, where the planes need a per-board plane error, the board's plane
    as the LiDAR sees it (``key_deviation``, :func:`deviation_prior`); whitened inside by :func:`end_loss`
    (``scale`` multiplies the ends' standard deviations)."""
    keys = [key_extrinsic, key_board, key_shift, key_outline] + ([] if key_deviation is None else [key_deviation])
    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(edges.size), keys,
                              partial(_edge_error, edges, board, scale, keys))


def deviation_prior(key: int, floor_m: float, half_m: float) -> gtsam.PriorFactorVector:
    """The board's plane as the LiDAR sees it against the camera's, for its ends: moved along the normal by
    ``d`` and tilted about the board's centre by ``(a, b)`` (the deviation at the board's point ``(x, y)`` from
    its centre is ``d + a x + b y``), under the per-board plane error the planes take (``floor_m`` along the
    normal, ``floor_m`` over the half-size ``half_m`` in tilt: ``noise_levels.plane_noise``). A board bent or
    held off its camera pose moves its ends along their beams, across its sides where the beams meet it
    obliquely: one error shared by a frame's ends, which without it would be read as many independent ones."""
    return gtsam.PriorFactorVector(key, np.zeros(3), gtsam.noiseModel.Diagonal.Sigmas(
        np.array([floor_m, floor_m / half_m, floor_m / half_m])))


def outline_prior(key: int) -> gtsam.PriorFactorVector:
    """The board's outline against the dataset's: its sides' growth (x and y sides) 0 +- ``GROWTH_PRIOR_SD_M``,
    the pattern's offset from where the dataset puts it 0 +- ``OFFSET_PRIOR_SD_M``."""
    return gtsam.PriorFactorVector(key, np.zeros(4), gtsam.noiseModel.Diagonal.Sigmas(outline_prior_sd()))


# Bound of the boards' in-plane scatter (m): a board's outline placed further off than this by the camera is not
# a pose error (a wrong board size or pattern offset, which the shift check reports).
MAX_EDGE_SCATTER_M = 0.05
# Fewest outline-shift directions (summed over frames) from which that scatter is estimated: the extrinsic's six
# directions absorb much of what a few boards' shifts show (3 scan lines give 3), and the scatter is then kept
# at its start.
MIN_SCATTER_RANK = 10


def edge_scatter(frames: list, board: BoardModel, outline: np.ndarray, scale: float, tau: float
                 ) -> tuple[float, float]:
    """The boards' in-plane scatter (m) and the ends' scale by the method of moments at a solve, over ``frames``
    (``(T_camera_lidar, T_camera_board, EdgeCrossings)`` each): each frame's outline shift by least squares on its
    ends' residuals (without the shift), its excess over the ends' own variance pooled over frames; the ends'
    scatter about their frame's shift against their standard deviations (those within twice the Huber threshold;
    never below 1). The scatter stays ``tau`` when the shifts show fewer than ``MIN_SCATTER_RANK`` directions."""
    excess, rank, within, dof = 0.0, 0, 0.0, 0
    for T, Tb, e in frames:
        shift, cov, k = frame_shift(T, Tb, e, board, outline, scale)
        excess += float(shift @ shift - np.trace(cov))
        rank += k
        r = edge_residuals(T, Tb, e, board, outline[:2], shift + outline[2:], jacobian=False)[0] / e.sd_m
        core = r[np.abs(r) <= 2 * EDGE_HUBER * scale]
        within += float(core @ core)
        dof += max(len(core) - k, 0)
    tau = (float(np.clip(np.sqrt(max(excess, 0.0) / max(rank, 1)), 1e-4, MAX_EDGE_SCATTER_M))
           if rank >= MIN_SCATTER_RANK else tau)
    new_scale = float(np.sqrt(within / dof)) if dof > 10 else 1.0
    return tau, max(1.0, new_scale)


def shift_prior(key_shift: int, sd_m: float) -> gtsam.PriorFactorVector:
    """The frame's outline shift: 0 +- the boards' in-plane scatter (the camera's board pose against the LiDAR's
    board, per board: a board that sways, a pose the corners place a little off, the board's real outline)."""
    return gtsam.PriorFactorVector(key_shift, np.zeros(2), gtsam.noiseModel.Isotropic.Sigma(2, max(sd_m, 1e-5)))


def frame_shift(T_camera_lidar: np.ndarray, T_camera_board: np.ndarray, edges: EdgeCrossings,
                board: BoardModel, outline=(0.0, 0.0, 0.0, 0.0), scale: float = 1.0
                ) -> tuple[np.ndarray, np.ndarray, int]:
    """The shift ``(dx, dy)`` (m, board axes) of the board's outline that the frame's ends call for under the
    estimate and the dataset's ``outline`` (its growth and offset), by weighted least squares over
    the ends (outward normals against residuals); its covariance (2x2) and the rank the sides give it (1 when
    every end crosses sides of one direction)."""
    outline = np.asarray(outline, dtype=float)
    r, _, _ = edge_residuals(T_camera_lidar, T_camera_board, edges, board, outline[:2], outline[2:], jacobian=False)
    sd = scale * edges.sd_m
    a = SIDE_NORMALS[edges.sides] / sd[:, None]
    info = a.T @ a
    rank = int(np.linalg.matrix_rank(info, tol=1e-9 * max(np.trace(info), 1e-300)))
    cov = np.linalg.pinv(info)
    return cov @ (a.T @ (r / sd)), cov, rank


@dataclass(frozen=True, eq=False)
class EndTerms:
    """A refinement's ends and their nuisances at its estimate, by frame name: the ends used, the frames' outline
    shifts (m, board axes), the dataset's outline and the scale of the ends' standard
    deviations."""

    edges: dict
    shifts: dict
    outline: np.ndarray
    scale: float

    def end_set(self, T_camera_lidar: np.ndarray, boards: dict, board: BoardModel,
                board_covariances: dict | None = None) -> "EndSet":
        """The ends of the frames in ``boards`` (name: ``T_camera_board``) as an :class:`EndSet`; each end's
        variance grows by its board pose's (``board_covariances``, name: 6x6, right tangent), carried to its
        residual at ``T_camera_lidar``."""
        beams, sides, sd, frame, Tb, shift = [], [], [], [], [], []
        for name, b in boards.items():
            e = self.edges.get(name)
            if e is None or e.size == 0:
                continue
            shift_k = np.asarray(self.shifts.get(name, np.zeros(2)), dtype=float)
            var = (self.scale * e.sd_m) ** 2
            if board_covariances is not None and name in board_covariances:
                _, _, H_b = edge_residuals(T_camera_lidar, b, e, board, self.outline[:2], shift_k + self.outline[2:])
                var = var + np.einsum("ij,jk,ik->i", H_b, board_covariances[name], H_b)
            beams.append(e.beams)
            sides.append(e.sides)
            sd.append(np.sqrt(var))
            frame.append(np.full(e.size, len(Tb)))
            Tb.append(np.linalg.inv(b))
            shift.append(np.tile(shift_k, (e.size, 1)))
        if not beams:
            raise ValueError("no frame with ends among the boards given")
        sides = np.concatenate(sides)
        return EndSet(np.vstack(beams), sides, np.concatenate(sd), np.concatenate(frame), np.array(Tb),
                      np.vstack(shift), side_offsets(board, sides))


@dataclass(frozen=True, eq=False)
class EndSet:
    """A 2D calibration's segment ends as the posterior evaluates them (:func:`end_set`): per end its mid-beam
    (LiDAR frame), its side, its standard deviation (m; the refinement's scaled one with the camera's board pose
    uncertainty added), its frame's board pose (``T_board_camera``, index ``frame``) and that frame's outline
    shift at the MAP (board axes)."""

    beams: np.ndarray  # (E, 3)
    sides: np.ndarray  # (E,)
    sd_m: np.ndarray  # (E,)
    frame: np.ndarray  # (E,) index into T_board_camera
    T_board_camera: np.ndarray  # (F, 4, 4)
    shift_m: np.ndarray  # (E, 2)
    offset_m: np.ndarray  # (E,) each side's offset (``side_offsets``)

    @property
    def size(self) -> int:
        return len(self.sides)

    def residuals(self, Ts: np.ndarray, outline: np.ndarray) -> np.ndarray:
        """Each end's outward distance (m) from its side (:func:`edge_residuals`) for (K, 4, 4) ``T_camera_lidar``
        and (K, 4) outlines (growth x, y; offset x, y): (K, E). A beam that misses the board's plane (it cuts it
        behind the LiDAR) lies 1 m outward."""
        Tb = self.T_board_camera[self.frame]  # (E, 4, 4)
        Rb = Tb[:, :3, :3]
        # Each beam and the LiDAR's origin in the board's frame, R_board_camera (R_camera_lidar beam) per (K, E): the
        # walkers' rotations first (one batched product), then each end's board.
        u = np.matmul(Ts[:, :3, :3], self.beams.T).transpose(0, 2, 1)  # (K, E, 3)
        d = np.matmul(Rb[None], u[..., None])[..., 0]
        t = np.tensordot(Ts[:, :3, 3], Rb, axes=([1], [2])) + Tb[None, :, :3, 3]
        dz = np.where(np.abs(d[..., 2]) < 1e-9, 1e-9, d[..., 2])
        s = -t[..., 2] / dz
        q = t[..., :2] + s[..., None] * d[..., :2]
        r = (np.einsum("ej,kej->ke", SIDE_NORMALS[self.sides], q - self.shift_m[None] - outline[:, None, 2:])
             - self.offset_m - outline[:, self.sides // 2])
        return np.where(s > 0, r, 1.0)

    def log_likelihood(self, Ts: np.ndarray, outline: np.ndarray) -> np.ndarray:
        """The ends' log-likelihood (:func:`end_loss`, relative to every end on its side), (K,)."""
        e, _ = end_loss(self.residuals(Ts, outline), np.broadcast_to(self.sd_m, (len(Ts), self.size)))
        return -0.5 * np.sum(e * e, axis=1)


def outline_prior_sd() -> np.ndarray:
    """The standard deviations of the outline's prior: growth of the x and y sides, offset along x and y (m)."""
    return np.array([GROWTH_PRIOR_SD_M, GROWTH_PRIOR_SD_M, OFFSET_PRIOR_SD_M, OFFSET_PRIOR_SD_M])

"""Each return's beam recovered from its elevation, for a sweep whose file holds no beam index (a KITTI-style
``.bin``, an unorganised PCD without a ``ring`` field).

A spinning LiDAR's lasers sit at fixed elevations, and a return lies on its laser's ray whatever its range error:
seen from the beams' own origin, a sweep's returns fall into narrow bands of elevation, one a laser. The points'
origin may lie off the beams': an Ouster's sensor frame lies 36 mm below its lidar frame, and its beams leave from
16 mm off the spin axis. Seen from the points' origin a beam's elevation then drifts with range (by ``h cos(el) /
rho``: 0.9 degrees at 2 m, more than its 64 beams' spacing), so the beams' origin comes first: its height ``h``
above the points' origin and its distance ``a`` from the spin axis. The grid of ``HEIGHTS_M`` and ``RADII_M``
gives those that gather the elevations ``atan2(z - h, rho - a)`` tightest (the largest sum of squared counts of
their histogram in ``BIN_DEG`` bins: the height, the radius, then each again finer); least squares on the returns
then given a beam refines them. On the recorded Ouster set they are 36 and 16 mm, and each of its 64 beams then
lies within 0.002 degrees RMS of its band's centre, against their 0.65 degree spacing.

The bands are the runs of the histogram's bins that hold returns beyond ``MIN_RHO_M`` from the spin axis (near
returns drift with the origins' horizontal offsets); each return is given the band whose centre lies within
``ASSIGN_SHARE`` of the spacing to its neighbours, or none (``-1``; the scene's contours leave it out). Refused (a
:class:`ScanReadError`) where the elevations do not gather into bands: a rosette or solid-state LiDAR's, a sweep
turned in its file so that z is not its spin axis, or too few returns.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ScanReadError

BIN_DEG = 0.02
# The beams' origin's height above the points' and distance from the spin axis (m) tried, then a finer grid about
# each's best.
HEIGHTS_M = np.arange(-0.15, 0.1501, 0.005)
RADII_M = np.arange(-0.05, 0.0801, 0.005)
FINE_STEP_M = 0.0005
# Returns this far from the spin axis (m) or more find the bands; nearer ones drift with the origins' offsets.
MIN_RHO_M = 2.0
# Returns used to find the height (every k-th of those beyond MIN_RHO_M).
HEIGHT_SAMPLE = 10000
# Least-squares steps of the beams' origin on the returns given a beam (after the grid's).
ORIGIN_ITERATIONS = 2
# A return is its band's within this share of the spacing to the nearest other band.
ASSIGN_SHARE = 0.3
# A band: its central 95% of returns spans at most this share of the spacing to its nearest neighbour.
MAX_BAND_SHARE = 0.5
# Far returns that must fall in bands, and the fewest returns a sweep must have beyond MIN_RHO_M.
MIN_IN_BANDS = 0.9
MIN_RETURNS = 500
# Returns from all of one LiDAR's sweeps its beams are found from together (:func:`sweeps_beams`).
JOINT_SAMPLE = 200000
FIX = "write the sweeps with a ring field (PCD or PLY) or as organised clouds"


@dataclass(frozen=True, eq=False)
class BeamRings:
    """Each return's beam (``ring``: 0 the lowest band, -1 none) and how they were found: the beams' origin's height
    above the points' (``height_m``) and distance from the spin axis (``radius_m``), and each band's elevation seen
    from there (``elevations_deg``)."""

    ring: np.ndarray
    height_m: float
    radius_m: float
    elevations_deg: np.ndarray

    def rings_of(self, points: np.ndarray) -> np.ndarray:
        """Other returns of the same LiDAR given these beams (another sweep's: -1 where none)."""
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        return _assign(_elevations(points, self.height_m, self.radius_m), self.elevations_deg,
                       _spacing(self.elevations_deg))


def sweeps_beams(sweeps: list[np.ndarray]) -> BeamRings:
    """The beams of one LiDAR's sweeps, found over them all (up to ``JOINT_SAMPLE`` returns, an equal share from
    each): every sweep's returns then take their beams from one set (:meth:`BeamRings.rings_of`), numbered alike
    across sweeps, even where a sweep holds no far return of some laser (a near wall) or too few to find its own."""
    share = max(1, JOINT_SAMPLE // max(len(sweeps), 1))
    sample = np.concatenate([np.asarray(p, dtype=float).reshape(-1, 3)[:: max(1, len(p) // share)] for p in sweeps])
    return beam_rings(sample)


def _elevations(points: np.ndarray, h: float, a: float) -> np.ndarray:
    return np.degrees(np.arctan2(points[:, 2] - h, np.hypot(points[:, 0], points[:, 1]) - a))


def _bins(el_deg: np.ndarray) -> np.ndarray:
    return np.floor((el_deg + 90.0) / BIN_DEG).astype(np.int64)


def _sharpness(points: np.ndarray, h: float, a: float) -> float:
    counts = np.bincount(_bins(_elevations(points, h, a)))
    return float(np.sum(counts.astype(float) ** 2))


def _origin(far: np.ndarray) -> tuple[float, float]:
    """The beams' origin (height above the points', distance from the spin axis) that gathers the elevations
    tightest: the height, the radius, then each again on a finer grid about it."""
    sample = far[:: max(1, len(far) // HEIGHT_SAMPLE)]
    h = max(HEIGHTS_M, key=lambda v: _sharpness(sample, v, 0.0))
    a = max(RADII_M, key=lambda v: _sharpness(sample, h, v))
    h = max(np.arange(h - 0.005, h + 0.0051, FINE_STEP_M), key=lambda v: _sharpness(sample, v, a))
    a = max(np.arange(a - 0.005, a + 0.0051, FINE_STEP_M), key=lambda v: _sharpness(sample, h, v))
    return float(h), float(a)


def _runs(occupied: np.ndarray) -> list[tuple[int, int]]:
    """The runs ``(first, last)`` of the occupied bins (sorted), two runs joined where the free bins between them are
    fewer than the wider one spans: a beam's sparse tail leaves free bins within its band, and bands lie farther
    apart than they are wide."""
    starts = np.concatenate([[0], np.flatnonzero(np.diff(occupied) > 1) + 1])
    runs = [[int(occupied[s]), int(occupied[e - 1])] for s, e in zip(starts, np.append(starts[1:], len(occupied)))]
    out = [runs[0]]
    for lo, hi in runs[1:]:
        last = out[-1]
        if lo - last[1] - 1 < max(last[1] - last[0] + 1, hi - lo + 1):
            last[1] = hi
        else:
            out.append([lo, hi])
    return [(lo, hi) for lo, hi in out]


def beam_rings(points: np.ndarray, path=None) -> BeamRings:
    """Each return's beam from its elevation (module docstring); ``path`` names the file in a refusal."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    rho = np.hypot(points[:, 0], points[:, 1])
    far = points[rho >= MIN_RHO_M]
    if len(far) < MIN_RETURNS:
        raise ScanReadError(f"the sweep has no beam index and only {len(far)} returns beyond {MIN_RHO_M:g} m of its "
                            "spin axis to find its beams from", path=path, hint=FIX)
    h, a = _origin(far)
    el_far = np.sort(_elevations(far, h, a))
    bins = _bins(el_far)
    centres, spans, held = [], [], 0
    for lo, hi in _runs(np.unique(bins)):
        i, j = np.searchsorted(bins, lo, "left"), np.searchsorted(bins, hi, "right")
        if j - i < 3:  # a stray return or two between bands
            continue
        band = el_far[i:j]
        centres.append(float(np.median(band)))
        spans.append(float(np.percentile(band, 97.5) - np.percentile(band, 2.5)))
        held += j - i
    centres, spans = np.asarray(centres), np.asarray(spans)
    spacing = _spacing(centres)
    if len(centres) < 2 or held < MIN_IN_BANDS * len(el_far) or np.any(spans > MAX_BAND_SHARE * spacing):
        widest = f", the widest {np.max(spans / spacing):.0%} of its spacing" if len(centres) >= 2 else ""
        raise ScanReadError(f"the sweep has no beam index and its returns' elevations do not fall into separate beams "
                            f"({held / len(el_far):.0%} in {len(centres)} bands{widest}: a LiDAR without rings, or z "
                            "is not its spin axis)", path=path, hint=FIX)
    ring = _assign(_elevations(points, h, a), centres, spacing)
    # The origin's least squares on the returns given a beam (each band's elevation free), then the bands again.
    for _ in range(ORIGIN_ITERATIONS):
        h, a = _fit_origin(points, ring, h, a)
        el = _elevations(points, h, a)
        centres = _band_medians(el[rho >= MIN_RHO_M], ring[rho >= MIN_RHO_M], centres)
        ring = _assign(el, centres, spacing)
    return BeamRings(ring, h, a, centres)


def _spacing(centres: np.ndarray) -> np.ndarray:
    """Each band's distance to its nearest neighbour band."""
    gaps = np.diff(centres)
    return np.minimum(np.append(gaps, np.inf), np.insert(gaps, 0, np.inf))


def _band_medians(el: np.ndarray, ring: np.ndarray, before: np.ndarray) -> np.ndarray:
    """Each band's median elevation over its returns (``before``'s where it has none)."""
    out = before.copy()
    order = np.lexsort((el, ring))
    el, ring = el[order], ring[order]
    bounds = np.searchsorted(ring, np.arange(len(before) + 1))
    for k in range(len(before)):
        i, j = bounds[k], bounds[k + 1]
        if j > i:
            out[k] = 0.5 * (el[i + (j - i - 1) // 2] + el[i + (j - i) // 2])
    return out


def _assign(el: np.ndarray, centres: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """Each elevation's band: the nearest centre, within ``ASSIGN_SHARE`` of that band's spacing; else -1."""
    k = np.clip(np.searchsorted(centres, el), 1, len(centres) - 1)
    nearest = np.where(np.abs(el - centres[k - 1]) <= np.abs(el - centres[k]), k - 1, k)
    return np.where(np.abs(el - centres[nearest]) <= ASSIGN_SHARE * spacing[nearest], nearest, -1).astype(np.int64)


def _fit_origin(points: np.ndarray, ring: np.ndarray, h: float, a: float) -> tuple[float, float]:
    """One Gauss-Newton step of the beams' origin: the elevations of each band's returns made equal, the band's own
    elevation eliminated (each column less its band's mean)."""
    given = ring >= 0
    p, k = points[given], ring[given]
    rho = np.hypot(p[:, 0], p[:, 1]) - a
    z = p[:, 2] - h
    r2 = rho ** 2 + z ** 2
    counts = np.bincount(k).astype(float)
    counts[counts == 0] = 1.0

    def centred(x):
        return x - (np.bincount(k, x, minlength=len(counts)) / counts)[k]

    J = np.column_stack([centred(-rho / r2), centred(z / r2)])  # d elevation / d h, d a
    step = np.linalg.lstsq(J, -centred(np.arctan2(z, rho)), rcond=None)[0]
    return float(h + step[0]), float(a + step[1])

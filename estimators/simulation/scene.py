"""A simulated scene of planar pieces (board, stand, ground, walls) and exact ray casting against it."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass(frozen=True, eq=False)
class Patch:
    """A planar piece: ``normal . x = distance``, optionally bounded to the rectangle
    ``origin + a u + b v`` with ``0 <= a <= width``, ``0 <= b <= height``.

    ``reflectance`` is a constant or a function of the rectangle coordinates ``(a, b)``.
    """

    normal: np.ndarray
    distance: float
    reflectance: float | Callable[[np.ndarray, np.ndarray], np.ndarray]
    origin: np.ndarray | None = None
    u: np.ndarray | None = None
    v: np.ndarray | None = None
    width: float = np.inf
    height: float = np.inf
    label: str = ""


def rectangle(origin, u, v, width, height, reflectance, label="") -> Patch:
    u = np.asarray(u, float) / np.linalg.norm(u)
    v = np.asarray(v, float) / np.linalg.norm(v)
    n = np.cross(u, v)
    n /= np.linalg.norm(n)
    origin = np.asarray(origin, float)
    return Patch(n, float(n @ origin), reflectance, origin, u, v, float(width), float(height), label)


def infinite_plane(normal, distance, reflectance, label="") -> Patch:
    n = np.asarray(normal, float)
    return Patch(n / np.linalg.norm(n), float(distance) / np.linalg.norm(n), reflectance, label=label)


def cast(origin: np.ndarray, dirs: np.ndarray, patches: list[Patch], max_range: float = np.inf
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest hit of rays ``origin + s dirs`` (unit dirs): range (inf if none), patch index (-1), reflectance."""
    origin = np.asarray(origin, float)
    n_rays = len(dirs)
    best = np.full(n_rays, np.inf)
    which = np.full(n_rays, -1)
    refl = np.full(n_rays, np.nan)
    for k, p in enumerate(patches):
        denom = dirs @ p.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (p.distance - origin @ p.normal) / denom
        ok = np.isfinite(s) & (s > 1e-6) & (s < best) & (s <= max_range)
        if not ok.any():
            continue
        idx = np.nonzero(ok)[0]
        if p.origin is not None:
            hit = origin + s[idx, None] * dirs[idx]
            rel = hit - p.origin
            a, b = rel @ p.u, rel @ p.v
            inside = (a >= 0) & (a <= p.width) & (b >= 0) & (b <= p.height)
            idx, a, b = idx[inside], a[inside], b[inside]
        else:
            a = b = None
        best[idx] = s[idx]
        which[idx] = k
        refl[idx] = p.reflectance(a, b) if callable(p.reflectance) else p.reflectance
    return best, which, refl

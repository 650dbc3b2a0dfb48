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


def _cone(origin: np.ndarray, p: Patch) -> tuple[np.ndarray, float]:
    """Axis and half-angle of a cone from ``origin`` that holds the bounded patch ``p``."""
    corners = np.array([p.origin, p.origin + p.width * p.u, p.origin + p.height * p.v,
                        p.origin + p.width * p.u + p.height * p.v]) - origin
    centre = corners.mean(0)
    norm = np.linalg.norm(centre)
    if norm < 1e-9:
        return np.array([1.0, 0.0, 0.0]), np.pi
    axis = centre / norm
    cos = (corners @ axis) / np.maximum(np.linalg.norm(corners, axis=1), 1e-12)
    # A convex quad lies in the cone of its corners (their angular hull) only when seen from in front of its
    # plane at some distance; pad, and give up (whole sphere) when the origin is close to the patch.
    half = float(np.arccos(np.clip(cos.min(), -1.0, 1.0)))
    if norm < 0.5 * np.hypot(p.width, p.height):
        return axis, np.pi
    return axis, min(half + 1e-3, np.pi)


@dataclass(frozen=True, eq=False)
class Background:
    """The cast of one bundle of rays (``dirs``) from one origin against the static part of a scene: the
    patches that end every frame's list (ground, walls, furniture). Frames that only move the board cast just
    their own patches and lay them over it (:func:`cast` with ``background``)."""

    dirs: np.ndarray
    n_patches: int
    ranges: np.ndarray
    which: np.ndarray
    refl: np.ndarray


def cast_background(origin: np.ndarray, dirs: np.ndarray, static: list[Patch], max_range: float = np.inf
                    ) -> Background:
    return Background(dirs, len(static), *cast(origin, dirs, static, max_range))


def cast(origin: np.ndarray, dirs: np.ndarray, patches: list[Patch], max_range: float = np.inf,
         background: Background | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest hit of rays ``origin + s dirs`` (unit dirs): range (inf if none), patch index (-1), reflectance.

    A bounded patch is tested only against the rays inside the cone that holds it (and skipped when that cone
    misses the bundle of rays altogether): the same hits, far fewer intersections in a cluttered scene.
    ``background``: the cast of these rays (same origin and ``max_range``) against the last
    ``background.n_patches`` of ``patches``, which are then not cast again; the others are cast only on the
    rays inside their cones. The result is the same: an earlier patch keeps a tie, as in a single pass."""
    if background is not None:
        if background.dirs is not dirs or background.n_patches > len(patches):
            raise ValueError("the background was cast for other rays or another scene")
        n_own = len(patches) - background.n_patches
        ranges = background.ranges.copy()
        which = np.where(background.which >= 0, background.which + n_own, -1)
        refl = background.refl.copy()
        rays = np.zeros(len(dirs), bool)
        for p in patches[:n_own]:
            axis, half = _cone(origin, p) if p.origin is not None else (None, np.pi)
            if half >= np.pi:
                rays[:] = True
                break
            rays |= dirs @ axis >= np.cos(half)
        rays = np.flatnonzero(rays)
        best, own, own_refl = cast(origin, dirs[rays], patches[:n_own], max_range)
        front = best <= ranges[rays]  # the frame's own patches come first: they keep a tie
        front &= own >= 0
        rays, best, own, own_refl = rays[front], best[front], own[front], own_refl[front]
        ranges[rays], which[rays], refl[rays] = best, own, own_refl
        return ranges, which, refl
    origin = np.asarray(origin, float)
    n_rays = len(dirs)
    best = np.full(n_rays, np.inf)
    which = np.full(n_rays, -1)
    refl = np.full(n_rays, np.nan)
    # the bundle's mean direction by a product (numpy's mean down the columns of an (N, 3) array is ten times
    # slower); any axis serves, as the skip below measures the bundle's spread about this same axis
    bundle_axis = np.ones(n_rays) @ dirs / n_rays if n_rays else np.zeros(3)
    spread = np.pi
    if np.linalg.norm(bundle_axis) > 0.5:
        bundle_axis = bundle_axis / np.linalg.norm(bundle_axis)
        spread = float(np.arccos(np.clip((dirs @ bundle_axis).min(), -1.0, 1.0)))
    for k, p in enumerate(patches):
        rays = None  # every ray (no index: the full arrays are used as they are)
        if p.origin is not None:
            axis, half = _cone(origin, p)
            if half < np.pi:
                if np.arccos(np.clip(axis @ bundle_axis, -1.0, 1.0)) > half + spread + 1e-6 and spread < np.pi:
                    continue
                rays = np.nonzero(dirs @ axis >= np.cos(half))[0]
                if len(rays) == 0:
                    continue
                if len(rays) == n_rays:  # the cone holds every ray: no copies of the arrays by index
                    rays = None
        # a cone holding many of the rays: every ray's product, then the cone's (cheaper than gathering the rays)
        denom = dirs @ p.normal if rays is None else \
            (dirs @ p.normal)[rays] if 4 * len(rays) > n_rays else dirs[rays] @ p.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (p.distance - origin @ p.normal) / denom
        ok = np.isfinite(s) & (s > 1e-6) & (s < (best if rays is None else best[rays])) & (s <= max_range)
        sel = np.flatnonzero(ok)
        if len(sel) == 0:
            continue
        idx, s = (sel if rays is None else rays[sel]), s[sel]
        if p.origin is not None:
            rel = dirs[idx]  # the hit less the patch's origin, in place: the same sums, no temporaries
            rel *= s[:, None]
            rel += origin
            rel -= p.origin
            a, b = rel @ p.u, rel @ p.v
            inside = (a >= 0) & (a <= p.width) & (b >= 0) & (b <= p.height)
            idx, s, a, b = idx[inside], s[inside], a[inside], b[inside]
        else:
            a = b = None
        best[idx] = s
        which[idx] = k
        refl[idx] = p.reflectance(a, b) if callable(p.reflectance) else p.reflectance
    return best, which, refl

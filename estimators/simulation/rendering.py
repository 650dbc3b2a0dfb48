"""Rendering anti-aliased camera images of a simulated scene through a distorted camera model."""
from __future__ import annotations

import threading
from concurrent.futures import Executor

import cv2
import numpy as np

from geometry.camera import CameraModel
from geometry.rotations import transform_points
from geometry.vectors import row_norms

from .scene import Background, Patch, cast

_GRID_CACHE: dict[tuple, np.ndarray] = {}
# About a dozen 1280 x 960 cameras' grids, or a 4K camera's and a few more (the last one is always kept).
_GRID_CACHE_BYTES = 256 * 2**20
_GRID_LOCK = threading.Lock()  # frames are rendered on several threads
_PARTS = 4  # blocks of rows for a pool's threads (fixed: the result never depends on the pool)
SKY_REFLECTANCE = 0.85


def _in_parts(f, rows: np.ndarray, pool: Executor | None) -> np.ndarray:
    """``f`` of ``rows`` (row by row independent) in ``_PARTS`` blocks of rows, on the threads of ``pool``
    (OpenCV and numpy release the interpreter) or here: always the same blocks, so that not even a BLAS
    kernel's handling of a block's last rows can make the result depend on the pool."""
    parts = np.array_split(rows, _PARTS)
    return np.concatenate(list(map(f, parts) if pool is None else pool.map(f, parts)))


def _normalized_grid(camera: CameraModel, pool: Executor | None = None) -> np.ndarray:
    """Undistorted normalized coordinates of every pixel centre, (H+1, W+1, 2) (one extra row/column); kept for
    the cameras rendered last, up to ``_GRID_CACHE_BYTES`` in all (a rig renders its cameras in turn, frame by
    frame: keeping only the last camera's grid undistorted every pixel again for each camera of each frame)."""
    key = (camera.model, camera.K.tobytes(), camera.dist.tobytes(), camera.width, camera.height)
    with _GRID_LOCK:
        if key in _GRID_CACHE:
            _GRID_CACHE[key] = _GRID_CACHE.pop(key)  # the most recently used last
            return _GRID_CACHE[key]
    u, v = np.meshgrid(np.arange(camera.width + 1, dtype=float), np.arange(camera.height + 1, dtype=float))
    xy = _in_parts(camera.normalized_from_pixels, np.column_stack([u.ravel(), v.ravel()]), pool)
    grid = xy.reshape(camera.height + 1, camera.width + 1, 2)
    with _GRID_LOCK:
        _GRID_CACHE.pop(key, None)
        while _GRID_CACHE and sum(g.nbytes for g in _GRID_CACHE.values()) + grid.nbytes > _GRID_CACHE_BYTES:
            _GRID_CACHE.pop(next(iter(_GRID_CACHE)))
        _GRID_CACHE[key] = grid
    return grid


def _interp(grid: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of the normalized-coordinate grid at fractional pixels (distortion is smooth)."""
    u0 = np.clip(np.floor(u).astype(int), 0, grid.shape[1] - 2)
    v0 = np.clip(np.floor(v).astype(int), 0, grid.shape[0] - 2)
    fu, fv = (u - u0)[:, None], (v - v0)[:, None]
    flat, k = grid.reshape(-1, 2), v0 * grid.shape[1] + u0  # one flat index: cheaper than 2D fancy indexing
    below = k + grid.shape[1]
    return ((1 - fu) * (1 - fv) * flat[k] + fu * (1 - fv) * flat[k + 1]
            + (1 - fu) * fv * flat[below] + fu * fv * flat[below + 1])


def _interp_subpixels(grid: np.ndarray, pu: np.ndarray, pv: np.ndarray, offs: np.ndarray) -> np.ndarray:
    """:func:`_interp` at every sub-pixel ``(pu + offs[j], pv + offs[i])`` of the pixels ``(pu, pv)``, pixel by
    pixel and ``i`` by ``j`` within it, as one (N S^2, 2) array: the same values, bit for bit. Away from the
    grid's edges, each sub-pixel's four grid points and weights are the same for every pixel,
    so each neighbour is gathered once per pixel rather than once per sub-pixel. (That holds when every
    offset is a multiple of 1/1024: ``pu + o - floor(pu + o)`` is then ``o - floor(o)`` exactly.)"""
    S = len(offs)
    ou, ov = np.meshgrid(offs, offs)

    def general(pu: np.ndarray, pv: np.ndarray) -> np.ndarray:
        return _interp(grid, (pu[:, None] + ou.ravel()[None, :]).ravel(),
                       (pv[:, None] + ov.ravel()[None, :]).ravel())

    if not np.all(offs * 1024 == np.round(offs * 1024)):
        return general(pu, pv)
    out = np.empty((len(pu), S * S, 2))
    floor = np.floor(offs).astype(int)
    inner = (pu + floor.min() >= 0) & (pv + floor.min() >= 0) & (pu + floor.max() <= grid.shape[1] - 2) \
        & (pv + floor.max() <= grid.shape[0] - 2)
    flat, width = grid.reshape(-1, 2), grid.shape[1]
    k = pv[inner] * width + pu[inner]
    near: dict[int, np.ndarray] = {}

    def at(step: int) -> np.ndarray:
        if step not in near:
            near[step] = flat[k + step]
        return near[step]

    for i, (dv, fv) in enumerate(zip(floor, offs - floor)):
        for j, (du, fu) in enumerate(zip(floor, offs - floor)):
            corner = dv * width + du
            out[inner, i * S + j] = ((1 - fu) * (1 - fv) * at(corner) + fu * (1 - fv) * at(corner + 1)
                                     + (1 - fu) * fv * at(corner + width) + fu * fv * at(corner + width + 1))
    if not inner.all():
        out[~inner] = general(pu[~inner], pv[~inner]).reshape(-1, S * S, 2)
    return out.reshape(-1, 2)


def _rays_world(xy: np.ndarray, T_world_camera: np.ndarray) -> np.ndarray:
    """Unit rays in the world frame through normalized coordinates ``xy`` (N, 2)."""
    d = np.column_stack([xy, np.ones(len(xy))])
    d /= row_norms(d)[:, None]
    return d @ T_world_camera[:3, :3].T


def render_image(camera: CameraModel, T_world_camera: np.ndarray, patches: list[Patch], board_index: int,
                 board_outline_world: np.ndarray, rng: np.random.Generator, supersample: int = 4,
                 pixel_noise: float = 2.0, blur_sigma_px: float = 0.5) -> np.ndarray:
    """An 8-bit greyscale image: :func:`render_clean`, then Gaussian pixel noise (:func:`add_pixel_noise`)."""
    clean = render_clean(camera, T_world_camera, patches, board_index, board_outline_world, supersample,
                         blur_sigma_px)
    return add_pixel_noise(clean, rng, pixel_noise)


def add_pixel_noise(clean: np.ndarray, rng: np.random.Generator, pixel_noise: float = 2.0) -> np.ndarray:
    """A noise-free rendering as an 8-bit image with Gaussian pixel noise of ``pixel_noise`` grey levels."""
    img = clean + rng.normal(0.0, pixel_noise, clean.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _may_hide(origin: np.ndarray, patch: Patch, board_outline: np.ndarray, margin_m: float = 1e-6) -> bool:
    """Whether ``patch`` could lie between ``origin`` and the board (its outline's corners): not when the
    origin and every corner lie on the same side of the patch's plane (by ``margin_m``), since the segment
    from the origin to any point of the (convex) board then stays on that side."""
    side = board_outline @ patch.normal - patch.distance
    own = float(origin @ patch.normal - patch.distance)
    return not (abs(own) > margin_m and np.all(side * np.sign(own) > margin_m))


def pixel_rays(camera: CameraModel, T_world_camera: np.ndarray, pool: Executor | None = None) -> np.ndarray:
    """Unit rays in the world frame through every pixel centre, row by row: (H W, 3); ``pool``: threads
    that share the work (the same rays)."""
    grid = _normalized_grid(camera, pool)[:camera.height, :camera.width].reshape(-1, 2)
    return _in_parts(lambda xy: _rays_world(xy, T_world_camera), grid, pool)


def edge_pixels(which: np.ndarray, refl: np.ndarray, reach: int, step: float = 0.0) -> np.ndarray:
    """The pixels (H, W bool) within ``reach`` pixels of a change between neighbouring pixel centres: another
    patch seen (``which``), or a reflectance more than ``step`` apart (``refl``, finite). A pixel's rays all see
    what its centre sees elsewhere, so only these need supersampling."""
    change = np.zeros(which.shape, np.uint8)
    change[:, 1:] |= (which[:, 1:] != which[:, :-1]) | (np.abs(refl[:, 1:] - refl[:, :-1]) > step)
    change[1:, :] |= (which[1:, :] != which[:-1, :]) | (np.abs(refl[1:, :] - refl[:-1, :]) > step)
    k = 2 * reach + 1
    return cv2.dilate(change, np.ones((k, k), np.uint8)) > 0


def render_clean(camera: CameraModel, T_world_camera: np.ndarray, patches: list[Patch], board_index: int,
                 board_outline_world: np.ndarray, supersample: int = 4, blur_sigma_px: float = 0.5,
                 background: Background | None = None) -> np.ndarray:
    """The noise-free image (grey levels, float): one ray per pixel for the scene, ``supersample^2`` rays per
    pixel over the board's edges (anti-aliased squares), then optical blur. It draws no random numbers, so
    frames can be rendered in parallel and their noise added in order. ``background``: the static scene's cast
    of this camera's :func:`pixel_rays` (``scene.cast_background``), reused across frames."""
    grid = _normalized_grid(camera)
    H, W = camera.height, camera.width
    origin = T_world_camera[:3, 3]
    rays = pixel_rays(camera, T_world_camera) if background is None else background.dirs
    _, which, refl = cast(origin, rays, patches, background=background)
    refl = np.where(np.isnan(refl), SKY_REFLECTANCE, refl).reshape(H, W)
    which = which.reshape(H, W)

    # Anti-aliasing over the board: average supersample x supersample rays inside each pixel, where that can
    # change the pixel. A pixel's rays all see what its centre sees unless an edge (of a square, or of the
    # board) passes within the pixel, and then a neighbour's centre lies across it: only pixels within two
    # of such a change (a margin for the squares' corners) are supersampled.
    T_camera_world = np.linalg.inv(T_world_camera)
    uv = camera.project(transform_points(T_camera_world, board_outline_world))
    uv = uv[np.all(np.isfinite(uv), axis=1)]  # a board behind the camera (a rig's other cameras) projects nowhere
    uv = np.clip(uv, -1e6, 1e6)  # nearly behind a fisheye: far outside the image, and no integer overflow
    if len(uv):
        u_lo, v_lo = np.floor(uv.min(axis=0)).astype(int) - 2
        u_hi, v_hi = np.ceil(uv.max(axis=0)).astype(int) + 2
        u_lo, v_lo, u_hi, v_hi = max(u_lo, 0), max(v_lo, 0), min(u_hi, W - 1), min(v_hi, H - 1)
    else:
        u_lo = v_lo = u_hi = v_hi = 0
    if u_hi > u_lo and v_hi > v_lo:
        box = (slice(v_lo, v_hi + 1), slice(u_lo, u_hi + 1))
        w_box = which[box]
        near = edge_pixels(w_box, refl[box], 2)
        near &= cv2.dilate((w_box == board_index).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        pv, pu = np.nonzero(near)
        pv, pu = pv + v_lo, pu + u_lo
        offs = (np.arange(supersample) + 0.5) / supersample - 0.5
        dirs = _rays_world(_interp_subpixels(grid, pu, pv, offs), T_world_camera)
        if background is None:
            _, hit, r_sub = cast(origin, dirs, patches)
        else:  # the frame's own patches, then the static pieces that could hide the board, where they could
            n_own = len(patches) - background.n_patches
            s_own, hit, r_sub = cast(origin, dirs, patches[:n_own])
            hiding = [q for q in patches[n_own:] if _may_hide(origin, q, board_outline_world)]
            if hiding:
                on = np.flatnonzero(hit == board_index)
                s_static = cast(origin, dirs[on], hiding)[0]
                hit[on[s_static < s_own[on]]] = -1
        base = np.repeat(refl[pv, pu], supersample * supersample)
        r_sub = np.where(hit == board_index, r_sub, base)
        refl[pv, pu] = r_sub.reshape(-1, supersample * supersample).mean(1)

    img = 20.0 + 210.0 * refl
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
    return img

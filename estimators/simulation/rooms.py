"""Furnished rooms drawn at random: their pieces (walls, windows, doors, posters, free-standing furniture) as
planar patches, each face shaded by its turn to a light above the room.

A room (6-11 x 5-9 m) holds what such rooms hold: desks with monitors (black screens), shelves and cabinets,
chairs, sofas, boxes on the floor, pillars and thin plant stands; posters and pictures with printed texture,
doors in proud frames, windows (``GLASS``: the LiDAR's beams pass it); materials from dark (0.04) to bright (0.9).
Two scenes are made of them: the scene check's own (``furnished_room``: the rig carried through the room, no
board) and a board scene's static room about a still rig (:func:`room_around_rig`, ``simulate_dataset(
scene="furnished")``), its furniture kept off the lines of sight to the boards.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geometry.rotations import R_from_rotvec, T_from_Rt

from .scene import Patch, infinite_plane, rectangle

LIGHT = np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0])  # the room's light, from above
GLASS = "glass"


def _shade(reflectance, normal: np.ndarray):
    """A face's appearance: its material darkened by its turn away from the light (0.55-1.0 of the albedo)."""
    k = 0.55 + 0.45 * abs(float(np.asarray(normal) @ LIGHT))
    if callable(reflectance):
        return lambda a, b: k * reflectance(a, b)
    return k * reflectance


def _texture(rng: np.random.Generator):
    """A printed surface (poster, picture, rug): random blocks, stripes or a plain tint, as a function of the
    rectangle's coordinates (m)."""
    kind = rng.integers(3)
    base, amp = rng.uniform(0.25, 0.7), rng.uniform(0.1, 0.25)
    if kind == 0:
        cells = rng.uniform(0.05, 0.2)
        table = rng.uniform(-1.0, 1.0, (64, 64))
        return lambda a, b: base + amp * table[(a / cells).astype(int) % 64, (b / cells).astype(int) % 64]
    if kind == 1:
        period, angle = rng.uniform(0.04, 0.25), rng.uniform(0, np.pi)
        c, s = np.cos(angle), np.sin(angle)
        return lambda a, b: base + amp * np.sign(np.sin(2 * np.pi * (c * a + s * b) / period))
    return float(base)


def _box(centre_xy, size, yaw: float, bottom: float, reflectance, label: str) -> list[Patch]:
    """The four sides and the top of an upright box (base centre ``centre_xy`` at height ``bottom``)."""
    sx, sy, sz = size
    u = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    v = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    z = np.array([0.0, 0.0, 1.0])
    base = np.array([centre_xy[0], centre_xy[1], bottom]) - 0.5 * sx * u - 0.5 * sy * v
    faces = [(base, u, z, sx, sz, -v), (base + sy * v, u, z, sx, sz, v), (base, v, z, sy, sz, -u),
             (base + sx * u, v, z, sy, sz, u), (base + sz * z, u, v, sx, sy, z)]
    return [rectangle(o, a, b, w, h, _shade(reflectance, n), label) for o, a, b, w, h, n in faces]


@dataclass(frozen=True)
class Room:
    """A furnished room (world frame: z up, the floor at 0, the room ``[0, length] x [0, width]``), its pieces
    and the footprints of its furniture (centre x, y and radius) that a rig keeps clear of."""

    length: float
    width: float
    patches: tuple
    footprints: tuple
    # Each free-standing piece's footprint and the range of its patches in ``patches`` (``(start, stop)``).
    pieces: tuple = ()


def _material(rng: np.random.Generator) -> float:
    return float(rng.choice([rng.uniform(0.04, 0.12), rng.uniform(0.2, 0.5), rng.uniform(0.55, 0.9)]))


def _on_wall(rng: np.random.Generator, length: float, width: float, item_w: float, bottom: float, height: float,
             proud: float, reflectance, label: str) -> tuple[Patch, np.ndarray]:
    """A rectangle on a random wall, ``proud`` metres in front of it (negative: behind the wall's face), and
    the wall's normal into the room."""
    wall = rng.integers(4)
    z = np.array([0.0, 0.0, 1.0])
    if wall < 2:  # x = 0 (facing +x) or x = length (facing -x)
        x = proud if wall == 0 else length - proud
        y = rng.uniform(0.3, width - 0.3 - item_w)
        o, u = (np.array([x, y, bottom]), np.array([0.0, 1.0, 0.0]))
        n = np.array([1.0, 0.0, 0.0]) * (1 if wall == 0 else -1)
    else:
        y = proud if wall == 2 else width - proud
        x = rng.uniform(0.3, length - 0.3 - item_w)
        o, u = (np.array([x, y, bottom]), np.array([1.0, 0.0, 0.0]))
        n = np.array([0.0, 1.0, 0.0]) * (1 if wall == 2 else -1)
    return rectangle(o, u, z, item_w, height, _shade(reflectance, n), label), n


def furnished_room(rng: np.random.Generator) -> Room:
    """A room drawn at random (module docstring)."""
    L, W = rng.uniform(6.0, 11.0), rng.uniform(5.0, 9.0)
    wall_tint = rng.uniform(0.5, 0.8)
    patches = [infinite_plane([0, 0, 1], 0.0, _shade(rng.uniform(0.15, 0.4), [0, 0, 1]), "floor"),
               infinite_plane([0, 0, 1], rng.uniform(2.6, 3.2), 0.85, "ceiling")]
    for n, d in (([1, 0, 0], 0.0), ([1, 0, 0], L), ([0, 1, 0], 0.0), ([0, 1, 0], W)):
        patches.append(infinite_plane(n, d, _shade(wall_tint, np.array(n, float)), "wall"))
    # Windows (glass, bright) in frames; doors in proud frames; posters and pictures.
    for _ in range(int(rng.integers(1, 4))):
        w, h = rng.uniform(0.8, 1.8), rng.uniform(0.9, 1.5)
        glass, n = _on_wall(rng, L, W, w, rng.uniform(0.8, 1.1), h, 0.005, 0.95, GLASS)
        patches += [glass, *_frame(glass, n, 0.005, 0.06, 0.04, rng.uniform(0.1, 0.9))]
    for _ in range(int(rng.integers(1, 3))):
        door, n = _on_wall(rng, L, W, 0.9, 0.0, 2.05, 0.01, _material(rng), "door")
        patches += [door, *_frame(door, n, 0.01, 0.08, 0.05, _material(rng))]
    for _ in range(int(rng.integers(3, 8))):
        w, h = rng.uniform(0.4, 1.4), rng.uniform(0.4, 1.1)
        patches.append(_on_wall(rng, L, W, w, rng.uniform(0.8, 1.7), h, 0.01, _texture(rng), "poster")[0])
    # Free-standing furniture, anywhere in the room (the rig keeps clear of its footprints).
    footprints = []

    def place(size, against_wall: bool) -> tuple[np.ndarray, float]:
        if against_wall:
            side = rng.integers(4)
            along = rng.uniform(0.6, (L if side < 2 else W) - 0.6)
            off = size[1] / 2 + 0.03
            xy = {0: (off, along), 1: (L - off, along), 2: (along, off), 3: (along, W - off)}[side]
            yaw = {0: np.pi / 2, 1: -np.pi / 2, 2: 0.0, 3: np.pi}[side]
            return np.array(xy), yaw
        return np.array([rng.uniform(0.8, L - 0.8), rng.uniform(0.8, W - 0.8)]), rng.uniform(0, np.pi)

    kinds = rng.choice(["desk", "shelf", "cabinet", "chair", "sofa", "crate", "pillar", "plant"],
                       size=int(rng.integers(8, 15)))
    pieces = []
    for kind in kinds:
        start = len(patches)
        if kind == "desk":
            xy, yaw = place((1.4, 0.7), rng.uniform() < 0.5)
            top = _material(rng)
            patches += _box(xy, (1.4, 0.7, 0.04), yaw, 0.72, top, "desk")
            for sx in (-0.65, 0.65):  # side panels
                c = xy + sx * np.array([np.cos(yaw), np.sin(yaw)])
                patches += _box(c, (0.04, 0.66, 0.72), yaw, 0.0, top, "desk")
            if rng.uniform() < 0.7:
                patches += _box(xy, (0.55, 0.05, 0.35), yaw, 0.85, 0.04, "monitor")
            footprints.append((*xy, 0.8))
        elif kind in ("shelf", "cabinet"):
            size = (rng.uniform(0.6, 1.6), rng.uniform(0.35, 0.6),
                    rng.uniform(1.6, 2.2) if kind == "shelf" else rng.uniform(0.7, 1.3))
            xy, yaw = place(size, rng.uniform() < 0.7)
            patches += _box(xy, size, yaw, 0.0, _material(rng), kind)
            footprints.append((*xy, 0.5 * np.hypot(size[0], size[1])))
        elif kind == "chair":
            xy, yaw = place((0.5, 0.5), False)
            m = _material(rng)
            patches += _box(xy, (0.48, 0.48, 0.06), yaw, 0.42, m, "chair")
            back = xy - 0.22 * np.array([-np.sin(yaw), np.cos(yaw)])
            patches += _box(back, (0.46, 0.05, 0.5), yaw, 0.48, m, "chair")
            patches += _box(xy, (0.08, 0.08, 0.42), yaw, 0.0, 0.1, "chair")
            footprints.append((*xy, 0.4))
        elif kind == "sofa":
            xy, yaw = place((1.9, 0.9), rng.uniform() < 0.6)
            m = _material(rng)
            patches += _box(xy, (1.9, 0.9, 0.45), yaw, 0.0, m, "sofa")
            back = xy - 0.35 * np.array([-np.sin(yaw), np.cos(yaw)])
            patches += _box(back, (1.9, 0.2, 0.4), yaw, 0.45, m, "sofa")
            footprints.append((*xy, 1.05))
        elif kind == "crate":
            s = rng.uniform(0.3, 0.8)
            xy, yaw = place((s, s), False)
            patches += _box(xy, (s, s, rng.uniform(0.3, 0.9)), yaw, 0.0, _material(rng), "crate")
            footprints.append((*xy, 0.75 * s))
        elif kind == "pillar":
            s = rng.uniform(0.25, 0.5)
            xy, yaw = place((s, s), False)
            patches += _box(xy, (s, s, 3.5), yaw, 0.0, _material(rng), "pillar")
            footprints.append((*xy, 0.75 * s))
        else:  # a plant on a thin stand
            xy, yaw = place((0.4, 0.4), False)
            patches += _box(xy, (0.05, 0.05, 0.9), yaw, 0.0, 0.1, "plant")
            patches += _box(xy, (0.45, 0.45, 0.6), yaw, 0.9, rng.uniform(0.1, 0.3), "plant")
            footprints.append((*xy, 0.35))
        pieces.append((footprints[-1], (start, len(patches))))
    return Room(L, W, tuple(patches), tuple(footprints), tuple(pieces))


# A board scene's room: the LiDAR this far from the wall behind it at most (m), the boards' farthest centre (m,
# ``simulator`` draws 2-5 m) and the margin the furniture keeps from each line of sight to a board (m).
BEHIND_M, FARTHEST_BOARD_M, SIGHT_MARGIN_M = 2.0, 5.0, 0.7


def room_around_rig(ground_z: float, rng: np.random.Generator, board_centres: np.ndarray) -> list[Patch]:
    """A furnished room (module docstring) around a still rig, for the board scenes (``simulate_dataset(
    scene="furnished")``): in the level frame (the LiDAR at the origin, z up, the floor at ``ground_z``), the
    rig near one end of the room facing along it (turned by up to 20 degrees), the free-standing furniture kept
    off the lines of sight to the boards (``board_centres``, level frame, k x 3) and away from the rig; what
    remains in view lies beside and behind the boards."""
    room = furnished_room(rng)
    x0 = float(np.clip(rng.uniform(0.8, BEHIND_M), 0.6, max(room.length - FARTHEST_BOARD_M - 0.6, 0.6)))
    y0 = float(np.clip(room.width / 2 + rng.uniform(-1.0, 1.0), 1.5, room.width - 1.5))
    T_world_level = T_from_Rt(R_from_rotvec([0.0, 0.0, rng.uniform(-0.35, 0.35)]), np.array([x0, y0, -ground_z]))
    R, t = T_world_level[:3, :3], T_world_level[:3, 3]
    ends = np.asarray(board_centres, float)[:, :2]

    def clear(fx: float, fy: float, r: float) -> bool:
        p = (R.T @ (np.array([fx, fy, 0.0]) - t))[:2]
        if np.hypot(*p) < r + 0.8:
            return False
        for e in ends:
            reach = np.linalg.norm(e) + 0.6
            s = np.clip(p @ e / (np.linalg.norm(e) * reach), 0.0, 1.0) * reach  # along the line of sight
            if np.linalg.norm(p - s * e / np.linalg.norm(e)) < r + SIGHT_MARGIN_M:
                return False
        return True

    first = room.pieces[0][1][0] if room.pieces else len(room.patches)
    kept = list(room.patches[:first])
    for (fx, fy, r), (a, b) in room.pieces:
        if clear(fx, fy, r):
            kept += room.patches[a:b]
    return _in_lidar(kept, T_world_level)


def _frame(inner: Patch, into_room: np.ndarray, inner_proud: float, band: float, proud: float,
           reflectance: float) -> list[Patch]:
    """A frame of four strips ``band`` wide round a rectangle on a wall (a door's, a window's), ``proud`` metres
    in front of the wall (the rectangle itself ``inner_proud``)."""
    o = inner.origin + (proud - inner_proud) * into_room
    u, v, w, h = inner.u, inner.v, inner.width, inner.height
    r = _shade(reflectance, into_room)
    return [rectangle(o - band * u - band * v, u, v, w + 2 * band, band, r, "frame"),
            rectangle(o - band * u + h * v, u, v, w + 2 * band, band, r, "frame"),
            rectangle(o - band * u, u, v, band, h, r, "frame"),
            rectangle(o + w * u, u, v, band, h, r, "frame")]


def _in_lidar(patches, T_world_lidar: np.ndarray) -> list[Patch]:
    """The room's pieces in the LiDAR's frame."""
    R, t = T_world_lidar[:3, :3], T_world_lidar[:3, 3]
    out = []
    for p in patches:
        n = R.T @ p.normal
        d = p.distance - p.normal @ t
        if p.origin is None:
            out.append(Patch(n, d, p.reflectance, label=p.label))
        else:
            out.append(Patch(n, d, p.reflectance, R.T @ (p.origin - t), R.T @ p.u, R.T @ p.v, p.width, p.height,
                             p.label))
    return out

"""Scenes beyond the empty room: an office full of board-sized flat surfaces, an open hall, and the person who
holds the board.

- ``office``: walls with doors (recessed), pictures and whiteboards (proud of the wall), cabinets, a table with
  monitors, and a pillar. Many of these are flat, about the board's size, and at the boards' distances from the
  LiDAR, so that no rotation-invariant cue tells them from the board.
- ``hall``: only the ground and distant walls; with range noise of a few centimetres, patches of ground of the
  board's size lie at the boards' distances.
- The board is held by a person (body and head behind it, hands and forearms at its side edges, in its plane)
  or stands on a thin stand, at random per frame.

The static part is drawn once per dataset (``office_layout``); the board and its holder change per frame.
"""
from __future__ import annotations

import numpy as np

from .scene import Patch, infinite_plane, rectangle

SCENES = ("default", "office", "hall", "furnished")


def _box(centre, size, yaw: float, reflectance: float, label: str) -> list[Patch]:
    """The four vertical faces and the top of an upright box (centre of its base, size x, y, z)."""
    c = np.asarray(centre, float)
    sx, sy, sz = size
    u = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    v = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    z = np.array([0.0, 0.0, 1.0])
    base = c - 0.5 * sx * u - 0.5 * sy * v
    return [rectangle(base, u, z, sx, sz, reflectance, label),
            rectangle(base + sy * v, u, z, sx, sz, reflectance, label),
            rectangle(base, v, z, sy, sz, reflectance, label),
            rectangle(base + sx * u, v, z, sy, sz, reflectance, label),
            rectangle(base + sz * z, u, v, sx, sy, reflectance, label)]


def _on_wall(wall_x: float | None, wall_y: float | None, along: float, bottom: float, width: float, height: float,
             proud: float, reflectance: float, label: str) -> Patch:
    """A rectangle on a wall: ``x = wall_x`` (facing -x) or ``y = wall_y`` (facing -y/+y), ``proud`` metres in
    front of it (negative: recessed)."""
    zv = np.array([0.0, 0.0, 1.0])
    if wall_x is not None:
        x = wall_x - np.sign(wall_x) * proud
        return rectangle([x, along, bottom], [0.0, 1.0, 0.0], zv, width, height, reflectance, label)
    y = wall_y - np.sign(wall_y) * proud
    return rectangle([along, y, bottom], [1.0, 0.0, 0.0], zv, width, height, reflectance, label)


def office_layout(ground_z: float, rng: np.random.Generator) -> list[Patch]:
    """The static office (LiDAR frame, z up): a room about 13 x 10 m around the rig, with furniture placed at
    random but away from the space in front of the camera where the boards are held."""
    front, back = rng.uniform(6.5, 8.5), -rng.uniform(3.5, 5.0)
    left, right = rng.uniform(4.0, 5.5), -rng.uniform(4.0, 5.5)
    g = ground_z
    patches = [infinite_plane([0, 0, 1], g, 0.3, "ground"),
               infinite_plane([1, 0, 0], front, 0.55, "wall"), infinite_plane([1, 0, 0], back, 0.55, "wall"),
               infinite_plane([0, 1, 0], left, 0.6, "wall"), infinite_plane([0, 1, 0], right, 0.6, "wall"),
               infinite_plane([0, 0, 1], g + 3.0, 0.5, "ceiling")]
    # Doors (recessed 5 cm) and pictures / whiteboards (2 cm proud) on every wall.
    for wall in ("front", "left", "right", "back"):
        wx = {"front": front, "back": back}.get(wall)
        wy = {"left": left, "right": right}.get(wall)
        span = (right + 0.5, left - 1.5) if wx is not None else (back + 0.5, front - 1.5)
        for _ in range(int(rng.integers(1, 3))):
            patches.append(_on_wall(wx, wy, rng.uniform(*span), g, 0.9, 2.05, -0.05, 0.4, "door"))
        for _ in range(int(rng.integers(1, 4))):
            w, h = rng.uniform(0.5, 1.2), rng.uniform(0.5, 1.0)
            patches.append(_on_wall(wx, wy, rng.uniform(*span), g + rng.uniform(0.9, 1.6), w, h, 0.02,
                                    rng.uniform(0.2, 0.8), "picture"))
    # Cabinets along the side walls, 2-6 m ahead.
    for side in (left, right):
        for _ in range(int(rng.integers(1, 3))):
            depth = 0.5
            y = side - np.sign(side) * (depth / 2 + 0.02)
            patches += _box([rng.uniform(1.5, 6.0), y, g], (rng.uniform(0.6, 1.0), depth, rng.uniform(0.8, 1.8)),
                            0.0, 0.45, "cabinet")
    # A table with two monitors facing the rig, off to one side at the boards' distances.
    side = rng.choice([-1.0, 1.0])
    tx, ty = rng.uniform(2.5, 4.5), side * rng.uniform(2.4, 3.2)
    top = g + 0.75
    patches.append(rectangle([tx - 0.4, ty - 0.8, top], [1, 0, 0], [0, 1, 0], 0.8, 1.6, 0.35, "table"))
    for leg in ((-0.35, -0.75), (-0.35, 0.7), (0.3, -0.75), (0.3, 0.7)):
        patches += _box([tx + leg[0], ty + leg[1], g], (0.05, 0.05, 0.75), 0.0, 0.3, "table")
    for dy in (-0.4, 0.4):
        yaw = np.arctan2(-(ty + dy), -tx)
        n = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        u = np.array([-n[1], n[0], 0.0])
        centre = np.array([tx, ty + dy, top + 0.12])
        patches.append(rectangle(centre - 0.27 * u, u, [0, 0, 1], 0.55, 0.35, 0.1, "monitor"))
    # A pillar, off the camera's view, at the boards' distances.
    patches += _box([rng.uniform(2.5, 5.0), -side * rng.uniform(2.3, 3.0), g], (0.4, 0.4, 3.0), 0.3, 0.5, "pillar")
    return patches


def hall_layout(ground_z: float) -> list[Patch]:
    """An open hall: the ground and walls 25 m away."""
    return [infinite_plane([0, 0, 1], ground_z, 0.3, "ground"),
            infinite_plane([1, 0, 0], 25.0, 0.55, "wall"), infinite_plane([1, 0, 0], -25.0, 0.55, "wall"),
            infinite_plane([0, 1, 0], 25.0, 0.6, "wall"), infinite_plane([0, 1, 0], -25.0, 0.6, "wall")]


def holder(board_outline_lidar: np.ndarray, ground_z: float) -> list[Patch]:
    """A person holding the board by its side edges: body and head behind it (seen from the LiDAR), hands
    gripping the two side edges at mid height (in the board's plane, reaching 6 cm past it) and forearms from
    the hands back to the body. ``board_outline_lidar``: the board's four corners (LiDAR frame), in order."""
    o = np.asarray(board_outline_lidar, float)
    centre = o.mean(0)
    away = np.append(centre[:2] / np.linalg.norm(centre[:2]), 0.0)  # horizontal, from the LiDAR through the board
    side = np.array([-away[1], away[0], 0.0])
    normal = np.cross(o[1] - o[0], o[3] - o[0])
    normal /= np.linalg.norm(normal)
    normal = normal if normal @ centre > 0 else -normal  # from the sensor through the board
    body_c = centre + 0.35 * away
    # The person stands behind the board: every part of the body at least 20 cm behind its plane.
    corners_body = np.array([[*(body_c[:2] + dx * away[:2] + dy * side[:2]), z]
                             for dx in (-0.13, 0.13) for dy in (-0.25, 0.25) for z in (ground_z, ground_z + 1.75)])
    behind = float(np.min((corners_body - centre) @ normal))
    if behind < 0.2:
        body_c = body_c + (0.2 - behind) / max(away @ normal, 0.3) * away
    patches = _box([body_c[0], body_c[1], ground_z], (0.25, 0.45, 1.45), float(np.arctan2(away[1], away[0])), 0.25,
                   "holder")
    patches += _box([body_c[0], body_c[1], ground_z + 1.5], (0.2, 0.18, 0.25), float(np.arctan2(away[1], away[0])),
                    0.35, "holder")
    # The board's side edges: the two edges whose direction is closest to vertical.
    edges = [(o[i], o[(i + 1) % 4]) for i in range(4)]
    vertical = sorted(edges, key=lambda e: -abs((e[1] - e[0])[2]) / np.linalg.norm(e[1] - e[0]))[:2]
    for a, b in vertical:
        mid = 0.5 * (a + b)
        along = (b - a) / np.linalg.norm(b - a)
        outward = mid - centre
        outward -= (outward @ along) * along + (outward @ normal) * normal
        outward /= np.linalg.norm(outward)
        # The hand: 10 cm tall, from 2 cm inside the edge to 6 cm outside, 1 cm in front of the board.
        toward = -np.sign(normal @ centre) * normal
        hand_o = mid - 0.05 * along - 0.02 * outward + 0.01 * toward
        patches.append(rectangle(hand_o, outward, along, 0.08, 0.10, 0.3, "holder"))
        # The forearm: from outside the hand's grip back towards the body's side.
        start = mid + 0.06 * outward
        shoulder = body_c + (0.2 if side @ outward > 0 else -0.2) * side
        shoulder[2] = ground_z + 1.3
        arm = shoulder - start
        length = float(np.linalg.norm(arm))
        if length > 0.05:
            patches.append(rectangle(start - 0.04 * np.array([0.0, 0.0, 1.0]), arm / length, [0.0, 0.0, 1.0],
                                     length, 0.08, 0.3, "holder"))
    return patches


def board_fraction_in_fov(board_outline_lidar: np.ndarray, elevations_rad: np.ndarray, samples: int = 12) -> float:
    """Share of the board's area inside the LiDAR's vertical field of view."""
    o = np.asarray(board_outline_lidar, float)
    s = (np.arange(samples) + 0.5) / samples
    a, b = np.meshgrid(s, s)
    pts = o[0] + a.reshape(-1, 1) * (o[1] - o[0]) + b.reshape(-1, 1) * (o[3] - o[0])
    el = np.arctan2(pts[:, 2], np.linalg.norm(pts[:, :2], axis=1))
    return float(np.mean((el >= elevations_rad.min()) & (el <= elevations_rad.max())))


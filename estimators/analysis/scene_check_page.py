"""The scene's check page (``check.html``): the verdict, the test, and per frame the image with the LiDAR's
contour returns drawn where the given extrinsic puts them (red) and where the scene's estimate does (blue), over
the image's edges (green). Under a right extrinsic the red dots sit on green lines."""
from __future__ import annotations

import html
from pathlib import Path

import cv2
import numpy as np

from geometry.rotations import transform_points

from ..io.output import write_atomic
from ..solvers.scene_alignment import STAGES_PX
from .report import html_page, verdict_part

# Frames drawn at most, and the width they are drawn at (px).
MAX_FRAMES, WIDTH_PX = 6, 960


def _overlay(result, view) -> np.ndarray:
    """A frame's edges with its contour returns under the given and the scene's extrinsic."""
    field = view.edges.distance
    img = np.full(field.shape + (3,), 40, np.uint8)
    img[field == 0] = (60, 200, 60)
    for T, colour in ((result.fit.T_camera_lidar, (230, 120, 40)), (result.T_given, (40, 40, 230))):
        uv = result.camera.project(transform_points(T, view.points))
        inside = np.all(np.isfinite(uv), axis=1) & np.all(np.abs(uv) < 4 * max(field.shape), axis=1)
        for u, v in uv[inside]:
            cv2.circle(img, (int(round(u * 4)), int(round(v * 4))), 12, colour, -1, cv2.LINE_AA, 2)
    scale = WIDTH_PX / img.shape[1]
    return cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else img


def write_check_page(result, out: str | Path, page_name: str = "check.html", verdict_of=None,
                     given: str = "the given extrinsic") -> Path:
    """``out/check.html`` (or ``page_name``) and its frames' overlays (``check_NNNN.jpg``), each written
    atomically. ``verdict_of``: the result whose verdict opens the page (a targetless calibration's; default
    ``result``); ``given``: what the extrinsic checked is (``an initial guess``)."""
    out = Path(out)
    t = result.test
    rot, trans = result.camera_axes_sd()
    p = "undetermined" if t["p_value"] is None else f"{t['p_value']:.3g}"
    title = "the scene's check of an extrinsic" if verdict_of is None else "a targetless calibration from the scene"
    parts = [f"<h1>lidarcam: {title}</h1>", verdict_part(result if verdict_of is None else verdict_of),
             f"<p>dataset: {html.escape(result.dataset)}; {result.fit.frames} frames, {result.fit.points} LiDAR "
             f"contour returns{', the board left out' if result.board_left_out else ''}; "
             f"{'' if verdict_of is None else 'the initial guess '}consistent: "
             f"{result.consistent}; p = {p} ({t['dof']} constrained directions, Hotelling's F).</p>",
             f"<p>contours on edges: {result.fit.rms_start_px:.2f} px RMS at {given}, "
             f"{result.fit.rms_px:.2f} px at the scene's (along the rings, truncated at {min(STAGES_PX):g} px). "
             f"The scene's estimate's standard deviations about the camera's x, y, z: "
             f"{', '.join(f'{v:.2f}' for v in rot)} deg; along them: {', '.join(f'{v:.1f}' for v in trans)} mm.</p>",
             "<p>Green: the image's edges square enough to the LiDAR's rings to meet its contours; red: the LiDAR's "
             f"contour returns under {given}; blue: under the scene's estimate.</p>"]
    for view in result.views[:MAX_FRAMES]:
        name = f"check_{view.name}.jpg"
        ok, jpg = cv2.imencode(".jpg", _overlay(result, view), [cv2.IMWRITE_JPEG_QUALITY, 90])
        if ok:
            write_atomic(out / name, lambda fh, data=jpg.tobytes(): fh.write(data), mode="wb")
            parts.append(f"<h3>frame {html.escape(view.name)}</h3><img src='{name}'>")
    page = html_page("lidarcam scene check", parts)
    return write_atomic(out / page_name, lambda fh: fh.write(page))

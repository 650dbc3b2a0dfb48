"""A top view of one LiDAR sweep or scan (x forward to the right, y left upwards), drawn with OpenCV into a PNG:
every return grey, board candidates coloured and numbered, the chosen one ringed in black, a metric grid with
labelled axes and a legend. One per frame in the report: a matplotlib figure of the same content cost about
0.14 s each, this a few milliseconds."""
from __future__ import annotations

import cv2
import numpy as np

# matplotlib's tab10 colours (C0-C9) as BGR, so the candidates keep the colours the rest of the report uses
_TAB10 = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22",
          "#17becf"]
_COLOURS = [tuple(int(h[i:i + 2], 16) for i in (5, 3, 1)) for h in _TAB10]
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_BLACK, _GRID, _WHITE = (0, 0, 0), (225, 225, 225), (255, 255, 255)
PLOT_PX = 520  # the square plot area
_LEFT, _BOTTOM, _TOP, _RIGHT = 64, 44, 30, 16


def _nice_step(span: float, ticks: int = 6) -> float:
    """A grid step of 1, 2 or 5 times a power of ten giving about ``ticks`` lines over ``span``."""
    raw = span / ticks
    p = 10.0 ** np.floor(np.log10(raw))
    return float(p * min((m for m in (1.0, 2.0, 5.0, 10.0) if m * p >= raw), default=10.0))


def top_view_png(points_xy: np.ndarray, candidates: list[np.ndarray], chosen: int | None, title: str,
                 dot_px: int = 1) -> bytes:
    """PNG bytes of the view centred on the candidates (a square at least 8 m wide), or on the sensor without
    any. ``points_xy``: every return (N, 2+); ``candidates``: each candidate's points (M, 2+)."""
    pts = np.asarray(points_xy, float)[:, :2]
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    centres = [np.asarray(P, float)[:, :2].mean(0) for P in candidates]
    if centres:
        c = np.mean(centres, axis=0)
        reach = max(4.0, 1.5 * max(float(np.linalg.norm(x - c)) for x in centres))
    else:
        c, reach = np.zeros(2), 4.0
    scale = PLOT_PX / (2 * reach)  # pixels per metre

    def to_px(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = _LEFT + (xy[:, 0] - (c[0] - reach)) * scale
        v = _TOP + (c[1] + reach - xy[:, 1]) * scale
        return u, v

    W, H = _LEFT + PLOT_PX + _RIGHT, _TOP + PLOT_PX + _BOTTOM
    img = np.full((H, W, 3), 255, np.uint8)
    step = _nice_step(2 * reach)
    for axis in (0, 1):
        for g in np.arange(np.ceil((c[axis] - reach) / step), np.floor((c[axis] + reach) / step) + 1) * step + 0.0:
            if axis == 0:
                u = int(round(_LEFT + (g - (c[0] - reach)) * scale))
                cv2.line(img, (u, _TOP), (u, _TOP + PLOT_PX), _GRID, 1)
                _centred_text(img, f"{g:g}", u, _TOP + PLOT_PX + 16)
            else:
                v = int(round(_TOP + (c[1] + reach - g) * scale))
                cv2.line(img, (_LEFT, v), (_LEFT + PLOT_PX, v), _GRID, 1)
                label = f"{g:g}"
                w = cv2.getTextSize(label, _FONT, 0.4, 1)[0][0]
                cv2.putText(img, label, (_LEFT - 6 - w, v + 4), _FONT, 0.4, _BLACK, 1, cv2.LINE_AA)
    _stamp(img, *to_px(pts), (170, 170, 170), dot_px)
    for i, P in enumerate(candidates):
        u, v = to_px(np.asarray(P, float)[:, :2])
        if i == chosen:
            _stamp(img, u, v, _BLACK, dot_px + 2)
        _stamp(img, u, v, _COLOURS[i % 10], dot_px + 1)
    for i, x in enumerate(centres):  # the numbers, where they fit in the plot
        u, v = to_px(x[None])
        if not (_LEFT <= u[0] <= _LEFT + PLOT_PX - 20 and _TOP + 14 <= v[0] <= _TOP + PLOT_PX):
            continue
        at = (int(u[0]) + 6, int(v[0]) - 6)
        cv2.putText(img, str(i), at, _FONT, 0.5, _WHITE, 4, cv2.LINE_AA)  # a halo over the points
        cv2.putText(img, str(i), at, _FONT, 0.5, _BLACK, 2 if i == chosen else 1, cv2.LINE_AA)
    u, v = to_px(np.zeros((1, 2)))  # the sensor, where it lies in the view
    if _LEFT + 6 <= u[0] <= _LEFT + PLOT_PX - 6 and _TOP + 6 <= v[0] <= _TOP + PLOT_PX - 6:
        tri = np.array([[u[0], v[0] - 6], [u[0] - 5, v[0] + 4], [u[0] + 5, v[0] + 4]])
        cv2.fillPoly(img, [np.rint(tri).astype(np.int32)], _BLACK, cv2.LINE_AA)
    cv2.rectangle(img, (_LEFT, _TOP), (_LEFT + PLOT_PX, _TOP + PLOT_PX), _BLACK, 1)
    legend = [(_COLOURS[i % 10], f"{i}: {'chosen' if i == chosen else 'rejected'} ({len(P)} points)")
              for i, P in enumerate(candidates)]
    _legend(img, legend)
    cv2.putText(img, title, (_LEFT, 20), _FONT, 0.5, _BLACK, 1, cv2.LINE_AA)
    _centred_text(img, "LiDAR x [m]", _LEFT + PLOT_PX // 2, H - 8)
    ylabel = np.full((18, 110, 3), 255, np.uint8)
    cv2.putText(ylabel, "LiDAR y [m]", (4, 13), _FONT, 0.45, _BLACK, 1, cv2.LINE_AA)
    ylabel = cv2.rotate(ylabel, cv2.ROTATE_90_COUNTERCLOCKWISE)
    y0 = _TOP + PLOT_PX // 2 - ylabel.shape[0] // 2
    img[y0:y0 + ylabel.shape[0], 2:2 + ylabel.shape[1]] = ylabel
    ok, png = cv2.imencode(".png", img)
    return png.tobytes()


def _stamp(img: np.ndarray, u: np.ndarray, v: np.ndarray, colour, size: int) -> None:
    """Squares of ``2 size - 1`` pixels at (u, v), clipped to the plot area."""
    iu, iv = np.rint(u).astype(np.int64, copy=False), np.rint(v).astype(np.int64, copy=False)
    keep = (iu >= _LEFT) & (iu <= _LEFT + PLOT_PX) & (iv >= _TOP) & (iv <= _TOP + PLOT_PX)
    iu, iv = iu[keep], iv[keep]
    for du in range(-size + 1, size):
        for dv in range(-size + 1, size):
            uu, vv = iu + du, iv + dv
            ok = (uu >= _LEFT) & (uu <= _LEFT + PLOT_PX) & (vv >= _TOP) & (vv <= _TOP + PLOT_PX)
            img[vv[ok], uu[ok]] = colour


def _centred_text(img: np.ndarray, text: str, u: int, v: int, size: float = 0.4) -> None:
    w = cv2.getTextSize(text, _FONT, size, 1)[0][0]
    cv2.putText(img, text, (int(u - w / 2), int(v)), _FONT, size, _BLACK, 1, cv2.LINE_AA)


def _legend(img: np.ndarray, entries: list[tuple[tuple[int, int, int], str]]) -> None:
    """A boxed legend in the plot's upper right corner."""
    if not entries:
        return
    width = max(cv2.getTextSize(t, _FONT, 0.4, 1)[0][0] for _, t in entries) + 30
    x1, y0 = _LEFT + PLOT_PX - 6, _TOP + 6
    x0, y1 = x1 - width, y0 + 16 * len(entries) + 6
    cv2.rectangle(img, (x0, y0), (x1, y1), _WHITE, -1)
    cv2.rectangle(img, (x0, y0), (x1, y1), (120, 120, 120), 1)
    for k, (colour, text) in enumerate(entries):
        y = y0 + 15 + 16 * k
        cv2.rectangle(img, (x0 + 6, y - 7), (x0 + 14, y + 1), colour, -1)
        cv2.putText(img, text, (x0 + 22, y), _FONT, 0.4, _BLACK, 1, cv2.LINE_AA)

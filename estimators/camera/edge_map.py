"""An image's edges for laying LiDAR contours on: each edge pixel with its normal, and each pixel's nearest edge.

Edges by Canny on the lightly blurred grey image, its thresholds from the image's own gradients (``HIGH_QUANTILE``
of the Sobel magnitude, and a fraction of it), so that a dim, flat or noisy image gives edges alike. Each edge
pixel keeps its normal (the blurred image's gradient direction there). ``EdgeMap`` holds a chosen set of them
(the scene's alignment keeps those square enough to the LiDAR's rings) and, for every pixel, the nearest one
(OpenCV's distance transform with labels), from which an aligner measures a point's offset across that edge.
``edge_distance`` is the plain truncated distance to the nearest edge.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

TRUNCATE_PX = 20.0
BLUR_PX = 1.5
# Canny's high threshold: this quantile of the blurred image's Sobel magnitude (at least ``MIN_HIGH``); its low
# threshold this fraction of it.
HIGH_QUANTILE, LOW_FRACTION, MIN_HIGH = 0.85, 0.4, 12.0


def _edges_and_gradient(gray: np.ndarray, blur_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    g = cv2.GaussianBlur(gray, (0, 0), blur_px)
    gu, gv = cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1)
    high = max(float(np.quantile(np.hypot(gu, gv), HIGH_QUANTILE)), MIN_HIGH)
    return cv2.Canny(g, LOW_FRACTION * high, high, L2gradient=True) > 0, gu, gv


def edge_pixels(gray: np.ndarray, blur_px: float = BLUR_PX) -> np.ndarray:
    """Canny's edges (bool (H, W)) of an 8-bit grey image."""
    return _edges_and_gradient(gray, blur_px)[0]


def edges_with_normals(gray: np.ndarray, ignore: np.ndarray | None = None, blur_px: float = BLUR_PX
                       ) -> tuple[np.ndarray, np.ndarray]:
    """The edge pixels (``(M, 2)`` u, v, in raster order) and their unit normals (``(M, 2)``: the blurred image's
    gradient direction); ``ignore``: a mask (bool (H, W)) whose edges are dropped (found in the whole image
    first, so that the mask's own border is none)."""
    edges, gu, gv = _edges_and_gradient(gray, blur_px)
    if ignore is not None:
        edges &= ~ignore
    v, u = np.nonzero(edges)
    n = np.column_stack([gu[v, u], gv[v, u]]).astype(float)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
    return np.column_stack([u, v]).astype(float), n


@dataclass(frozen=True, eq=False)
class EdgeMap:
    """Edge pixels (``edges`` (M, 2) u, v), their unit normals (``normals`` (M, 2)), and for every pixel of an
    image of ``shape`` (H, W) the index of its nearest edge pixel (``nearest``, int32 (H, W); -1 with no edge)
    and its distance to it (``distance``, px, float32 (H, W); OpenCV's 5x5 mask, within 2% of Euclidean)."""

    edges: np.ndarray
    normals: np.ndarray
    nearest: np.ndarray
    distance: np.ndarray

    @classmethod
    def of(cls, shape: tuple[int, int], edges: np.ndarray, normals: np.ndarray) -> "EdgeMap":
        """The map of these edge pixels (integer u, v within ``shape``)."""
        free = np.ones(shape, np.uint8)
        if len(edges) == 0:
            return cls(np.zeros((0, 2)), np.zeros((0, 2)), np.full(shape, -1, np.int32),
                       np.full(shape, np.inf, np.float32))
        u, v = edges[:, 0].astype(np.int64), edges[:, 1].astype(np.int64)
        order = np.lexsort((u, v))  # OpenCV numbers the zero pixels in raster order, from 1
        edges, normals, u, v = edges[order], normals[order], u[order], v[order]
        free[v, u] = 0
        distance, labels = cv2.distanceTransformWithLabels(free, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
        return cls(edges, normals, (labels - 1).astype(np.int32), distance)


def edge_distance(gray: np.ndarray, truncate_px: float = TRUNCATE_PX, blur_px: float = BLUR_PX,
                  ignore: np.ndarray | None = None) -> np.ndarray:
    """Each pixel's distance to the nearest edge (px, float32 (H, W)), at most ``truncate_px``; ``ignore``: a mask
    (bool (H, W)) whose edges are dropped (found in the whole image first, so that the mask's own border is
    none)."""
    edges = edge_pixels(gray, blur_px)
    if ignore is not None:
        edges &= ~ignore
    if not edges.any():
        return np.full(gray.shape[:2], truncate_px, np.float32)
    d = cv2.distanceTransform((~edges).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.minimum(d, truncate_px).astype(np.float32)

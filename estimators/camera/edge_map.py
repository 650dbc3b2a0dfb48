"""An image's edges as a field to align LiDAR contours with: each pixel's distance to the nearest edge, truncated.

Edges by Canny on the lightly blurred grey image, its thresholds from the image's own gradients (``HIGH_QUANTILE``
of the Sobel magnitude, and a fraction of it), so that a dim, flat or noisy image gives edges alike; the distance transform of the edge-free pixels (OpenCV's exact Euclidean
one) truncated at ``TRUNCATE_PX``, so that a LiDAR contour far from any edge (a contour the camera does not see
as one: a jump between two surfaces of one colour) weighs a bounded amount and pulls nothing. The field's
gradient (central differences) is what an aligner follows.
"""
from __future__ import annotations

import cv2
import numpy as np

TRUNCATE_PX = 20.0
BLUR_PX = 1.5
# Canny's high threshold: this quantile of the blurred image's Sobel magnitude (at least ``MIN_HIGH``); its low
# threshold this fraction of it.
HIGH_QUANTILE, LOW_FRACTION, MIN_HIGH = 0.85, 0.4, 12.0


def edge_pixels(gray: np.ndarray, blur_px: float = BLUR_PX) -> np.ndarray:
    """Canny's edges (bool (H, W)) of an 8-bit grey image."""
    g = cv2.GaussianBlur(gray, (0, 0), blur_px)
    mag = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    high = max(float(np.quantile(mag, HIGH_QUANTILE)), MIN_HIGH)
    return cv2.Canny(g, LOW_FRACTION * high, high, L2gradient=True) > 0


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


def field_gradient(field: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The field's derivatives along u and v (central differences, float32 (H, W) each; zero on the border)."""
    f = np.asarray(field, np.float32)
    kernel = np.array([[-0.5, 0.0, 0.5]], np.float32)
    gu = cv2.filter2D(f, cv2.CV_32F, kernel, borderType=cv2.BORDER_CONSTANT)
    gv = cv2.filter2D(f, cv2.CV_32F, kernel.T, borderType=cv2.BORDER_CONSTANT)
    gu[:, [0, -1]] = 0.0
    gv[[0, -1], :] = 0.0
    return gu, gv

"""Reading images as 8-bit greyscale (colour, palette and 16-bit PNGs, JPEGs)."""
from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from ..errors import ImageReadError


def read_gray(path: str | os.PathLike) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise ImageReadError("image file not found", path=path, hint="check the dataset folder")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise ImageReadError("corrupt or unreadable image", path=path, hint="re-export it as PNG or JPEG")
    return to_gray8(img)


def to_gray8(img: np.ndarray) -> np.ndarray:
    """8-bit greyscale of a decoded image (colour in OpenCV's BGR/BGRA order; 16-bit scaled to its range)."""
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        img = cv2.normalize(img.astype(np.float64), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return img

"""Reading images as 8-bit greyscale (colour, palette and 16-bit PNGs, JPEGs).

The declared size is read from the file's header (Pillow, which parses headers without decoding) and checked
before anything is decoded: a header that claims gigapixels is refused, not allocated.
"""
from __future__ import annotations

import io
import os

import cv2
import numpy as np

from ..errors import ImageReadError, LidarcamError
from .input_files import read_bytes

# Far above any calibration camera (an 8K sensor has 33 megapixels), far below what would exhaust memory
# (decoded as colour: 192 MB).
MAX_IMAGE_PIXELS = 64_000_000
# At most this many bytes are decoded (a 64-megapixel 8-bit colour image takes 192 MB).
MAX_DECODED_BYTES = 256 * 1024 * 1024
# An image file larger than this is not a camera frame.
MAX_IMAGE_BYTES = 512 * 1024 * 1024


def read_gray(path: str | os.PathLike) -> np.ndarray:
    """An image file as 8-bit greyscale."""
    data = read_bytes(path, "image", MAX_IMAGE_BYTES, ImageReadError)
    return to_gray8(decode_image_bytes(data, path, ImageReadError))


def decode_image_bytes(data: bytes, source: object, error: type[LidarcamError] = ImageReadError) -> np.ndarray:
    """Decode encoded image bytes (as OpenCV's ``imdecode``, unchanged channels and depth) after checking the
    format and the declared size; ``source`` names the file or topic in the error."""
    from PIL import Image, UnidentifiedImageError

    if len(data) == 0:
        raise error("empty image file", path=source, hint="re-export it as PNG or JPEG")
    try:
        with Image.open(io.BytesIO(data)) as im:
            width, height, fmt = int(im.size[0]), int(im.size[1]), im.format
            bands = 3 if im.mode in ("P", "PA") else len(im.getbands())  # a palette decodes to colour
            sample_bytes = 2 if im.mode.startswith("I;16") or im.mode in ("I", "F") or "16" in im.mode else 1
    except UnidentifiedImageError:
        raise error("not an image file (no known image header)", path=source,
                    hint="re-export it as PNG or JPEG") from None
    except Image.DecompressionBombError:
        raise error(f"image header declares more than {MAX_IMAGE_PIXELS} pixels", path=source,
                    hint="the file is corrupt or not a camera frame") from None
    except Exception as exc:  # Pillow's header parsers raise many kinds on damaged headers
        raise error(f"damaged image header ({type(exc).__name__})", path=source,
                    hint="re-export it as PNG or JPEG") from None
    if width <= 0 or height <= 0 or width * height > MAX_IMAGE_PIXELS:
        raise error(f"{fmt} header declares {width}x{height} pixels (at most {MAX_IMAGE_PIXELS} are read)",
                    path=source, hint="the file is corrupt or not a camera frame")
    if width * height * bands * sample_bytes > MAX_DECODED_BYTES:
        raise error(f"{fmt} header declares {width}x{height} pixels of {bands} {8 * sample_bytes}-bit channels "
                    f"(more than {MAX_DECODED_BYTES >> 20} MB decoded)", path=source,
                    hint="the file is corrupt or not a camera frame; save it as 8-bit")
    if fmt == "PNG":
        _check_png_chunks(data, source, error)
    try:
        img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise error(f"{fmt} image cannot be decoded ({str(exc).strip().splitlines()[-1][:120]})", path=source,
                    hint="re-export it as PNG or JPEG") from None
    if img is None or img.size == 0:
        raise error(f"corrupt or unreadable {fmt} image", path=source, hint="re-export it as PNG or JPEG")
    if img.shape[0] != height or img.shape[1] != width:
        raise error(f"{fmt} header declares {width}x{height} but {img.shape[1]}x{img.shape[0]} decoded",
                    path=source, hint="the file is corrupt; re-export it")
    return img


def _check_png_chunks(data: bytes, source: object, error: type[LidarcamError]) -> None:
    """Every PNG chunk's declared length fits in the file. OpenCV's PNG reader allocates a chunk's declared
    length before reading it: a damaged length word (an IDAT of "4 GB" in an 800-byte file) cost the
    long fuzz run 4 GB of memory for one image."""
    pos = 8  # the signature
    while pos + 8 <= len(data):
        length = int.from_bytes(data[pos:pos + 4], "big")
        kind = data[pos + 4:pos + 8]
        if length > len(data) - pos - 12:
            name = kind.decode("latin-1") if kind.isalpha() else kind.hex()
            raise error(f"PNG chunk {name} declares {length} bytes but the file has {len(data) - pos - 12} left "
                        "(truncated or corrupt)", path=source, hint="re-export it as PNG or JPEG")
        if kind == b"IEND":
            return
        pos += 12 + length


def to_gray8(img: np.ndarray) -> np.ndarray:
    """8-bit greyscale of a decoded image (colour in OpenCV's BGR/BGRA order; 16-bit scaled to its range)."""
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        # straight to 8 bits: a float64 copy of a 64-megapixel 16-bit image would take 512 MB
        if img.dtype not in (np.uint16, np.int16, np.float32):
            img = img.astype(np.float32)
        img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX, dtype=cv2.CV_8U)
    return img

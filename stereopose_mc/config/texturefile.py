"""Texture image files (``measurements.images.texture.file``): read with OpenCV as a grayscale albedo."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray


class TextureFileError(ValueError):
    """An image file that OpenCV cannot read."""


def read_albedo(path: str | Path) -> NDArray[np.float32]:
    """The grayscale albedo ``(rows, cols)`` in [0, 1] of an image file: 8 or 16 bits over their full scale
    (0..255 -> 0..1); a colour image is converted to luma by OpenCV."""
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH)
    if img is None or img.size == 0:
        raise TextureFileError(f"{path}: not an image OpenCV can read (PNG, JPEG, TIFF, BMP)")
    top = np.iinfo(img.dtype).max if np.issubdtype(img.dtype, np.integer) else 1.0
    return np.clip(img.astype(np.float32) / np.float32(top), 0.0, 1.0)

"""Writing images: 8-bit sRGB PNG with the standard library (zlib + struct)."""

from __future__ import annotations

import os
import struct
import zlib

import numpy as np


def to_srgb8(image, exposure: float = 1.0) -> np.ndarray:
    """Linear RGB → 8-bit sRGB (clipped to [0, 1] after scaling by `exposure`)."""
    x = np.clip(np.asarray(image, dtype=np.float64) * exposure, 0.0, 1.0)
    x = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(x * 255.0).astype(np.uint8)


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def save_png(path: str | os.PathLike, image, *, exposure: float = 1.0) -> None:
    """Write a linear RGB image `(H, W, 3)` (or grey `(H, W)`) as an 8-bit sRGB PNG.

    Non-finite values are written as black. `exposure` scales the image first.
    """
    arr = np.asarray(image, dtype=np.float64)
    if arr.ndim == 2:
        arr = np.repeat(arr[..., None], 3, axis=-1)
    if arr.ndim != 3 or arr.shape[-1] != 3:
        raise ValueError(f"`image` must have shape (H, W, 3) or (H, W), got {arr.shape}.")
    arr = np.where(np.isfinite(arr), arr, 0.0)
    pixels = to_srgb8(arr, exposure)
    height, width, _ = pixels.shape
    raw = b"".join(b"\x00" + row.tobytes() for row in pixels)  # filter type 0 per row
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)  # 8-bit RGB
    png = (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(raw, 9))
        + _chunk(b"IEND", b"")
    )
    with open(path, "wb") as f:
        f.write(png)

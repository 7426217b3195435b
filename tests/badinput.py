"""Hostile and awkward input files for ingest tests.

``make_bad_collection(folder, faces)`` writes a photo collection in which every file
exercises one way a real collection goes wrong (or is merely unusual but fine), and
returns what ingest must make of each: ``"ok"`` or a substring the rejection reason
must contain.

``make_bomb_png(path, width, height)`` writes a tiny PNG whose header claims a huge
size (a real 64x64 PNG with a patched IHDR): a decompression bomb that costs nothing
to make and must be rejected from its header alone.
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

EXIF_ORIENTATION = 0x0112

#: what each file of :func:`make_bad_collection` must give ("ok" or part of the reason)
EXPECTED = {
    "good.jpg": "ok",
    "corrupt.jpg": "corrupt",
    "notes.jpg": "not an image",
    "empty.jpg": "empty",
    "tiny.png": "too small",
    "sixteen_bit.png": "ok",
    "gray.jpg": "ok",
    "rgba.png": "ok",
    "rotated.jpg": "ok",
    "palette.png": "ok",
    # a name whose bytes are not UTF-8 (Python holds them as lone surrogates): a photo like any other
    os.fsdecode(b"bad\xff\xfename.jpg"): "ok",
}


def jpeg_bytes(image: np.ndarray, quality: int = 95, **save_kw) -> bytes:
    """An RGB or grey uint8 array as JPEG bytes (Pillow)."""
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="JPEG", quality=quality, **save_kw)
    return buf.getvalue()


def rgba_with_border(face: np.ndarray, border: int = 4, alpha: int = 64) -> np.ndarray:
    """``face`` with alpha 255 inside and ``alpha`` on a ``border``-pixel frame."""
    a = np.full(face.shape[:2], 255, np.uint8)
    a[:border] = a[-border:] = alpha
    a[:, :border] = a[:, -border:] = alpha
    return np.dstack([face, a])


def exif_rotated_jpeg(path: Path, face: np.ndarray, orientation: int = 6) -> None:
    """A JPEG whose stored pixels are ``face`` transformed so that EXIF ``orientation``
    (as applied by ``PIL.ImageOps.exif_transpose``) brings back the upright ``face``."""
    stored = {
        1: lambda a: a,
        2: lambda a: a[:, ::-1],
        3: lambda a: a[::-1, ::-1],
        4: lambda a: a[::-1],
        5: lambda a: a.swapaxes(0, 1),
        6: lambda a: np.rot90(a, 1),  # shown after rotating 90 degrees clockwise
        7: lambda a: a[::-1, ::-1].swapaxes(0, 1),
        8: lambda a: np.rot90(a, -1),  # shown after rotating 90 degrees counter-clockwise
    }[orientation](face)
    exif = Image.Exif()
    exif[EXIF_ORIENTATION] = orientation
    path.write_bytes(jpeg_bytes(np.ascontiguousarray(stored), exif=exif.tobytes()))


def make_bomb_png(path: Path, width: int = 30000, height: int = 30000) -> Path:
    """A ~100-byte PNG whose IHDR claims ``width`` x ``height`` (1-bit grey)."""
    buf = io.BytesIO()
    Image.new("1", (64, 64)).save(buf, format="PNG")
    data = bytearray(buf.getvalue())
    assert data[12:16] == b"IHDR"
    data[16:24] = struct.pack(">II", width, height)
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])) & 0xFFFFFFFF)
    Path(path).write_bytes(bytes(data))
    return Path(path)


def make_bad_collection(folder: Path, faces: Sequence[np.ndarray]) -> dict[str, str]:
    """Write a mixed good/bad collection into ``folder`` from >= 3 good RGB faces.

    Returns ``{filename: "ok" | substring of the rejection reason}``.
    """
    if len(faces) < 3:
        raise ValueError(f"make_bad_collection needs at least 3 faces, got {len(faces)}")
    faces = [np.ascontiguousarray(np.asarray(f, dtype=np.uint8)) for f in faces]
    for i, f in enumerate(faces[:3]):
        if f.ndim != 3 or f.shape[2] != 3:
            raise ValueError(f"face {i} must be (h, w, 3) uint8 RGB, got {f.shape}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)

    # a plain good JPEG
    (folder / "good.jpg").write_bytes(jpeg_bytes(faces[0]))

    # a good JPEG cut halfway, then garbage (deterministic)
    good = jpeg_bytes(faces[1])
    garbage = np.random.default_rng(0).integers(0, 256, 64, dtype=np.uint8).tobytes()
    (folder / "corrupt.jpg").write_bytes(good[: len(good) // 2] + garbage)

    # a text file with an image extension, and an empty one
    (folder / "notes.jpg").write_text("Photos from the 2004 trip; the good ones are in the other folder.\n")
    (folder / "empty.jpg").write_bytes(b"")

    # a 1x1 PNG
    Image.new("RGB", (1, 1), (200, 10, 10)).save(folder / "tiny.png")

    # 16-bit RGB PNG of faces[0] (OpenCV writes 16-bit; v * 257 maps 255 -> 65535)
    ok = cv2.imwrite(str(folder / "sixteen_bit.png"), faces[0][..., ::-1].astype(np.uint16) * 257)
    assert ok, "cv2.imwrite failed for the 16-bit PNG"

    # grayscale JPEG of faces[1]
    (folder / "gray.jpg").write_bytes(jpeg_bytes(np.asarray(Image.fromarray(faces[1]).convert("L"))))

    # RGBA PNG of faces[2]: opaque face, partly transparent border
    Image.fromarray(rgba_with_border(faces[2]), "RGBA").save(folder / "rgba.png")

    # EXIF-rotated JPEG of faces[0]: pixels stored rotated, Orientation 6 restores them
    exif_rotated_jpeg(folder / "rotated.jpg", faces[0], orientation=6)

    # palette PNG of faces[1], with a tRNS chunk (transparency as bytes): the case that
    # makes Pillow warn on a naive convert("RGBA")
    pal = Image.fromarray(faces[1]).quantize(colors=255)
    trns = bytes([255] * 255 + [0])  # index 255 (unused) is transparent
    pal.save(folder / "palette.png", transparency=trns)

    # a good JPEG whose file name is not UTF-8
    (folder / os.fsdecode(b"bad\xff\xfename.jpg")).write_bytes(jpeg_bytes(faces[2]))

    return dict(EXPECTED)

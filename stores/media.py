"""Media I/O for the ingest stage: photos, video frames, landmark sidecars, outputs.

Everything that touches image or video *files* lives here, so the rest of Persona
only ever sees NumPy arrays:

- :func:`resolve_sources` turns a workflow's ``photos:`` entry (folder, glob, list,
  image, video, or a video frame range) into a sorted list of :class:`Source`.
- :func:`decode_image` turns one photo into an ``(h, w, 3) uint8`` RGB array, or raises
  :class:`PhotoRejected` with a short, specific reason. A rejected photo is *data* (the
  ingest stage records the reason in ``status/ingest``), never a crash; no Pillow or
  OpenCV exception and no warning escapes.
- :class:`VideoReader` reads every frame of a video exactly, in order (PyAV).
- :func:`read_landmark_sidecar` / :func:`write_landmark_sidecar`: iBUG ``.pts`` files.
- :func:`write_png`, :func:`write_video_mp4` (H.264, yuv420p, even size) and
  :func:`contact_sheet` for the outputs people open. Writes are atomic: a temporary
  file in the same folder, then :func:`os.replace` (for a URL: a local temporary file, uploaded).

Any path may also be an fsspec URL (``s3://bucket/key``): every file is reached through
:mod:`persona.stores.storage`.

This module imports neither ``persona.plugins`` nor ``persona.dag``.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import tempfile
import threading
import warnings
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from struct import error as struct_error

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from persona.stores import storage
from persona.stores.errors import InputError

__all__ = [
    "PhotoRejected",
    "Source",
    "ImageInfo",
    "VIDEO_EXTENSIONS",
    "is_video",
    "resolve_sources",
    "probe_image",
    "decode_image",
    "fit_max_side",
    "sha256_file",
    "VideoReader",
    "read_landmark_sidecar",
    "write_landmark_sidecar",
    "write_png",
    "write_bytes",
    "atomic_path",
    "contact_sheet",
    "write_video_mp4",
    "write_videos_mp4",
]

log = logging.getLogger(__name__)

VIDEO_EXTENSIONS = frozenset({".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v"})
MIN_SIDE = 32
MAX_PIXELS = 64_000_000
MAX_SIDE = 1920  # a 1080p clip keeps its size
N_LANDMARKS = 68
_GREY = 128  # alpha is composited over this mid-grey
_GLOB_CHARS = frozenset("*?[")


class PhotoRejected(Exception):
    """One photo (or frame) cannot be used. Data, not a crash: record ``reason``.

    ``reason`` is short and specific, e.g. ``"empty file (0 bytes)"`` or
    ``"too small: 1x1 px (minimum 32 px a side)"``.
    """

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True)
class Source:
    """One input picture: a photo file, or one frame of a video.

    ``id`` is stable and unique within one :func:`resolve_sources` result: the file
    stem (:func:`printable`; a later file with the same stem gets ``_2``, ``_3``, ...) or
    ``frame000123`` for frame 123 of a video.
    """

    id: str
    path: str
    frame: int | None = None


@dataclass(frozen=True)
class ImageInfo:
    """Size of a photo as it will be decoded: after EXIF orientation, before any
    downscaling."""

    width: int
    height: int


# --------------------------------------------------------------------------- sources

#: the prefix of a stored path that is not UTF-8 (:func:`stored_path`); no absolute path or URL begins so
_FS_BYTES = "fsbytes:"


def stored_path(path: str) -> str:
    """``path`` as the store keeps it: itself, or where the file system's name is not valid UTF-8 (a file
    named by other bytes, which Python holds as lone surrogates and a store's UTF-8 strings cannot) its bytes
    in hex after ``fsbytes:``; :func:`opened_path` gives the path back."""
    try:
        path.encode("utf-8")
        return path
    except UnicodeEncodeError:
        return _FS_BYTES + os.fsencode(path).hex()


def opened_path(stored: str) -> str:
    """The path :func:`stored_path` stored, to open the file with."""
    return os.fsdecode(bytes.fromhex(stored[len(_FS_BYTES):])) if stored.startswith(_FS_BYTES) else stored


def printable(name: str) -> str:
    """``name`` with the bytes of a file name that are not UTF-8 written as ``\\xff``: a photo's id, shown in
    reports and kept in the store."""
    return name.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def is_video(path) -> bool:
    """True when ``path`` has a video extension (.mp4 .mov .avi .mkv .webm .m4v)."""
    return Path(path).suffix.lower() in VIDEO_EXTENSIONS


#: files beside photos that describe them (landmark sidecars): never listed as photos
SIDECAR_EXTENSIONS = (".pts",)


def _hidden(path) -> bool:
    """Hidden files and sidecars are not photos; any other file is, and decode judges it."""
    name = storage.name(path)
    return name.startswith(".") or os.path.splitext(name)[1].lower() in SIDECAR_EXTENSIONS


def _located(text, base_dir: Path):
    """(the path: a Path, or a URL string as given; how to name it in an error; what to check when it
    does not exist). A URL's bucket is reached first, so that a missing bucket or an unreachable
    endpoint is said as such."""
    raw = os.fspath(text)
    if storage.is_url(raw):
        storage.check(raw, "input")
        return raw, repr(raw), "check the URL (the bucket exists; the key or prefix does not)"
    p = Path(os.path.expanduser(raw))
    if not p.is_absolute():
        p = base_dir / p
    path = Path(os.path.abspath(p))
    where = f"{raw!r}" if str(raw) == str(path) else f"{raw!r} (resolved to {path})"
    return path, where, f"check the path (relative paths resolve against {base_dir})"


def _video_frame_count(path) -> int:
    with VideoReader(path) as reader:
        return reader.n_frames


def _frames_of(path, start: int = 0, stop: int | None = None, step: int = 1):
    n = _video_frame_count(path)
    return [(str(path), i) for i in range(n)[start:stop:step]]


def _member(path) -> list[tuple[str, int | None]]:
    """The entries of one file found in a folder or by a glob: a video's frames, or the file as a
    photo. A file named like a video that does not open as one is kept as a photo, so that ingest
    rejects it with its reason instead of one stray file stopping the whole collection (a video
    named on its own is an error: the user asked for it)."""
    if not is_video(path):
        return [(str(path), None)]
    try:
        return _frames_of(path)
    except InputError as exc:
        log.warning("%s", exc)
        return [(str(path), None)]


def _expand_string(text, base_dir: Path) -> list[tuple[str, int | None]]:
    raw = os.fspath(text)
    if not str(raw).strip():
        raise InputError(f"empty path in photos (relative to {base_dir}): give a folder, a glob, an image or a video")
    path, where, check = _located(raw, base_dir)
    if storage.isdir(path):
        files = [p for p in storage.entries_in(path) if not _hidden(p)]
        if not any(storage.isfile(p) for p in files):
            held = f" (it holds only {', '.join(Path(p).name for p in files[:3])}{', …' if len(files) > 3 else ''}; " \
                   "sub-folders are not searched)" if files else ""
            raise InputError(
                f"folder {where} is empty (no visible files){held}: put photos in it or point to another folder"
            )
        return [entry for f in files for entry in _member(f)]
    if storage.isfile(path):
        return _frames_of(path) if is_video(path) else [(str(path), None)]
    if any(c in str(raw) for c in _GLOB_CHARS):
        matches = [m for m in storage.glob(path) if not _hidden(m)]
        if not matches:
            raise InputError(f"glob pattern {where} matches no files: check the pattern and the folder")
        return [entry for f in matches for entry in _member(f)]
    if storage.exists(path):
        raise InputError(f"{where} is neither a file nor a folder: point photos to a folder, a glob, an image or a video")
    raise InputError(f"{where} does not exist: {check}")


def _as_int(spec: dict, key: str, default, *, minimum: int) -> int | None:
    value = spec.get(key, default)
    if value is None and default is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InputError(f"video frame range: {key!r} must be an integer, got {value!r}")
    if value < minimum:
        raise InputError(f"video frame range: {key!r} must be >= {minimum}, got {value}")
    return int(value)


def _expand_range(spec: dict, base_dir: Path) -> list[tuple[str, int | None]]:
    allowed = {"video", "start", "stop", "step"}
    unknown = sorted(set(spec) - allowed)
    if unknown:
        raise InputError(
            f"video frame range: unknown key(s) {unknown}; allowed keys are {sorted(allowed)}"
        )
    if "video" not in spec:
        raise InputError("video frame range: missing key 'video' (the path of the video file)")
    start = _as_int(spec, "start", 0, minimum=0)
    stop = _as_int(spec, "stop", None, minimum=0)
    step = _as_int(spec, "step", 1, minimum=1)
    raw = spec["video"]
    path, where, check = _located(raw, base_dir)
    if not storage.isfile(path):
        raise InputError(f"video {where} does not exist: {check}")
    n = _video_frame_count(path)
    frames = range(n)[start:stop:step]
    if not frames:
        raise InputError(
            f"video {where}: frame range start={start} stop={stop} step={step} selects no frames "
            f"(the video has {n} frames, 0..{n - 1})"
        )
    return [(str(path), i) for i in frames]


def resolve_sources(spec, base_dir) -> list[Source]:
    """Expand a ``photos:`` entry into sources.

    ``spec`` is one of:

    - a folder: everything visible in it, sorted by name, not recursive (files of every
      extension, sub-folders and links whose target is gone are listed, so that a text file
      named ``x.jpg``, a folder or a dangling link reaches :func:`decode_image` and is rejected
      there with a reason; a video gives its frames, and a file named like a video that does
      not open is kept as a photo to reject, not an error);
    - a glob pattern (``*``, ``?``, ``[``), sorted, hidden files skipped;
    - a single image file;
    - a video file (by extension, see :func:`is_video`): every frame;
    - a dict ``{"video": path, "start": 0, "stop": None, "step": 1}``: a frame range,
      with Python slice semantics (``stop`` is exclusive and may exceed the length);
    - a list of any of the above, concatenated in order.

    Relative paths resolve against ``base_dir``. The same (path, frame) reached twice
    (say by a folder and an overlapping glob) is listed once, at its first place.
    Ids: the file stem, with ``_2``, ``_3``, ... for later files with a stem already
    taken; ``frame000123`` for video frames (with the same suffix rule when several
    videos are listed).

    Raises :class:`InputError` naming the path when something does not exist, matches
    nothing, or is an empty folder or frame range.
    """
    base = Path(os.path.abspath(os.path.expanduser(os.fspath(base_dir))))
    items = spec if isinstance(spec, (list, tuple)) else [spec]
    if not items:
        raise InputError("photos: the list is empty; give at least one folder, glob, image or video")
    entries: list[tuple[str, int | None]] = []
    for item in items:
        if isinstance(item, dict):
            entries.extend(_expand_range(item, base))
        elif isinstance(item, (str, os.PathLike)):
            entries.extend(_expand_string(item, base))
        else:
            raise InputError(
                f"photos: cannot use {item!r} ({type(item).__name__}); give a path string, "
                "a list of paths, or {'video': path, 'start': 0, 'stop': None, 'step': 1}"
            )
    seen: set[tuple[str, int | None]] = set()
    taken: set[str] = set()
    out: list[Source] = []
    for path, frame in entries:
        if (path, frame) in seen:
            continue
        seen.add((path, frame))
        stem = f"frame{frame:06d}" if frame is not None else printable(Path(path).stem)
        ident, k = stem, 1
        while ident in taken:
            k += 1
            ident = f"{stem}_{k}"
        taken.add(ident)
        out.append(Source(id=ident, path=path, frame=frame))
    return out


# --------------------------------------------------------------------------- photos


def _mp(n: int) -> str:
    return f"{n / 1e6:.0f} MP" if n >= 1e6 else f"{n / 1e6:.2g} MP"


def _open_checked(path, max_pixels: int, min_side: int) -> tuple[Image.Image, object, int]:
    """Open the header, check size limits. Returns (image, file handle, orientation).

    Must be called inside ``_quiet_warnings()``.
    """
    try:
        size, folder = storage.stat(path)
    except FileNotFoundError:
        if not storage.is_url(path) and os.path.islink(path):
            raise PhotoRejected(f"a link to {os.readlink(path)}, which does not exist") from None
        raise PhotoRejected(f"file not found: {path}") from None
    except OSError as e:
        raise PhotoRejected(f"cannot read file: {e.strerror or e}") from None
    if folder:
        raise PhotoRejected("not an image (a folder)")
    if size == 0:
        raise PhotoRejected("empty file (0 bytes)")
    try:
        fh = storage.open_file(path, "rb")
    except OSError as e:
        raise PhotoRejected(f"cannot read file: {e.strerror or e}") from None
    try:
        img = Image.open(fh)
    except Image.DecompressionBombError as e:
        fh.close()
        raise PhotoRejected(_pil_bomb_reason(e, max_pixels)) from None
    except UnidentifiedImageError:
        fh.close()
        raise PhotoRejected("not an image (cannot identify image file)") from None
    except Exception as e:  # noqa: BLE001 - Pillow raises many kinds on bad headers
        fh.close()
        raise PhotoRejected(f"not an image (bad header: {_short(e)})") from None
    try:
        w, h = img.size
        if w * h > max_pixels:
            raise PhotoRejected(
                f"decompression bomb: {w}x{h} = {_mp(w * h)} exceeds max_pixels {_mp(max_pixels)}"
            )
        if min(w, h) < min_side:
            raise PhotoRejected(f"too small: {w}x{h} px (minimum {min_side} px a side)")
        orientation = _orientation(img)
    except BaseException:
        img.close()
        fh.close()
        raise
    return img, fh, orientation


def _pil_bomb_reason(e: BaseException, max_pixels: int) -> str:
    """Pillow's own limit fired (in Image.open, before our check could): say it our way."""
    m = re.search(r"\((\d+) pixels\).*?limit of (\d+) pixels", str(e))
    if not m:
        return f"decompression bomb: {_short(e)}"
    n, limit = int(m.group(1)), int(m.group(2))
    return (
        f"decompression bomb: header claims {_mp(n)}, over Pillow's limit of {_mp(limit)} "
        f"(max_pixels {_mp(max_pixels)})"
    )


_quiet_lock = threading.Lock()
_quiet_depth = 0
_quiet_saved: list | None = None


@contextlib.contextmanager
def _quiet_warnings():
    """Silence warnings (Pillow's EXIF, palette and size warnings) while decoding.

    ``warnings.catch_warnings()`` saves and restores the process-global filter list;
    with several threads decoding at once (a Dask worker's threads) the enter/exit
    pairs interleave and can leave ``"ignore"`` installed for good. Here the first
    thread in installs the filter and the last one out restores the saved list, under
    a lock. (While any decode runs, other threads' warnings are silenced too.)
    """
    global _quiet_depth, _quiet_saved
    with _quiet_lock:
        if _quiet_depth == 0:
            _quiet_saved = list(warnings.filters)
            warnings.simplefilter("ignore")
        _quiet_depth += 1
    try:
        yield
    finally:
        with _quiet_lock:
            _quiet_depth -= 1
            if _quiet_depth == 0:
                warnings.filters[:] = _quiet_saved
                _quiet_saved = None
                mutated = getattr(warnings, "_filters_mutated", None)
                if mutated is not None:  # invalidate the per-module "already warned" caches
                    mutated()


def _short(e: BaseException, limit: int = 160) -> str:
    """The error's message on one line, at most ``limit`` characters; for OS-level errors (PyAV's
    among them) the plain reason, without the "[Errno N]" and the path repeated."""
    text = (getattr(e, "strerror", None) or str(e)).strip() or type(e).__name__
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _orientation(img: Image.Image) -> int:
    """EXIF orientation 1..8 (1 when absent or unreadable)."""
    try:
        if img.format == "PNG":
            # PngImageFile.getexif() decodes the whole image to look for an eXIf chunk
            # after the pixels; read only an eXIf chunk found in the header
            raw = img.info.get("exif")
            if not raw:
                return 1
            exif = Image.Exif()
            exif.load(raw)
        else:
            exif = img.getexif()
        value = int(exif.get(0x0112, 1))
    except Exception:  # noqa: BLE001 - a broken EXIF block is not worth rejecting a photo
        return 1
    return value if 1 <= value <= 8 else 1


def _apply_orientation(a: np.ndarray, orientation: int) -> np.ndarray:
    """The NumPy equivalent of ``PIL.ImageOps.exif_transpose`` for orientation 1..8."""
    if orientation == 2:
        return a[:, ::-1]
    if orientation == 3:
        return a[::-1, ::-1]
    if orientation == 4:
        return a[::-1]
    if orientation == 5:
        return a.swapaxes(0, 1)
    if orientation == 6:
        return np.rot90(a, -1)
    if orientation == 7:
        return a[::-1, ::-1].swapaxes(0, 1)
    if orientation == 8:
        return np.rot90(a, 1)
    return a


def probe_image(path, *, max_pixels: int = MAX_PIXELS, min_side: int = MIN_SIDE) -> ImageInfo:
    """Size of a photo from its header only (no pixel decoding), after EXIF orientation.

    Raises :class:`PhotoRejected` for a missing, empty, unidentifiable, too small or
    too large (decompression bomb) file. A photo that passes can still be rejected by
    :func:`decode_image` (e.g. a truncated body).
    """
    with _quiet_warnings():
        img, fh, orientation = _open_checked(path, max_pixels, min_side)
        try:
            w, h = img.size
        finally:
            img.close()
            fh.close()
    return ImageInfo(width=h, height=w) if orientation >= 5 else ImageInfo(width=w, height=h)


def _to_uint8(a: np.ndarray) -> np.ndarray:
    """Scale an integer or float array to uint8 (16-bit -> /257 rounded, not clipped)."""
    if a.dtype == np.uint8:
        return a
    if a.dtype == np.bool_:
        return a.astype(np.uint8) * 255
    if np.issubdtype(a.dtype, np.floating):
        a = np.nan_to_num(a.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
        hi = float(a.max()) if a.size else 0.0
        if hi <= 1.0:
            a = a * 255.0
        elif hi > 255.0:
            a = a * (255.0 / 65535.0) if hi <= 65535.0 else a * (255.0 / hi)
        return np.clip(np.rint(a), 0, 255).astype(np.uint8)
    # integers: 16-bit data (uint16, or Pillow's 32-bit "I" holding 16-bit values)
    if a.dtype.itemsize == 1:
        return np.clip(a, 0, 255).astype(np.uint8)
    a64 = a.astype(np.float64)
    hi = float(a64.max()) if a.size else 0.0
    if a.dtype == np.uint16 or a.dtype == np.dtype(">u2") or hi > 255.0:
        scale = 255.0 / 65535.0 if hi <= 65535.0 else 255.0 / hi
        a64 = a64 * scale
    return np.clip(np.rint(a64), 0, 255).astype(np.uint8)


def _composite(rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Composite ``rgb`` (uint8) over mid-grey with ``alpha`` (uint8, 255 = opaque)."""
    a = alpha.astype(np.float32)[..., None] / 255.0
    out = rgb.astype(np.float32) * a + _GREY * (1.0 - a)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def _is_16bit_colour(img: Image.Image) -> bool:
    """Pillow reads 16-bit RGB(A)/LA by keeping the high byte; we want proper rounding."""
    if img.mode not in ("RGB", "RGBA", "LA"):
        return False
    try:
        return any(";16" in str(getattr(t, "args", t[3] if len(t) > 3 else "")) for t in img.tile)
    except Exception:  # noqa: BLE001
        return False


def _decode_16bit_cv2(path) -> np.ndarray:
    """A 16-bit colour PNG/TIFF through OpenCV: (h, w, 3|4) RGB(A) or (h, w, 2) LA, uint8."""
    data = np.frombuffer(storage.read_bytes(path), dtype=np.uint8)
    a = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)  # UNCHANGED: no EXIF rotation here
    if a is None:
        raise PhotoRejected("corrupt 16-bit image: OpenCV cannot decode it")
    a = _to_uint8(a)
    if a.ndim == 3 and a.shape[2] == 3:
        a = a[..., ::-1]
    elif a.ndim == 3 and a.shape[2] == 4:
        a = a[..., [2, 1, 0, 3]]
    return a


def _pil_to_array(img: Image.Image) -> np.ndarray:
    """A loaded Pillow image -> (h, w) | (h, w, 2|3|4) uint8, alpha last where present."""
    mode = img.mode
    if mode == "P" or mode == "PA":
        if "transparency" in img.info:
            img.apply_transparency()  # palette alpha; avoids Pillow's bytes-transparency warning
        has_alpha = mode == "PA" or img.palette is not None and img.palette.mode == "RGBA"
        img = img.convert("RGBA" if has_alpha else "RGB")
        return np.asarray(img)
    if mode in ("L", "RGB") and "transparency" in img.info:
        return np.asarray(img.convert("LA" if mode == "L" else "RGBA"))
    if mode in ("1",):
        return np.asarray(img.convert("L"))
    if mode in ("L", "LA", "RGB", "RGBA"):
        return np.asarray(img)
    if mode in ("La", "RGBa", "PA"):
        return np.asarray(img.convert("RGBA"))
    if mode.startswith("I;16") or mode in ("I", "F"):
        a = np.asarray(img)
        if mode.startswith("I;16"):
            a = a.astype(np.uint16)  # also un-byteswaps I;16B
        return _to_uint8(a)
    # CMYK, YCbCr, LAB, HSV, ...: Pillow knows how to get to RGB
    return np.asarray(img.convert("RGB"))


def _to_rgb(a: np.ndarray) -> np.ndarray:
    if a.ndim == 2:
        return np.repeat(a[..., None], 3, axis=2)
    c = a.shape[2]
    if c == 1:
        return np.repeat(a, 3, axis=2)
    if c == 2:
        return _to_rgb(_composite(a[..., :1], a[..., 1]))
    if c == 3:
        return a
    if c == 4:
        if a[..., 3].min() == 255:
            return a[..., :3]
        return _composite(a[..., :3], a[..., 3])
    raise PhotoRejected(f"unsupported image: {c} channels")


def fit_max_side(image: np.ndarray, max_side: int) -> np.ndarray:
    """Downscale (cv2.INTER_AREA) so the longer side is <= ``max_side``; never upscales."""
    h, w = image.shape[:2]
    if max_side is None or max(h, w) <= max_side:
        return image
    s = max_side / max(h, w)
    size = (max(1, min(max_side, round(w * s))), max(1, min(max_side, round(h * s))))
    return cv2.resize(np.ascontiguousarray(image), size, interpolation=cv2.INTER_AREA)


def decode_image(
    path,
    *,
    max_side: int = MAX_SIDE,
    max_pixels: int = MAX_PIXELS,
    min_side: int = MIN_SIDE,
) -> np.ndarray:
    """Decode one photo to an ``(h, w, 3) uint8`` RGB array, C-contiguous.

    - EXIF orientation is applied (as ``PIL.ImageOps.exif_transpose`` does).
    - 16-bit images are scaled to 8-bit (``round(v / 257)``), not clipped; 16-bit
      colour PNG/TIFF go through OpenCV, since Pillow keeps only the high byte.
    - 1, L, LA, P (palette, with or without transparency), RGBA, CMYK, ... -> RGB;
      alpha is composited over mid-grey (128).
    - The longer side is downscaled (``cv2.INTER_AREA``) to at most ``max_side``.
    - Decompression bombs: the header's width x height is checked against
      ``max_pixels`` before any pixel is decoded. Pillow's own limit
      (``Image.MAX_IMAGE_PIXELS``, about 89 MP; an error at twice that) still applies
      when ``max_pixels`` is set higher, and is reported the same way.
    - Every failure raises :class:`PhotoRejected` with a specific reason; no Pillow or
      OpenCV exception and no warning escapes (see :func:`_quiet_warnings`: safe
      with many decoding threads, unlike a bare ``warnings.catch_warnings()``).
    """
    with _quiet_warnings():
        img, fh, orientation = _open_checked(path, max_pixels, min_side)
        fmt = img.format or "image"
        try:
            if _is_16bit_colour(img):
                img.close()
                fh.close()
                a = _decode_16bit_cv2(path)
            else:
                if fmt == "JPEG" and max_side and max(img.size) > 2 * max_side:
                    # DCT-domain downscale by 1/2, 1/4 or 1/8, never below the target size
                    s = max_side / max(img.size)
                    img.draft(img.mode, (math.ceil(img.size[0] * s), math.ceil(img.size[1] * s)))
                try:
                    img.load()
                except Image.DecompressionBombError as e:
                    raise PhotoRejected(_pil_bomb_reason(e, max_pixels)) from None
                except (OSError, SyntaxError, ValueError, EOFError, IndexError, struct_error) as e:
                    raise PhotoRejected(f"corrupt or truncated {fmt}: {_short(e)}") from None
                if fmt == "PNG" and orientation == 1:
                    orientation = _orientation(img)  # an eXIf chunk after the pixels
                a = _pil_to_array(img)
        except PhotoRejected:
            raise
        except MemoryError:
            raise PhotoRejected("out of memory decoding the image") from None
        except Exception as e:  # noqa: BLE001 - never let a decoder exception escape
            raise PhotoRejected(f"cannot decode {fmt}: {type(e).__name__}: {_short(e)}") from None
        finally:
            img.close()
            fh.close()
        try:
            a = _to_rgb(_to_uint8(a))
            a = _apply_orientation(a, orientation)
            a = fit_max_side(a, max_side)
        except PhotoRejected:
            raise
        except Exception as e:  # noqa: BLE001
            raise PhotoRejected(f"cannot convert {fmt} to RGB: {type(e).__name__}: {_short(e)}") from None
    return np.ascontiguousarray(a, dtype=np.uint8)


sha256_file = storage.sha256_file  # photos' identity in the store (one home: stores.storage)


# --------------------------------------------------------------------------- video


@contextlib.contextmanager
def _av_open(path, **kwargs):
    """PyAV's container of a video, closed on exit; raises :class:`InputError` naming the video when
    it does not open. A local video is opened by name; a URL's on a file object read through fsspec,
    in which PyAV reads and seeks as in a local file (s3fs fetches the byte ranges asked for, with
    read-ahead), so a video in object storage is streamed, not copied to a temporary file first."""
    import av  # local: importing PyAV is not free and only video needs it

    with contextlib.ExitStack() as stack:
        source = stack.enter_context(storage.open_file(path, "rb")) if storage.is_url(path) else str(path)
        try:
            container = av.open(source, **kwargs)
        except Exception as e:  # noqa: BLE001 - av.error.* and friends
            raise InputError(f"cannot read video {path}: {_short(e)}; check that it is a complete, "
                             "playable video file") from None
        with container:
            yield container


class VideoReader:
    """Exact, in-order frame reading with PyAV.

    ``fps`` (the stream's average rate), ``n_frames`` (from the container; counted by
    decoding when the container does not say), ``width`` and ``height`` (as displayed:
    a rotation in the stream's display matrix, as phones write, is applied to frames
    and swaps width and height for 90 degrees).

    Each call of :meth:`frames` decodes from the start, so frame indices are exact
    (seeking in compressed video is only keyframe-exact).
    """

    def __init__(self, path):
        self.path = os.fspath(path) if storage.is_url(path) else Path(os.path.abspath(os.fspath(path)))
        p = self.path
        try:
            size, folder = storage.stat(p)
        except FileNotFoundError:
            raise InputError(f"video {p} does not exist: check the path") from None
        if folder:
            raise InputError(f"video {p} is a folder, not a video file")
        if size == 0:
            raise InputError(f"video {p} is an empty file (0 bytes): re-export or re-download it")
        try:
            with _av_open(p) as container:
                fmt = container.format.name or ""
                if fmt == "image2" or fmt.endswith("_pipe"):
                    raise InputError(f"{p} is a still image ({fmt}), not a video")
                if not container.streams.video:
                    raise InputError(f"{p} has no video stream: give a video file")
                stream = container.streams.video[0]
                cc = stream.codec_context
                rate = stream.average_rate or stream.guessed_rate or stream.base_rate
                self.fps = float(rate) if rate else 0.0
                self._declared_frames = int(stream.frames or 0)
                w, h = int(cc.width), int(cc.height)
            if w <= 0 or h <= 0:
                raise InputError(f"video {p}: cannot read the frame size; is the file complete?")
            # the display rotation is per frame side data in FFmpeg: read the first frame
            frames = self._decode()
            try:
                first = next(frames, None)
            finally:
                frames.close()
            if first is None:
                raise InputError(f"video {p} has no decodable frames")
            self._rotation = float(getattr(first, "rotation", 0) or 0)
        except InputError:
            raise
        except Exception as e:  # noqa: BLE001 - av.error.* and friends
            raise InputError(
                f"cannot read video {p}: {_short(e)}; check that it is a complete, playable video file"
            ) from None
        self._k = int(round(self._rotation / 90.0)) % 4
        self.width, self.height = (h, w) if self._k % 2 else (w, h)
        self._n_frames: int | None = self._declared_frames or None

    @property
    def n_frames(self) -> int:
        if self._n_frames is None:
            self._n_frames = sum(1 for _ in self._decode())
        return self._n_frames

    def _decode(self):
        """Yield decoded av.VideoFrame objects from a fresh container, in order."""
        with _av_open(self.path) as container:
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            i = 0
            it = container.decode(stream)
            while True:
                try:
                    frame = next(it)
                except StopIteration:
                    return
                except Exception as e:  # noqa: BLE001
                    raise InputError(
                        f"video {self.path}: decoding failed after frame {i - 1}: {_short(e)}; "
                        "the file may be truncated or corrupt"
                    ) from None
                yield frame
                i += 1

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(index, (h, w, 3) uint8 RGB)`` for frames ``start, start+step, ... < stop``."""
        if start < 0 or step < 1 or (stop is not None and stop < 0):
            raise ValueError(f"frames(start={start}, stop={stop}, step={step}): need start >= 0, stop >= 0, step >= 1")
        count = 0
        for i, frame in enumerate(self._decode()):
            if stop is not None and i >= stop:
                break
            if i >= start and (i - start) % step == 0:
                a = frame.to_ndarray(format="rgb24")
                if self._k:
                    a = np.rot90(a, self._k)
                yield i, np.ascontiguousarray(a)
            count = i + 1
        if stop is None and count != self._n_frames:
            if self._n_frames is not None:
                log.info("%s: container says %d frames, decoding gave %d; using %d",
                         self.path, self._n_frames, count, count)
            self._n_frames = count

    def close(self) -> None:
        """Nothing stays open between calls (each decodes from a fresh container): a no-op, so that a
        reader is also a context manager."""

    def __enter__(self) -> VideoReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"VideoReader({str(self.path)!r}, {self.width}x{self.height}, fps={self.fps:g})"


def read_video_frame(path, index: int, *, max_side: int = MAX_SIDE) -> np.ndarray:
    """Frame ``index`` of a video as a photo of a collection: ``(h, w, 3) uint8`` RGB, the longer
    side downscaled to at most ``max_side``. Decodes from the start, so the index is exact
    (seeking is only keyframe-exact); for the many frames of one video in a row, use
    :meth:`VideoReader.frames`. Raises :class:`PhotoRejected` when the frame cannot be decoded."""
    try:
        with VideoReader(path) as reader:
            for _, image in reader.frames(index, index + 1):
                return fit_max_side(image, max_side)
    except InputError as exc:
        raise PhotoRejected(str(exc)) from None
    raise PhotoRejected(f"frame {index} could not be decoded: the video ends before it")


# --------------------------------------------------------------------------- landmarks


def _sidecar_path(image_path):
    return storage.with_suffix(image_path, ".pts")


def read_landmark_sidecar(image_path) -> np.ndarray | None:
    """Landmarks from an iBUG ``.pts`` file next to the image (same stem), or None.

    Returns ``(68, 2) float64`` (x, y) in **0-based pixel-centre coordinates**:
    (0, 0) is the centre of the top-left pixel. This is what
    :func:`write_landmark_sidecar` writes. (The original iBUG 300-W annotations are
    1-based, MATLAB style: subtract 1 when importing those.)

    Raises :class:`PhotoRejected` ``("bad landmark sidecar foo.pts: ...")`` for a
    malformed file.
    """
    pts = _sidecar_path(image_path)
    if not storage.isfile(pts):
        return None

    def bad(why: str) -> PhotoRejected:
        return PhotoRejected(f"bad landmark sidecar {storage.name(pts)}: {why}")

    try:
        text = storage.read_text(pts)
    except (OSError, UnicodeDecodeError) as e:
        raise bad(f"cannot read it ({_short(e)})") from None
    lines = [ln.strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln and not ln.startswith("//") and not ln.startswith("#")]
    header: dict[str, str] = {}
    i = 0
    while i < len(lines) and lines[i] != "{":
        key, sep, value = lines[i].partition(":")
        if not sep:
            raise bad(f"expected 'key: value' or '{{', got {lines[i][:40]!r}")
        header[key.strip().lower()] = value.strip()
        i += 1
    if i == len(lines):
        raise bad("no '{' opening the point list")
    if "n_points" not in header:
        raise bad("missing 'n_points:' line")
    try:
        n = int(header["n_points"])
    except ValueError:
        raise bad(f"n_points is not an integer: {header['n_points']!r}") from None
    if n != N_LANDMARKS:
        raise bad(f"{n} points, expected {N_LANDMARKS}")
    try:
        close = lines.index("}", i + 1)
    except ValueError:
        raise bad("no '}' closing the point list") from None
    body = lines[i + 1 : close]
    if len(body) != n:
        raise bad(f"n_points says {n} but the list has {len(body)} lines")
    try:
        xy = np.array([[float(v) for v in ln.split()] for ln in body], dtype=np.float64)
    except ValueError as e:
        raise bad(f"not a number: {_short(e)}") from None
    if xy.shape != (n, 2):
        raise bad("each point line must hold exactly two numbers 'x y'")
    if not np.isfinite(xy).all():
        raise bad("non-finite coordinate (nan or inf)")
    return xy


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


#: the process's umask, read once at import (reading it means setting it, which is not thread-safe)
_UMASK = _umask()


@contextlib.contextmanager
def atomic_path(path, suffix: str | None = None) -> Iterator[str]:
    """A temporary file beside ``path`` to write; it replaces ``path`` only if the block
    succeeds, and is removed otherwise, so an interrupted write never leaves half a file.
    ``suffix`` (default: the path's own) lets writers that pick a format by extension work.
    The file gets the mode any new file would (0666 less the umask), not the temporary
    file's private 0600. For a URL the temporary file is local and is uploaded when the block
    succeeds (an object store's upload is atomic itself)."""
    if storage.is_url(path):
        with storage.local_file(path, suffix or os.path.splitext(str(path))[1] or ".tmp") as tmp:
            yield tmp
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=suffix or path.suffix or ".tmp")
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_bytes(path, data: bytes) -> None:
    """Write a file atomically (a temporary file in the same folder, then os.replace)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(data)


def write_landmark_sidecar(image_path, landmarks: np.ndarray) -> Path:
    """Write ``landmarks`` ((68, 2) x, y; 0-based pixel centres) as an iBUG ``.pts``
    next to the image; returns its path. Values round-trip exactly."""
    xy = np.asarray(landmarks, dtype=np.float64)
    if xy.shape != (N_LANDMARKS, 2):
        raise ValueError(f"landmarks must have shape ({N_LANDMARKS}, 2), got {xy.shape}")
    if not np.isfinite(xy).all():
        raise ValueError("landmarks contain nan or inf")
    lines = ["version: 1", f"n_points: {N_LANDMARKS}", "{"]
    lines += [f"{float(x)!r} {float(y)!r}" for x, y in xy]
    lines += ["}", ""]
    out = _sidecar_path(image_path)
    write_bytes(out, "\n".join(lines).encode("utf-8"))
    return out


# --------------------------------------------------------------------------- outputs


def _check_uint8_image(image: np.ndarray, what: str = "image") -> np.ndarray:
    a = np.asarray(image)
    if a.dtype != np.uint8:
        raise TypeError(f"{what} must be uint8, got {a.dtype}")
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)):
        raise ValueError(f"{what} must be (h, w) or (h, w, 3), got shape {a.shape}")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"{what} is empty: shape {a.shape}")
    return a


def png_bytes(image: np.ndarray, what: str = "image") -> bytes:
    """A uint8 (h, w) grey or (h, w, 3) RGB image encoded as PNG."""
    a = _check_uint8_image(image, what)
    if a.ndim == 3:
        a = a[..., ::-1]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(a))
    if not ok:
        raise OSError(f"OpenCV could not encode {what} as a PNG")
    return buf.tobytes()


def write_png(path, image: np.ndarray) -> None:
    """Write a uint8 (h, w) grey or (h, w, 3) RGB image as PNG, atomically
    (a temporary file in the same folder, then ``os.replace``); creates parent folders."""
    write_bytes(path, png_bytes(image))


def contact_sheet(
    images: Sequence[np.ndarray], *, columns: int = 10, gap: int = 2, background=255
) -> np.ndarray:
    """Tile equal-size uint8 images (grey or RGB) row by row into one RGB image.

    ``gap`` pixels of ``background`` separate the tiles (none around the border).
    Grey tiles are promoted to RGB.
    """
    if len(images) == 0:
        raise ValueError("contact_sheet: no images")
    if columns < 1 or gap < 0:
        raise ValueError(f"contact_sheet: need columns >= 1 and gap >= 0, got {columns}, {gap}")
    tiles = [_check_uint8_image(im, f"image {i}") for i, im in enumerate(images)]
    h, w = tiles[0].shape[:2]
    for i, t in enumerate(tiles):
        if t.shape[:2] != (h, w):
            raise ValueError(f"contact_sheet: image {i} is {t.shape[1]}x{t.shape[0]}, expected {w}x{h}")
    cols = min(columns, len(tiles))
    rows = math.ceil(len(tiles) / cols)
    sheet = np.empty((rows * h + (rows - 1) * gap, cols * w + (cols - 1) * gap, 3), np.uint8)
    sheet[...] = np.asarray(background, dtype=np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, cols)
        y, x = r * (h + gap), c * (w + gap)
        sheet[y : y + h, x : x + w] = t[..., None] if t.ndim == 2 else t
    return sheet


def _rate(fps: float) -> Fraction:
    if not (fps > 0 and math.isfinite(fps)):
        raise ValueError(f"fps must be positive and finite, got {fps}")
    ntsc = Fraction(round(fps * 1.001) * 1000, 1001)
    if round(fps) != fps and abs(float(ntsc) - fps) < 1e-3:
        return ntsc  # 29.97 -> 30000/1001
    return Fraction(fps).limit_denominator(1001)


@dataclass(frozen=True)
class Audio:
    """Decoded sound: ``samples`` (channels, n) float32 in [-1, 1] at ``rate`` Hz."""

    samples: np.ndarray
    rate: int


def read_audio(path, start: float = 0.0, stop: float | None = None) -> Audio | None:
    """The first audio stream of a video from ``start`` to ``stop`` seconds (of the stream's own
    clock, which starts at its first sample), or None when the file has no sound."""
    import av

    with _av_open(path) as container:
        if not container.streams.audio:
            return None
        stream = container.streams.audio[0]
        resampler = av.AudioResampler(format="fltp", layout="stereo" if stream.channels > 1 else "mono",
                                      rate=stream.rate)
        chunks = []
        for frame in container.decode(stream):
            for out in resampler.resample(frame):
                chunks.append(out.to_ndarray())
        for out in resampler.resample(None):
            chunks.append(out.to_ndarray())
        if not chunks:
            return None
        samples = np.concatenate(chunks, axis=1).astype(np.float32)
        first = int(round(start * stream.rate))
        last = samples.shape[1] if stop is None else int(round(stop * stream.rate))
        return Audio(np.ascontiguousarray(samples[:, max(first, 0):last]), int(stream.rate))


def _add_audio_stream(container, audio: Audio):
    """An AAC stream for ``audio`` (added with the video's, before anything is written)."""
    stream = container.add_stream("aac", rate=audio.rate)
    stream.codec_context.layout = "stereo" if audio.samples.shape[0] > 1 else "mono"
    stream.codec_context.format = "fltp"
    stream.codec_context.time_base = Fraction(1, audio.rate)
    return stream


def _encode_audio(containers, streams, audio: Audio, duration: float) -> None:
    """Encode ``audio``, cut or padded with silence to ``duration`` seconds, once, into ``streams[0]``,
    and copy every packet into the other streams (each of its own container): the same sound for
    several videos at the cost of one."""
    import av

    def mux(packet):
        for container, stream in zip(containers[1:], streams[1:]):
            copy = av.Packet(bytes(packet))
            copy.pts, copy.dts, copy.time_base = packet.pts, packet.dts, packet.time_base
            copy.duration, copy.is_keyframe, copy.stream = packet.duration, packet.is_keyframe, stream
            container.mux(copy)
        containers[0].mux(packet)

    n = int(round(duration * audio.rate))
    samples = np.zeros((audio.samples.shape[0], n), np.float32)
    take = min(n, audio.samples.shape[1])
    samples[:, :take] = audio.samples[:, :take]
    encoder = streams[0]
    size = encoder.codec_context.frame_size or 1024
    for offset in range(0, n, size):
        frame = av.AudioFrame.from_ndarray(np.ascontiguousarray(samples[:, offset:offset + size]), format="fltp",
                                           layout=encoder.codec_context.layout.name)
        frame.sample_rate, frame.pts, frame.time_base = audio.rate, offset, Fraction(1, audio.rate)
        for packet in encoder.encode(frame):
            mux(packet)
    for packet in encoder.encode(None):
        mux(packet)


#: libx264's settings for every video Persona writes: constant quality 18 (visually lossless), and the
#: ``ultrafast`` preset, which encodes in about half of ``veryfast``'s CPU time at that quality, in files about
#: three times larger (a 720p face at about 5 Mbit/s): every drive writes three videos, while the evaluation
#: runs (docs/CHANGELOG.md, 2026-12-05)
X264 = {"crf": "18", "preset": "ultrafast"}


def write_video_mp4(path, frames: Iterable[np.ndarray], fps: float, audio: Audio | None = None) -> None:
    """Encode uint8 RGB (or grey) frames as H.264 (libx264, yuv420p) MP4 with PyAV, with ``audio``
    (AAC, cut or padded to the frames' duration) when given.

    Odd sizes are padded to even by repeating the last row/column (yuv420p needs even
    sizes). All frames must have the first frame's size. Written atomically (temporary
    file in the same folder, then ``os.replace``); ``+faststart`` so that browsers can
    play it while loading.
    """
    write_videos_mp4([path], ((image,) for image in frames), fps, audio)


def _add_video_stream(container, rate: Fraction, size: tuple[int, int]):
    """An H.264 stream (:data:`X264`) of even ``size`` (height, width) at ``rate`` frames a second."""
    stream = container.add_stream("libx264", rate=rate)
    stream.height, stream.width = size
    stream.pix_fmt = "yuv420p"
    stream.options = dict(X264)
    stream.codec_context.time_base = 1 / rate
    return stream


def write_videos_mp4(paths: Sequence, frames: Iterable[Sequence[np.ndarray]], fps: float,
                     audio: Audio | None = None) -> None:
    """:func:`write_video_mp4` for several videos of the same timing in one pass: each item of
    ``frames`` holds one image for each of ``paths``, so that what the images are made of is read
    once, and the sound is encoded once and copied into each. All the files are written, or none."""
    import av

    rate = _rate(float(fps))
    with contextlib.ExitStack() as files:
        temps = [files.enter_context(atomic_path(path, ".mp4")) for path in paths]
        containers = [files.enter_context(contextlib.closing(
            av.open(tmp, mode="w", format="mp4", options={"movflags": "+faststart"}))) for tmp in temps]
        streams = sizes = sound = None
        n = 0
        for i, images in enumerate(frames):
            arrays = [_check_uint8_image(image, f"frame {i}") for image in images]
            arrays = [np.repeat(a[..., None], 3, axis=2) if a.ndim == 2 else a for a in arrays]
            if sizes is None:
                sizes = [a.shape[:2] for a in arrays]
                streams = [_add_video_stream(c, rate, (h + h % 2, w + w % 2)) for c, (h, w) in zip(containers, sizes)]
                sound = [_add_audio_stream(c, audio) for c in containers] if audio is not None else None
            for a, size, stream, container in zip(arrays, sizes, streams, containers):
                if a.shape[:2] != size:
                    raise ValueError(
                        f"frame {i} is {a.shape[1]}x{a.shape[0]}, expected {size[1]}x{size[0]} like frame 0"
                    )
                even = (stream.height, stream.width)
                if even != size:
                    a = np.pad(a, ((0, even[0] - size[0]), (0, even[1] - size[1]), (0, 0)), mode="edge")
                # the stream's yuv420p made by OpenCV: BT.601 video range as libswscale would (Y within 1 level),
                # in a quarter of its time
                vf = av.VideoFrame.from_ndarray(cv2.cvtColor(np.ascontiguousarray(a), cv2.COLOR_RGB2YUV_I420),
                                                format="yuv420p")
                vf.pts, vf.time_base = i, 1 / rate
                for packet in stream.encode(vf):
                    container.mux(packet)
            n += 1
        if streams is None:
            raise ValueError(f"write_video_mp4({', '.join(map(str, paths))}): no frames")
        for stream, container in zip(streams, containers):
            for packet in stream.encode(None):
                container.mux(packet)
        if sound is not None:
            _encode_audio(containers, sound, audio, n / float(rate))

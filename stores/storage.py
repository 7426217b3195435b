"""Where files live: a local path or an fsspec URL (``s3://bucket/key``), behind one set of helpers.

Every file Persona reads or writes outside the Zarr store (photos, videos, landmark sidecars, the
pictures, videos, meshes and reports of the output) goes through these functions, so that workers
on machines without a shared file system cooperate through object storage. A local path goes
through Python's own ``os``, ``glob`` and ``open``; a URL goes through fsspec (``s3fs`` for
``s3://``, installed with ``pip install 'persona[s3]'``).

The storage options of ``s3://`` URLs (endpoint, credentials) are the workflow's
``storage_options``, set once per process with :func:`configure` (the runner does it on every Dask
worker too); what they leave unset comes from the standard AWS environment variables
(``AWS_ENDPOINT_URL``, ``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``, ``AWS_DEFAULT_REGION``) or
``~/.aws``. Credentials live only here, never in a URL, so they never reach provenance, metrics or
reports.

This module imports neither ``persona.plugins`` nor ``persona.dag``.
"""

from __future__ import annotations

import builtins
import contextlib
import functools
import glob as globlib
import hashlib
import os
import posixpath
import tempfile
from collections.abc import Iterator
from pathlib import Path

from .errors import StorageError

#: storage options of s3:// URLs, set by :func:`configure` (empty: the environment's)
_S3_OPTIONS: dict = {}
S3_PROTOCOLS = ("s3", "s3a")
HINT = ("check the URL, storage_options.endpoint_url (or AWS_ENDPOINT_URL) and that the server is running, "
        "and the credentials (storage_options.key/secret, AWS_ACCESS_KEY_ID/AWS_SECRET_ACCESS_KEY, "
        "or anon: true for a public bucket)")


def is_url(path) -> bool:
    """True for an fsspec URL such as ``s3://bucket/key``; False for a local path."""
    return "://" in str(path)


def configure(options: dict | None) -> None:
    """Set this process's storage options of s3:// URLs (s3fs keyword arguments such as
    ``endpoint_url``, ``key``, ``secret``, ``anon``); None or {} = the environment's."""
    _S3_OPTIONS.clear()
    _S3_OPTIONS.update(options or {})


def options(url: str) -> dict:
    """The storage options to open ``url`` with (fsspec's ``storage_options``)."""
    protocol = str(url).split("://", 1)[0]
    if protocol in S3_PROTOCOLS:
        return dict(_S3_OPTIONS)
    return {"auto_mkdir": True} if protocol in ("file", "local") else {}  # file://: folders made as needed


def filesystem(url: str):
    """(fsspec filesystem, path inside it) of a URL, with the configured storage options."""
    import fsspec

    try:
        return fsspec.core.url_to_fs(str(url), **options(url))
    except ImportError as exc:
        raise StorageError(f"{url}: {exc}; install Persona with object storage: pip install 'persona[s3]'") from None
    except ValueError as exc:  # an unknown protocol
        raise StorageError(f"{url}: {exc}") from None


def join(base, *names: str):
    """``base/name/...``: a :class:`Path` for a local ``base``, a URL string for a URL."""
    if is_url(base):
        return posixpath.join(str(base).rstrip("/"), *names)
    return Path(base).joinpath(*names)


def with_suffix(path, suffix: str):
    """``path`` with its extension replaced by ``suffix`` (as :meth:`Path.with_suffix`)."""
    if is_url(path):
        return posixpath.splitext(str(path))[0] + suffix
    return Path(path).with_suffix(suffix)


def name(path) -> str:
    """The last part of a path or URL."""
    return posixpath.basename(str(path).rstrip("/")) if is_url(path) else Path(path).name


# -- asking -------------------------------------------------------------------------------

def stat(path) -> tuple[int, bool]:
    """(size in bytes, is a folder) of an existing file or folder; FileNotFoundError when absent,
    OSError when it cannot be read."""
    if not is_url(path):
        s = os.stat(path)
        return s.st_size, os.path.isdir(path)
    fs, p = filesystem(path)
    info = fs.info(p)
    return int(info.get("size") or 0), info.get("type") == "directory"


def signature(path) -> tuple:
    """What changes when a file's content does, for cache keys: (size, SHA-256 of the bytes) for a
    local file, so that copying or provisioning the same photos again (new modification times)
    keeps every stage's results; (size, ETag or modification time) for a URL; (-1, -1) when it
    cannot be read."""
    try:
        if not is_url(path):
            s = os.stat(path)
            return s.st_size, _content_hash(os.path.realpath(path), s.st_size, s.st_mtime_ns)
        fs, p = filesystem(path)
        info = fs.info(p)
        return int(info.get("size") or 0), str(info.get("ETag") or info.get("LastModified") or info.get("mtime"))
    except OSError:
        return -1, -1


@functools.lru_cache(maxsize=65536)
def _content_hash(path: str, size: int, mtime_ns: int) -> str:
    """:func:`sha256_file` of a local file, once per process while its size and modification time
    stay (every frame of a video names the same file)."""
    return sha256_file(path)


def sha256_file(path) -> str:
    """Hex SHA-256 of a file's bytes, read in 1 MiB chunks."""
    digest = hashlib.sha256()
    with open_file(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _ask(path, local, method: str) -> bool:
    """``local(path)`` for a local path, else the fsspec filesystem's ``method`` on the URL."""
    if not is_url(path):
        return local(path)
    fs, p = filesystem(path)
    return getattr(fs, method)(p)


def isfile(path) -> bool:
    return _ask(path, os.path.isfile, "isfile")


def isdir(path) -> bool:
    return _ask(path, os.path.isdir, "isdir")


def exists(path) -> bool:
    return _ask(path, os.path.exists, "exists")


def entries_in(folder) -> list:
    """What is directly in ``folder``, sorted: for a local folder every entry as a Path (files,
    sub-folders, links whose target is gone: whatever is not a photo is rejected at ingest with its
    reason, not passed over in silence); for a URL, its files' URLs."""
    if not is_url(folder):
        return sorted(Path(folder).iterdir())
    fs, p = filesystem(folder)
    return sorted(fs.unstrip_protocol(e["name"]) for e in fs.ls(p, detail=True) if e["type"] == "file")


def glob(pattern) -> list:
    """The files matching a glob pattern, sorted: Paths for a local pattern (Python's :mod:`glob`:
    hidden files only when named), URLs for a URL."""
    if not is_url(pattern):
        return sorted(Path(m) for m in globlib.glob(str(pattern)) if os.path.isfile(m))
    fs, p = filesystem(pattern)
    found = fs.glob(p, detail=True)
    return sorted(fs.unstrip_protocol(k) for k, e in found.items() if e["type"] == "file")


# -- reading and writing ------------------------------------------------------------------

def open_file(path, mode: str = "rb"):
    """A file object for ``path``: :func:`open` locally; through fsspec for a URL (seekable: reads
    fetch byte ranges on demand)."""
    if not is_url(path):
        return builtins.open(path, mode)
    fs, p = filesystem(path)
    return fs.open(p, mode)


def read_bytes(path) -> bytes:
    with open_file(path, "rb") as f:
        return f.read()


def read_text(path) -> str:
    return read_bytes(path).decode("utf-8")


def remove(path) -> None:
    """Delete the file ``path``, local or a URL; none there is no error."""
    if not is_url(path):
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
        return
    fs, p = filesystem(path)
    with contextlib.suppress(FileNotFoundError):
        fs.rm_file(p)


@contextlib.contextmanager
def local_file(url, suffix: str = "") -> Iterator[str]:
    """A local temporary file to write, uploaded to ``url`` when the block succeeds (and removed
    either way). For writers that need a file name (OpenCV, PyAV, open3d)."""
    fd, tmp = tempfile.mkstemp(prefix="persona.", suffix=suffix)
    os.close(fd)
    try:
        yield tmp
        fs, p = filesystem(url)
        fs.put_file(tmp, p)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)


# -- clear errors before work starts ------------------------------------------------------

def check(url: str, what: str) -> None:
    """Raise :class:`StorageError` naming ``url`` and what to check when its bucket cannot be reached
    (missing bucket, unreachable endpoint, no or wrong credentials). A local path is not checked."""
    if not is_url(url):
        return
    fs, p = filesystem(url)
    if "file" in fs.protocol:  # a file:// URL: a local path, nothing to reach
        return
    bucket = p.split("/", 1)[0]
    with translated(url, what, missing=f"bucket {bucket!r} does not exist: create it, or correct the URL or the endpoint"):
        if not fs.exists(bucket):
            fs.ls(bucket)  # raises the reason: no such bucket, an unreachable endpoint, refused credentials


@contextlib.contextmanager
def translated(url: str, what: str, missing: str = "not found (no such bucket or key)") -> Iterator[None]:
    """Turn the errors of reaching ``url`` (a missing bucket or key, an unreachable endpoint, missing
    or refused credentials) into a :class:`StorageError` that names it and says what to check."""
    try:
        yield
    except StorageError:
        raise
    except FileNotFoundError:
        raise StorageError(f"{what} {url}: {missing}; {HINT}") from None
    except PermissionError as exc:
        raise StorageError(f"{what} {url}: access denied ({exc}); {HINT}") from None
    except Exception as exc:  # noqa: BLE001 - botocore's and aiohttp's connection and credential errors
        raise StorageError(f"{what} {url}: cannot reach it ({type(exc).__name__}: {exc}); {HINT}") from None


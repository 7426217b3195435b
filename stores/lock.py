"""One writer per store: a run holds the store's lock while it writes.

Two runs writing one store at once race each other's arrays: one of them stops with advice that does
not help, or both finish with a store neither made. ``persona run`` therefore takes the store's lock
(:func:`writer`) before it creates anything and gives it back at the end, whatever the end. The lock is
a small JSON file in the store, ``.persona-lock.json``: who holds it (host, process, since when) and when
it was last renewed. It works alike on a local disk and in object storage, where there are no POSIX
locks: the holder renews it every ``RENEW`` seconds, and a lock not renewed for ``STALE`` seconds, or
held by a process of this machine that no longer exists, was left by a run that was killed; the next
run takes it over and says so.

Taking it is a write and a read back: two runs that start within the same second could both find the
store free, and the read back leaves the lock to the last one that wrote it; the other stops.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
import threading
import time
import uuid
from collections.abc import Iterator
from datetime import datetime, timezone

from . import storage
from .errors import PersonaError

log = logging.getLogger(__name__)

#: the lock's file in the store's root (Zarr ignores it)
NAME = ".persona-lock.json"

#: how often (s) the holder renews the lock, and after how long without (s) a lock is stale
RENEW = 30.0
STALE = 300.0


class StoreLocked(PersonaError, RuntimeError):
    """The store is being written by another run."""


def _path(url: str) -> str:
    return str(storage.join(url, NAME))


def holder(url: str) -> dict | None:
    """Who holds the lock of the store at ``url`` (its JSON), or None when no one does; ``{}`` for a lock file
    cut short by a kill while it was written, which is stale (never renewed)."""
    try:
        return json.loads(storage.read_text(_path(url)))
    except FileNotFoundError:
        return None
    except json.JSONDecodeError:
        return {}


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: it exists
        return True
    return True


def stale(held: dict, now: float | None = None) -> bool:
    """True when the lock ``held`` was left by a run that is no longer running: one of this machine whose
    process is gone, or one not renewed for ``STALE`` seconds."""
    now = time.time() if now is None else now
    if held.get("host") == socket.gethostname() and not _alive(int(held.get("pid", -1))):
        return True
    return now - float(held.get("renewed", 0)) > STALE


def describe(held: dict | None) -> str:
    """The holder in words: process, host and since when (:func:`holder`'s answer)."""
    if held is None:
        return "no run now: it has let the lock go"
    if not held:
        return "a lock file cut short"
    return f"process {held.get('pid')} on {held.get('host')}, since {held.get('since')}"


def _write(url: str, lock: dict) -> None:
    with storage.open_file(_path(url), "w") as f:
        f.write(json.dumps(lock))


@contextlib.contextmanager
def writer(url: str) -> Iterator[dict]:
    """Hold the lock of the store at ``url`` for the block (the store's folder is created if needed).
    Raises :class:`StoreLocked` naming the holder when another run that is still running holds it."""
    held = holder(url)
    if held is not None and not stale(held):
        raise StoreLocked(f"the store {url} is being written by another run ({describe(held)}): wait for it to "
                          f"end, or stop it; if it was killed, its lock ({_path(url)}) is taken over "
                          f"{STALE / 60:.0f} minutes after it was last renewed (at once on {held.get('host')})")
    if held is not None:
        log.warning("the store's lock was left by a run that no longer runs (%s): taken over", describe(held))
    if not storage.is_url(url):
        os.makedirs(url, exist_ok=True)
    me = {"host": socket.gethostname(), "pid": os.getpid(), "token": uuid.uuid4().hex,
          "since": datetime.now(timezone.utc).isoformat(timespec="seconds"), "renewed": time.time()}
    try:  # from the first byte written: a SIGTERM or Ctrl-C while taking the lock still gives it back
        _write(url, me)
        if _token(url) != me["token"]:  # another run took it in the same moment
            raise StoreLocked(f"the store {url} is being written by another run ({describe(holder(url))}), "
                              "which started at the same time: wait for it to end")
        with _renewing(url, me):
            yield me
    finally:
        if _token(url) in (me["token"], None):  # ours, or our own write cut short
            with contextlib.suppress(FileNotFoundError):
                storage.remove(_path(url))


def _token(url: str) -> str | None:
    """The token of the lock's holder (None when there is no lock or its file was cut short)."""
    return (holder(url) or {}).get("token")


@contextlib.contextmanager
def _renewing(url: str, me: dict) -> Iterator[None]:
    """Renew the lock ``me`` every ``RENEW`` seconds for the block, until another run takes it."""
    done = threading.Event()

    def renew():
        while not done.wait(RENEW):
            if _token(url) != me["token"]:
                log.warning("the store's lock was taken by another run (%s)", describe(holder(url)))
                return
            _write(url, {**me, "renewed": time.time()})

    thread = threading.Thread(target=renew, name="persona-store-lock", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()

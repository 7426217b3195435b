"""The Zarr v3 layout of a Persona store.

::

    run.zarr/
      puppet/                     a collection: one actor's photos (photo axis first)
        photos/ids, photos/source, photos/frame, photos/sha256, photos/size
        photos/rgb                (photo, y, x, 3) uint8, padded to the collection's canvas
        photos/hint               (photo, 68, 2) float32, landmarks from sidecar files (NaN if none)
        status/<stage>/state      (photo,) int8: 0 pending, 1 ok, 2 rejected here, 3 rejected upstream
        status/<stage>/reason     (photo,) str: why a photo was rejected
        landmarks/points          (photo, 68, 2) float32 ; landmarks/fiducials (photo, 49, 2)
        landmarks/box, landmarks/n_faces
        pose                      (photo, 10) float64 (rx ry rz tx ty tz f cx cy rms)
        aligned/rgb               (photo, y, x, 3) uint8 ; aligned/mask (photo, y, x) bool
        aligned/landmarks         (photo, 68, 2) ; aligned/fiducials (photo, 49, 2)
        aligned/mean              (y, x, 3) float32
      driver/                     the driver's photos, the same arrays
      driver/frames/              the driver's video frames, the same arrays (+ fps)
      drive/                      the puppet performing the video: one item per frame

A store of a format-2 workflow (many people, many drives) holds each person once, each video
once and each drive once: ``people/<name>/``, ``videos/<name>/``, ``drives/<name>/``. A drive
records which collections it was made from (its :class:`Cast`).

Per-photo images have one photo per chunk and ``photos_per_shard`` photos per shard;
small per-photo values (landmarks, pose, status) are chunked by shard. A shard is the
write unit: one task writes whole shards, no two tasks the same one. Every chunk carries a
checksum and is written even when empty (:mod:`.chunks`), so :mod:`.verify` can tell a lost
or damaged shard from one never written.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zarr

from . import storage
from .chunks import COMPRESSORS
from .errors import PersonaError
from .provenance import Provenance

PENDING, OK, REJECTED, UPSTREAM = 0, 1, 2, 3
STATE_NAMES = {PENDING: "pending", OK: "ok", REJECTED: "rejected", UPSTREAM: "rejected upstream"}
LAYOUT_VERSION = 1


class StoreError(PersonaError, ValueError):
    """The store is missing, not a Persona store, or inconsistent."""


class StoreUnreadable(StoreError):
    """The store cannot be opened at all (its root is damaged, or it is not a Persona store): running again
    as it is cannot help."""


def open_store(url: str, mode: str = "a") -> zarr.Group:
    """Open (or create, with mode "a") a Persona store at a local path or fsspec URL (an ``s3://``
    URL with the storage options of :mod:`persona.stores.storage`)."""
    try:
        root = zarr.open_group(str(url), mode=mode, zarr_format=3,
                               storage_options=storage.options(url) if storage.is_url(url) else None)
    except Exception as exc:
        storage.check(url, "store")  # a missing bucket, an unreachable endpoint, refused credentials
        if isinstance(exc, FileNotFoundError):
            raise StoreError(f"no Persona store at {url}: run `persona run WORKFLOW` first") from None
        raise StoreUnreadable(f"cannot open {url} as a Zarr v3 store ({type(exc).__name__}: {exc}): its root "
                              "metadata (zarr.json) is damaged or not Zarr's; restore it, or move the store aside "
                              "and run again to make it anew") from exc
    if mode != "r" and "persona" not in root.attrs:
        root.attrs["persona"] = {"layout": LAYOUT_VERSION}
    if "persona" not in root.attrs:
        raise StoreUnreadable(f"{url} is a Zarr store but not a Persona store (no 'persona' attribute): set "
                              "store: to another path")
    return root


#: per-photo items at least this large (bytes) get a chunk of their own inside shards
IMAGE_BYTES = 4096


@dataclass(frozen=True)
class Cast:
    """Where one drive's collections are in the store: B's photos (``puppet``), A's photos (``driver``,
    whose average face is the driver's model), A's video frames (``frames``) and the drive itself
    (``drive``: B performing the frames, one item per frame). The defaults are a format-1 store's."""

    puppet: str = "puppet"
    driver: str = "driver"
    frames: str = "driver/frames"
    drive: str = "drive"

    @classmethod
    def of(cls, root: zarr.Group, drive: str) -> "Cast":
        """The cast the drive at ``drive`` records (a format-1 store's drive records none: the defaults)."""
        return cls(**{**dict(root[drive].attrs).get("cast", {}), "drive": drive})

    def record(self, group: zarr.Group) -> None:
        """Record the cast in the drive's group (:meth:`of` reads it back)."""
        group.attrs["cast"] = {"puppet": self.puppet, "driver": self.driver, "frames": self.frames}


@dataclass
class Collection:
    """One collection of photos (or video frames) in a store, e.g. ``puppet`` or ``driver/frames``."""

    root: zarr.Group
    path: str
    _arrays: dict = field(default_factory=dict, repr=False)

    @property
    def group(self) -> zarr.Group:
        return self.root[self.path]

    @property
    def attrs(self) -> dict:
        return dict(self.group.attrs)

    @property
    def n(self) -> int:
        return int(self.group.attrs["n_photos"])

    @property
    def shard(self) -> int:
        return int(self.group.attrs["photos_per_shard"])

    def exists(self) -> bool:
        try:
            return "n_photos" in self.root[self.path].attrs
        except KeyError:
            return False

    def shard_ranges(self) -> list[tuple[int, int]]:
        return [(s, min(s + self.shard, self.n)) for s in range(0, self.n, self.shard)]

    # -- arrays ------------------------------------------------------------------
    def create(self, name: str, tail: tuple[int, ...], dtype, dims: tuple[str, ...],
               provenance: Provenance, fill_value: Any = None, *, pending: bool = False,
               by_shard: bool = False) -> zarr.Array:
        """(Re)create a per-photo array of shape (n, *tail).

        Images get one photo per chunk, ``photos_per_shard`` chunks per shard; small
        per-photo values get one chunk per shard. Either way a shard of photos is one file.
        ``by_shard``: images only ever written and read a whole shard at a time get one chunk per
        shard too (each chunk costs a decode: B's texture cache, read by every worker of a drive,
        reads 2-3 times faster so). ``pending``: the array is filled later and counts as done
        (has its provenance) only once :meth:`mark_done` is called after the last write, so that
        a run killed half-way leaves an array the next run recomputes rather than trusts.
        """
        if len(dims) != 1 + len(tail):
            raise ValueError(f"{name}: {len(dims)} dimension names for {1 + len(tail)} dimensions")
        shape = (self.n, *tail)
        if dtype is str or np.dtype(dtype).kind in "OTU":
            dtype, chunks, shards = str, (self.shard,), None
        elif np.dtype(dtype).itemsize * int(np.prod(tail)) >= IMAGE_BYTES and not by_shard:
            chunks, shards = (1, *tail), (self.shard, *tail)
        else:
            chunks, shards = (self.shard, *tail), None
        if fill_value is None:
            fill_value = np.nan if np.dtype(dtype).kind == "f" else 0
        array = self.group.create_array(
            name, shape=shape, dtype=dtype, chunks=chunks, shards=shards,
            dimension_names=dims, fill_value=fill_value, compressors=COMPRESSORS, overwrite=True)
        if not pending:
            array.attrs["provenance"] = provenance.model_dump()
        self._arrays[name] = array
        return array

    def mark_done(self, name: str, provenance: Provenance) -> None:
        """Record that a ``pending`` array is complete: its provenance, written after its data."""
        self.array(name).attrs["provenance"] = provenance.model_dump()

    def create_single(self, name: str, data: np.ndarray, dims: tuple[str, ...],
                      provenance: Provenance) -> zarr.Array:
        """A collection-level array (e.g. the mean face), written at once."""
        array = self.group.create_array(name, shape=data.shape, dtype=data.dtype, chunks=data.shape,
                                        dimension_names=dims, compressors=COMPRESSORS, overwrite=True)
        array[...] = data
        array.attrs["provenance"] = provenance.model_dump()
        return array

    def array(self, name: str) -> zarr.Array:
        if name not in self._arrays:
            try:
                self._arrays[name] = self.group[name]
            except KeyError:
                raise StoreError(f"{self.path}/{name} is not in the store: run the stage that makes it") from None
            except Exception as exc:  # e.g. its zarr.json is not JSON
                raise StoreError(f"{self.path}/{name}: its metadata cannot be read ({type(exc).__name__}: {exc}); "
                                 "run the workflow again: a run replaces arrays it cannot open") from exc
        return self._arrays[name]

    def rows(self, name: str, rows: np.ndarray) -> np.ndarray:
        """The photos ``rows`` (in that order) of a per-photo array, read a shard at a time: in each
        shard that holds some, the one slice from the first to the last of them (rows that follow one
        another: their one slice, as read). zarr's orthogonal indexing (``.oindex``) reads a sharded
        array chunk by chunk, 7-15 times slower (100 of Obama's 252 aligned photos: 0.63 s against
        0.09 s), and reading the whole array takes memory in proportion to the collection."""
        array, rows = self.array(name), np.asarray(rows, np.int64).reshape(-1)
        if len(rows) and (np.diff(rows) == 1).all():  # one run of photos: their slice, not copied again
            return array[rows[0]:rows[-1] + 1]
        out = np.empty((len(rows), *array.shape[1:]), array.dtype)
        shard = rows // self.shard
        for s in np.unique(shard):
            where = np.flatnonzero(shard == s)
            lo, hi = int(rows[where].min()), int(rows[where].max()) + 1
            out[where] = array[lo:hi][rows[where] - lo]
        return out

    def in_order(self, name: str) -> "InOrder":
        """The per-photo array ``name`` for a pass over its photos in increasing order: :class:`InOrder`."""
        return InOrder(self.array(name), self.shard)

    def remove(self, *names: str) -> None:
        """Delete the arrays or groups ``names`` that exist: an earlier run's outputs that this run
        does not make again, so that nothing later reads them as its own."""
        for name in names:
            if name in self.group:
                del self.group[name]

    def has(self, name: str) -> bool:
        try:
            self.array(name)
            return True
        except StoreError:
            return False

    def provenance(self, name: str) -> Provenance | None:
        if not self.has(name):
            return None
        raw = self.group[name].attrs.get("provenance")
        return Provenance.model_validate(raw) if raw else None

    def made_by(self, name: str, provenance: Provenance) -> bool:
        """Whether the array ``name`` is done and was made with ``provenance`` (the same cache key:
        backend, version, params, inputs): the one test of "this step has nothing to redo"."""
        current = self.provenance(name)
        return current is not None and current.key == provenance.key

    # -- status ------------------------------------------------------------------
    def create_status(self, stage: str, provenance: Provenance) -> None:
        """A stage's status, every photo pending. The reasons first: the state is what a run tests (made by
        this stage's provenance?), so a run killed between the two leaves no state, and the next run makes
        both again rather than meet a state without its reasons."""
        self.create(f"status/{stage}/reason", (), str, ("photo",), provenance, fill_value="")
        self.create(f"status/{stage}/state", (), np.int8, ("photo",), provenance, fill_value=PENDING)

    def state(self, stage: str) -> np.ndarray:
        if not self.has(f"status/{stage}/state"):
            return np.zeros(self.n, np.int8)
        return self.array(f"status/{stage}/state")[:]

    def reasons(self, stage: str) -> np.ndarray:
        return self.array(f"status/{stage}/reason")[:]

    def write_status(self, stage: str, start: int, state: np.ndarray, reasons: list[str]) -> None:
        """Written last by a task, after its outputs: a shard counts as done only then."""
        stop = start + len(state)
        self.array(f"status/{stage}/reason")[start:stop] = np.asarray(reasons, dtype=object).astype(str)
        self.array(f"status/{stage}/state")[start:stop] = state

    def stages(self) -> list[str]:
        try:
            return sorted(self.group["status"].group_keys())
        except KeyError:
            return []


class InOrder:
    """A per-photo array indexed one photo at a time, read a whole shard at a time and the last shard read
    kept: for a pass over consecutive frames. A photo read alone costs about what its whole shard does
    (an aligned frame of a video, 5 ms a read on a drive's client: 0.7 s of the retargeting of 136 frames)."""

    def __init__(self, array: zarr.Array, shard: int):
        self.array, self.shard, self.start, self.block = array, shard, -1, None

    def __len__(self) -> int:
        return self.array.shape[0]

    def __getitem__(self, i: int) -> np.ndarray:
        start = i - i % self.shard
        if start != self.start:
            self.start, self.block = start, self.array[start:start + self.shard]
        return self.block[i - start]


def collections(root: zarr.Group) -> list[Collection]:
    """Every collection in the store, in a stable order."""
    found = []

    def walk(group: zarr.Group, path: str):
        if "n_photos" in group.attrs:
            found.append(Collection(root, path))
        for name, child in sorted(group.groups()):
            if name not in ("status", "photos", "landmarks", "aligned"):
                walk(child, f"{path}/{name}" if path else name)

    walk(root, "")
    return found


def first_rejection(collection: Collection, stages: list[str]) -> tuple[np.ndarray, list[str]]:
    """Final state per photo (OK / REJECTED / PENDING) and the reason of the stage that rejected it."""
    n = collection.n
    final = np.full(n, OK, np.int8)
    why = [""] * n
    for stage in stages:
        if not collection.has(f"status/{stage}/state"):
            final[final == OK] = PENDING
            continue
        state = collection.state(stage)
        reasons = collection.reasons(stage)
        for i in np.flatnonzero((state == REJECTED) & (final == OK)):
            final[i] = REJECTED
            why[i] = f"{stage}: {reasons[i]}"
        final[(state == PENDING) & (final == OK)] = PENDING
    return final, why


def rejections(collection: Collection) -> dict[str, list[str]]:
    """The ids of the rejected photos by the reason they were rejected for (the first stage that did),
    the most common reason first: what ``metrics.json`` and the report list."""
    stages = list(collection.attrs.get("stages", collection.stages()))
    final, why = first_rejection(collection, stages)
    ids = collection.array("photos/ids")[:]
    out: dict[str, list[str]] = {}
    for i in np.flatnonzero(final == REJECTED):
        out.setdefault(why[i], []).append(str(ids[i]))
    return dict(sorted(out.items(), key=lambda kv: -len(kv[1])))


def summarize(url: str) -> dict:
    """What ``persona inspect`` shows: each collection's photo counts by outcome, the stages that
    built its arrays (and arrays left unfinished), its arrays, and for a person the drives that use it."""
    root = open_store(url, mode="r")
    out: dict[str, Any] = {"store": str(url), "collections": {}}
    for c in collections(root):
        stages = list(c.attrs.get("stages", c.stages()))
        final, why = first_rejection(c, stages)
        by_reason: dict[str, int] = {}
        for i in np.flatnonzero(final == REJECTED):
            by_reason[why[i]] = by_reason.get(why[i], 0) + 1
        arrays, built, unfinished = {}, {}, []

        def walk(group: zarr.Group, prefix: str):
            for name, arr in sorted(group.arrays()):
                arrays[prefix + name] = {"shape": list(arr.shape), "dtype": str(arr.dtype),
                                         "dims": list(arr.metadata.dimension_names or ())}
                made = arr.attrs.get("provenance")
                if not made:
                    unfinished.append(prefix + name)
                elif made["stage"] not in built or made["created"] < built[made["stage"]]["created"]:
                    built[made["stage"]] = {k: made[k] for k in ("backend", "key", "created")}
            for name, child in sorted(group.groups()):
                if "n_photos" not in child.attrs:
                    walk(child, f"{prefix}{name}/")

        walk(c.group, "")
        per_stage = {}
        for s in stages:
            state = c.state(s)
            per_stage[s] = {STATE_NAMES[k]: int((state == k).sum()) for k in STATE_NAMES}
        out["collections"][c.path] = {
            "n_photos": c.n,
            "accepted": int((final == OK).sum()),
            "rejected": int((final == REJECTED).sum()),
            "pending": int((final == PENDING).sum()),
            "rejected_by_reason": dict(sorted(by_reason.items(), key=lambda kv: -kv[1])),
            "rejections": {str(root[c.path]["photos/ids"][i]): why[i] for i in np.flatnonzero(final == REJECTED)},
            "stages": per_stage,
            # by stage in the order they ran, from the provenance of the arrays each made
            "built": dict(sorted(built.items(), key=lambda kv: kv[1]["created"])),
            "unfinished": unfinished,  # arrays created but not marked done: a run stopped while making them
            "arrays": arrays,
            "attrs": {k: v for k, v in c.attrs.items() if k in ("source", "fps", "canvas", "video", "cast")},
        }
    for path, c in out["collections"].items():  # a person or a video is built once for every drive it is in
        c["used_by"] = sorted(drive for drive, d in out["collections"].items()
                              if path in d["attrs"].get("cast", {}).values())
    return out

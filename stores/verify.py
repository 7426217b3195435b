"""Verified chunks: find lost and damaged chunks of a store, and make the next run recompute them.

An array *done* by its stage (it has its ``provenance``) must have every chunk file its shape
and chunk grid call for: for the arrays of a per-photo stage, every shard holding a photo the
stage accepted (its ``status/<stage>/state``); for any other array, every chunk. Arrays with
checksums write every chunk even when it holds only the fill value (:mod:`.chunks`), so a
missing file is a loss; arrays from before checksums are read but not counted.

:func:`check` lists the problems: missing chunk files (listing the store's keys, cheap), and,
with ``read=True``, chunks that cannot be decoded (every chunk read, its checksum checked), and
arrays whose metadata cannot be read. :func:`recover` makes a run recompute each problem's
array and everything computed from it: provenance keys chain through ``inputs`` (a stage's key
hashes its inputs' keys, not their data), so every array whose key depends on a damaged one
loses its provenance too, and each stage sees its outputs as not done.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import zarr
from zarr.core.sync import sync

from .chunks import ChunkError, has_checksums
from .layout import OK, open_store
from .paths import array_of, item

#: how many photo ids a problem names before "and N more"
SHOWN_IDS = 8


@dataclass(frozen=True)
class Problem:
    """One lost or damaged piece of a store."""

    array: str  #: the array's (or group's) path in the store
    what: str  #: "missing", "damaged (the error)" or "metadata cannot be read (the error)"
    chunk: str = ""  #: the chunk file's key in the store ("" for metadata)
    shard: int | None = None  #: the chunk's index along the first axis
    items: str = ""  #: the photos or frames it holds: "photos 48–63: ids a, b, …"
    stage: str | None = None  #: the stage that wrote the array (None: unknown, or not done yet)

    def __str__(self) -> str:
        where = "" if self.shard is None else f": shard {self.shard}" + (f" ({self.items})" if self.items else "")
        return f"{self.array}{where} {self.what}"


@dataclass
class _Scan:
    """A store's keys, arrays (by path), nodes whose metadata cannot be read, and collections."""

    root: zarr.Group
    keys: set[str]
    arrays: dict[str, zarr.Array] = field(default_factory=dict)
    broken: dict[str, str] = field(default_factory=dict)
    collections: dict[str, int] = field(default_factory=dict)  #: path -> number of photos
    accepted: dict = field(default_factory=dict)  #: status path -> photos it accepted (read once)

    def collection(self, path: str) -> str | None:
        inside = [c for c in self.collections if path.startswith(c + "/")]
        return max(inside, key=len) if inside else None

    def provenance(self, path: str) -> dict | None:
        return self.arrays[path].attrs.get("provenance")


def _keys(root: zarr.Group) -> set[str]:
    """Every key of the store under ``root``, relative to it."""
    base = root.store_path.path  # "" when the store is the root group, as open_store makes it

    async def listing():
        return {key[len(base):].lstrip("/") async for key in root.store.list_prefix(base)}

    return sync(listing())


def _scan(root: zarr.Group) -> _Scan:
    scan = _Scan(root, _keys(root))
    nodes = sorted({key.rpartition("/")[0] for key in scan.keys if key.endswith("/zarr.json")})
    for path in nodes:
        try:
            node = root[path]
        except Exception as exc:  # a zarr.json that is not JSON, or not zarr's
            scan.broken[path] = f"{type(exc).__name__}: {exc}"
            continue
        if isinstance(node, zarr.Array):
            scan.arrays[path] = node
        elif "n_photos" in node.attrs:
            scan.collections[path] = int(node.attrs["n_photos"])
    return scan


def _blocks(array: zarr.Array):
    """(coordinates, store key, region) of every chunk (of every shard, for sharded arrays)."""
    size = array.shards or array.chunks
    for coords in np.ndindex(*(math.ceil(s / b) for s, b in zip(array.shape, size))):
        region = tuple(slice(c * b, min((c + 1) * b, s)) for c, b, s in zip(coords, size, array.shape))
        yield coords, f"{array.path}/{array.metadata.encode_chunk_key(coords)}", region


def _accepted_rows(scan: _Scan, path: str) -> np.ndarray | None:
    """Photos a per-photo stage accepted, for an array that stage wrote (None for other arrays)."""
    collection, prov = scan.collection(path), scan.provenance(path)
    status = f"{collection}/status/{prov['stage']}/state"
    if collection is None or status not in scan.arrays:
        return None
    if (scan.provenance(status) or {}).get("key") != prov["key"]:
        return None
    if status not in scan.accepted:
        try:
            scan.accepted[status] = scan.arrays[status][:] == OK
        except ChunkError:  # the status itself is damaged: its own check names it
            scan.accepted[status] = None
    return scan.accepted[status]


def _problem(scan: _Scan, path: str, coords: tuple[int, ...], chunk: str, what: str) -> Problem:
    """A problem with a chunk, naming the photos (or frames) it holds and their ids."""
    array, prov = scan.arrays[path], scan.provenance(path) or {}
    collection, items = scan.collection(path), ""
    dims = array.metadata.dimension_names or ()
    if coords and collection is not None and dims and dims[0] in ("photo", "frame") \
            and array.shape[0] == scan.collections[collection]:
        size = (array.shards or array.chunks)[0]
        start, stop = coords[0] * size, min((coords[0] + 1) * size, array.shape[0])
        items = f"{item(collection)} {start}" if stop - start == 1 else f"{item(collection)}s {start}–{stop - 1}"
        try:
            ids = [str(i) for i in scan.arrays[f"{collection}/photos/ids"][start:stop]]
            more = f" and {len(ids) - SHOWN_IDS} more" if len(ids) > SHOWN_IDS else ""
            items += ": ids " + ", ".join(ids[:SHOWN_IDS]) + more
        except (KeyError, ChunkError):
            pass
    return Problem(path, what, chunk, coords[0] if coords else 0, items, prov.get("stage"))


def check(root: zarr.Group, *, read: bool = False, run: Callable | None = None,
          url: str | None = None) -> list[Problem]:
    """Every node whose metadata cannot be read and every missing chunk of every done array (the
    store's keys listed, no chunk read); with ``read``, also every chunk of every array that cannot
    be decoded (each read, its checksum checked): here, one after another, or, given ``run``
    (``run(fn, argument_lists)`` yielding each call's result, as a run's executor does), by its
    workers from the store at ``url``, :data:`READ_BATCH` bytes a task."""
    scan = _scan(root)
    found: dict[str, list[tuple[tuple[int, ...], Problem]]] = {path: [] for path in scan.arrays}
    reads = []  # (array path, coords, chunk key, region) of every chunk to read back
    for path, array in scan.arrays.items():
        done = scan.provenance(path) is not None and has_checksums(array)
        accepted = _accepted_rows(scan, path) if done else None
        for coords, chunk, region in _blocks(array):
            present = chunk in scan.keys
            if done and not present and (accepted is None or accepted[region[0]].any()):
                found[path].append((coords, _problem(scan, path, coords, chunk, "missing")))
            elif read and present:
                reads.append((path, coords, chunk, region))
    here = run is None  # one after another in this process, on the arrays the scan opened
    tasks = [(scan.arrays if here else url, batch) for batch in _batches(scan, reads)]
    for damaged in (unreadable(*task) for task in tasks) if here else run(unreadable, tasks):
        for path, coords, chunk, reason in damaged:
            found[path].append((coords, _problem(scan, path, coords, chunk, f"damaged ({reason})")))
    return [Problem(path, f"metadata cannot be read ({why})") for path, why in scan.broken.items()] + \
        [problem for path in scan.arrays for _, problem in sorted(found[path], key=lambda f: f[0])]


#: bytes of decoded chunks one task of :func:`check` reads back (with ``run``)
READ_BATCH = 64 << 20


def _batches(scan: _Scan, reads: list[tuple]):
    """``reads`` (array path, coords, chunk key, region) in order, cut into lists of about
    :data:`READ_BATCH` decoded bytes."""
    batch, size = [], 0
    for path, coords, chunk, region in reads:
        batch.append((path, coords, chunk, region))
        size += math.prod(r.stop - r.start for r in region) * max(np.dtype(scan.arrays[path].dtype).itemsize, 1)
        if size >= READ_BATCH:
            yield batch
            batch, size = [], 0
    if batch:
        yield batch


def unreadable(store: dict[str, zarr.Array] | str, reads: list[tuple]) -> list[tuple[str, tuple[int, ...], str, str]]:
    """Which chunks of ``reads`` (array path, coords, chunk key, region) cannot be decoded, with why: (array
    path, coords, chunk key, reason). ``store``: the store's arrays by path, open, or its URL (a worker's task)."""
    arrays, root = (store, None) if isinstance(store, dict) else ({}, open_store(store, mode="r"))
    out = []
    for path, coords, chunk, region in reads:
        if path not in arrays:
            arrays[path] = root[path]
        try:
            arrays[path][region]
        except ChunkError as exc:
            out.append((path, coords, chunk, exc.reason))
    return out


def problem_of(root: zarr.Group, error: ChunkError) -> Problem:
    """The problem a run met reading a damaged chunk."""
    scan = _scan(root)
    path, coords = array_of(error.key)
    return _problem(scan, path, coords, error.key, f"damaged ({error.reason})")


def affected(root: zarr.Group, problems: list[Problem]) -> tuple[list[str], list[str]]:
    """The arrays to recompute for ``problems`` (with everything computed from them) and their
    stages, in the order a run makes them."""
    scan = _scan(root)
    provs = {path: scan.provenance(path) for path in scan.arrays if scan.provenance(path)}
    bad = {provs[p.array]["key"] for p in problems if p.array in provs}
    for p in problems:  # an array we cannot open: its key is unknown, so its whole collection
        if not p.chunk:
            scope = p.array if p.array in scan.collections else scan.collection(p.array) or p.array.split("/")[0]
            bad |= {prov["key"] for path, prov in provs.items() if path.startswith(scope + "/")}
    keys = {prov["key"] for prov in provs.values()}
    inputs = {prov["key"]: set(prov["inputs"].values()) & keys - {prov["key"]} for prov in provs.values()}
    grown = True
    while grown:  # everything computed from a damaged array, however far down
        grown = {key for key, needs in inputs.items() if key not in bad and needs & bad}
        bad |= grown

    @functools.cache
    def level(key: str) -> int:  # steps from the store's sources: the order the stages run in
        return 1 + max((level(k) for k in inputs[key]), default=-1)

    arrays = sorted((path for path, prov in provs.items() if prov["key"] in bad),
                    key=lambda path: (level(provs[path]["key"]), provs[path]["created"]))
    stages = list(dict.fromkeys(provs[path]["stage"] for path in arrays))
    return arrays, stages


def clear_unfinished_writes(root: zarr.Group) -> list[str]:
    """Delete what a writer killed mid-write left (returns their keys). Zarr's local store writes each
    file to a temporary ``<name>.<uuid>.partial`` beside it, then renames it into place: one left by a
    SIGKILL is never data, and where it was a ``zarr.json``'s, zarr warns that it is "not recognized as a
    component of a Zarr hierarchy" whenever the group's members are listed, in any tool that opens the
    store with zarr. Only for a run that holds the store's lock: no other writer is at work."""
    leftovers = sorted(key for key in _keys(root) if key.endswith(".partial"))
    base = root.store_path.path
    for key in leftovers:
        sync(root.store.delete(f"{base}/{key}".lstrip("/")))
    return leftovers


def recover(root: zarr.Group, problems: list[Problem]) -> list[str]:
    """Make the next stages recompute what ``problems`` touch: arrays whose metadata cannot be
    read are deleted, and every affected array (:func:`affected`) loses its provenance, so its
    stage counts it as not done. Returns one line per problem, saying so."""
    arrays, _ = affected(root, problems)
    for path in arrays:
        del root[path].attrs["provenance"]
    lines = []
    for p in problems:
        if not p.chunk:
            sync(root.store.delete_dir(f"{root.store_path.path}/{p.array}".lstrip("/")))
            lines.append(f"{p}; deleted it, recomputing its collection and everything after it")
        elif p.stage is None:
            lines.append(f"{p}; it was not finished yet, its stage writes it again")
        else:
            lines.append(f"{p}; recomputing {p.stage} and everything after it")
    return lines

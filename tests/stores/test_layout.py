import numpy as np
import pytest
from pydantic import ValidationError

from persona.stores.layout import (OK, PENDING, REJECTED, Collection, StoreError, first_rejection,
                                   open_store, summarize)
from persona.stores.provenance import Provenance, cache_key


def prov(stage="s", **params):
    return Provenance.make(stage=stage, backend="b", backend_version="1", params=params,
                           inputs={}, persona_version="test")


def make(tmp_path, n=10, shard=4):
    root = open_store(str(tmp_path / "s.zarr"))
    root.require_group("puppet").attrs.update({"n_photos": n, "photos_per_shard": shard})
    coll = Collection(root, "puppet")
    coll.create("photos/ids", (), str, ("photo",), prov())[:] = np.array([f"p{i}" for i in range(n)])
    return root, coll


def test_shards_are_the_write_unit_and_photos_the_chunk(tmp_path):
    _, coll = make(tmp_path)
    assert coll.shard_ranges() == [(0, 4), (4, 8), (8, 10)]
    arr = coll.create("aligned/rgb", (64, 64, 3), "uint8", ("photo", "y", "x", "channel"), prov())
    assert arr.chunks == (1, 64, 64, 3) and arr.shards == (4, 64, 64, 3)
    assert arr.metadata.dimension_names == ("photo", "y", "x", "channel")
    small = coll.create("landmarks/points", (68, 2), "float32", ("photo", "point", "xy"), prov())
    assert small.chunks == (4, 68, 2) and small.shards is None  # small values: a chunk per shard
    whole = coll.create("texture/weighted_0", (64, 64, 3), "float32", ("photo", "y", "x", "channel"), prov(),
                        by_shard=True)
    assert whole.chunks == (4, 64, 64, 3) and whole.shards is None  # read a shard at a time: a chunk per shard
    with pytest.raises(ValueError, match="dimension names"):
        coll.create("bad", (2,), "float32", ("photo",), prov())


def test_rows_are_read_a_shard_at_a_time_in_the_order_asked(tmp_path):
    _, coll = make(tmp_path)
    values = np.arange(10 * 8 * 8 * 3, dtype=np.uint8).reshape(10, 8, 8, 3)
    coll.create("aligned/rgb", (8, 8, 3), "uint8", ("photo", "y", "x", "channel"), prov())[:] = values
    coll.create("landmarks/points", (68, 2), "float32", ("photo", "point", "xy"), prov())[:] = \
        np.arange(10 * 68 * 2, dtype=np.float32).reshape(10, 68, 2)  # one chunk a shard, not sharded
    for rows in ([9, 0, 5, 5, 3], [6], [3, 4, 5], np.arange(10), np.zeros(0, int)):  # [3, 4, 5]: one run, two shards
        for name in ("aligned/rgb", "landmarks/points"):
            got = coll.rows(name, rows)
            assert got.dtype == coll.array(name).dtype
            assert np.array_equal(got, coll.array(name)[:][np.asarray(rows, int)])


def test_a_pass_in_order_reads_each_shard_once_and_gives_every_photo(tmp_path, monkeypatch):
    _, coll = make(tmp_path)
    values = np.arange(10 * 8 * 8 * 3, dtype=np.uint8).reshape(10, 8, 8, 3)
    coll.create("aligned/rgb", (8, 8, 3), "uint8", ("photo", "y", "x", "channel"), prov())[:] = values
    frames = coll.in_order("aligned/rgb")
    reads = []
    getitem = type(frames.array).__getitem__
    monkeypatch.setattr(type(frames.array), "__getitem__", lambda self, key: reads.append(key) or getitem(self, key))
    assert len(frames) == 10
    for i in [0, 1, 2, 3, 3, 4, 5, 9, 6]:  # back into a shard already passed: read again
        assert np.array_equal(frames[i], values[i])
    assert reads == [slice(0, 4), slice(4, 8), slice(8, 12), slice(4, 8)]


def test_provenance_is_validated_and_keys_are_stable(tmp_path):
    _, coll = make(tmp_path)
    coll.create("x", (2,), "float32", ("photo", "v"), prov(a=1))
    assert coll.provenance("x").key == prov(a=1).key != prov(a=2).key
    assert cache_key(a=1, b=[1, 2]) == cache_key(b=[1, 2], a=1)
    with pytest.raises(ValidationError):
        Provenance.model_validate({**prov().model_dump(), "surprise": 1})


def test_status_and_first_rejection(tmp_path):
    _, coll = make(tmp_path, n=5, shard=5)
    for stage in ("ingest", "landmarks"):
        coll.create_status(stage, prov(stage))
    assert (coll.state("ingest") == PENDING).all()
    coll.write_status("ingest", 0, np.array([OK, REJECTED, OK, OK, OK], np.int8),
                      ["", "empty file (0 bytes)", "", "", ""])
    coll.write_status("landmarks", 0, np.array([OK, 3, REJECTED, OK, OK], np.int8),
                      ["", "", "no face found", "", ""])
    final, why = first_rejection(coll, ["ingest", "landmarks"])
    assert list(final) == [OK, REJECTED, REJECTED, OK, OK]
    assert why[1] == "ingest: empty file (0 bytes)" and why[2] == "landmarks: no face found"
    coll.group.attrs["stages"] = ["ingest", "landmarks"]
    summary = summarize(str(tmp_path / "s.zarr"))["collections"]["puppet"]
    assert summary["accepted"] == 3 and summary["rejected"] == 2
    assert summary["rejected_by_reason"] == {"ingest: empty file (0 bytes)": 1, "landmarks: no face found": 1}
    assert summary["rejections"] == {"p1": "ingest: empty file (0 bytes)", "p2": "landmarks: no face found"}


def test_missing_or_foreign_store_is_a_clear_error(tmp_path):
    with pytest.raises(StoreError, match="persona run"):
        open_store(str(tmp_path / "nothing.zarr"), mode="r")
    import zarr

    zarr.open_group(str(tmp_path / "other.zarr"), mode="w")
    with pytest.raises(StoreError, match="not a Persona store"):
        open_store(str(tmp_path / "other.zarr"), mode="r")


def test_a_pending_array_counts_as_done_only_once_marked(tmp_path):
    """An array filled shard by shard is created ``pending``: until mark_done, written after the
    last shard, it has no provenance, so a run killed half-way leaves nothing to trust."""
    _, coll = make(tmp_path)
    arr = coll.create("texture/rgb", (8, 8, 3), "uint8", ("photo", "y", "x", "channel"), prov(a=1), pending=True)
    arr[0:4] = 7
    assert coll.has("texture/rgb") and coll.provenance("texture/rgb") is None
    arr[4:10] = 9
    coll.mark_done("texture/rgb", prov(a=1))
    assert coll.provenance("texture/rgb").key == prov(a=1).key


def test_a_run_killed_while_it_makes_a_stages_status_leaves_no_state_without_its_reasons(tmp_path, monkeypatch):
    """A run SIGKILLed between the two arrays of a stage's status (the chaos test's kill, as render3d
    started): the state is what the next run tests, so it must not be there without the reasons. It was,
    and every run after stopped at "status/render3d/reason is not in the store"."""
    _, coll = make(tmp_path)
    create, made = Collection.create, []

    def killed_after_one(self, name, *args, **kwargs):
        if made:
            raise KeyboardInterrupt  # the kill
        made.append(name)
        return create(self, name, *args, **kwargs)

    monkeypatch.setattr(Collection, "create", killed_after_one)
    with pytest.raises(KeyboardInterrupt):
        coll.create_status("render3d", prov("render3d"))
    monkeypatch.undo()
    again = Collection(open_store(str(tmp_path / "s.zarr"), mode="r"), "puppet")
    assert made and not again.has("status/render3d/state")  # the next run makes the stage's status again

"""Verified chunks: checksums, lost and damaged chunks found and named, what a run would recompute."""

import numpy as np
import pytest

from persona.dag.cli import main as cli
from persona.stores.chunks import ChunkError, has_checksums
from persona.stores.layout import OK, REJECTED, Collection, open_store
from persona.stores.provenance import Provenance
from persona.stores.verify import affected, check, recover


def _prov(stage: str, **inputs) -> Provenance:
    return Provenance.make(stage=stage, backend="-", backend_version="1", params={}, inputs=inputs,
                           persona_version="test")


def _store(tmp_path, n=10):
    """A collection of ``n`` photos, 4 per shard: ids (stage ingest), images of a per-photo stage
    ``warp`` with its status (the last shard's photos rejected) and a collection-level mean made
    from them."""
    root = open_store(tmp_path / "s.zarr")
    root.require_group("puppet").attrs.update({"n_photos": n, "photos_per_shard": 4, "canvas": [8, 8]})
    coll = Collection(root, "puppet")
    ingest = _prov("ingest")
    coll.create("photos/ids", (), str, ("photo",), ingest)[:] = np.array([f"p{i:02d}" for i in range(n)])
    warp = _prov("warp", ingest=ingest.key)
    images = coll.create("warp/rgb", (32, 32, 3), np.uint8, ("photo", "y", "x", "channel"), warp)
    coll.create_status("warp", warp)
    for start, stop in coll.shard_ranges()[:-1]:
        images[start:stop] = np.zeros((stop - start, 32, 32, 3), np.uint8)  # all fill value: still written
        coll.write_status("warp", start, np.full(stop - start, OK, np.int8), [""] * (stop - start))
    start, stop = coll.shard_ranges()[-1]  # every photo of the last shard rejected: its images never written
    coll.write_status("warp", start, np.full(stop - start, REJECTED, np.int8), ["no face"] * (stop - start))
    coll.create_single("mean", np.ones((4, 4), np.float32), ("y", "x"), _prov("mean", warp=warp.key))
    coll.create_single("other", np.ones(3), ("i",), _prov("other", ingest="something else"))
    return root, tmp_path / "s.zarr"


def _flip(path):
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(data)


def test_every_array_has_checksums_and_writes_empty_chunks(tmp_path):
    root, url = _store(tmp_path)
    assert all(has_checksums(root[name]) for name in ("puppet/photos/ids", "puppet/warp/rgb", "puppet/mean"))
    # shards 0 and 1 hold only zeros, the fill value, and are files all the same
    assert sorted(p.name for p in (url / "puppet/warp/rgb/c").iterdir()) == ["0", "1"]
    assert check(root, read=True) == []


def test_a_damaged_chunk_names_its_array_shard_and_photos(tmp_path):
    root, url = _store(tmp_path)
    _flip(url / "puppet/warp/rgb/c/1/0/0/0")
    with pytest.raises(ChunkError, match=r"puppet/warp/rgb: shard 1 \(photos 4–7\).*c/1/0/0/0.*checksum"):
        open_store(url, mode="r")["puppet/warp/rgb"][:]
    assert open_store(url, mode="r")["puppet/warp/rgb"][:4].sum() == 0  # the other shards read
    (problem,) = check(root, read=True)
    assert str(problem).startswith("puppet/warp/rgb: shard 1 (photos 4–7: ids p04, p05, p06, p07) damaged")
    assert problem.stage == "warp" and problem.chunk == "puppet/warp/rgb/c/1/0/0/0"
    assert check(root) == []  # without reading, a damaged chunk is not seen: it is there


def test_a_missing_shard_of_a_done_array_is_found_without_reading(tmp_path):
    root, url = _store(tmp_path)
    (url / "puppet/warp/rgb/c/0/0/0/0").unlink()
    (url / "puppet/mean/c/0/0").unlink()
    problems = check(root)
    assert [str(p) for p in problems] == [
        "puppet/mean: shard 0 missing", "puppet/warp/rgb: shard 0 (photos 0–3: ids p00, p01, p02, p03) missing"]
    # the mean is made from warp, "other" is not: the order is the order of a run
    arrays, stages = affected(root, problems)
    assert stages == ["warp", "mean"]
    assert "puppet/other" not in arrays and "puppet/photos/ids" not in arrays
    assert "puppet/status/warp/state" in arrays


def test_recover_takes_the_done_mark_of_the_array_and_everything_made_from_it(tmp_path):
    root, url = _store(tmp_path)
    (url / "puppet/warp/rgb/c/1/0/0/0").unlink()
    (line,) = recover(root, check(root))
    assert line == ("puppet/warp/rgb: shard 1 (photos 4–7: ids p04, p05, p06, p07) missing; "
                    "recomputing warp and everything after it")
    coll = Collection(open_store(url, mode="r"), "puppet")
    assert coll.provenance("warp/rgb") is None and coll.provenance("status/warp/state") is None
    assert coll.provenance("mean") is None
    assert coll.provenance("photos/ids") is not None and coll.provenance("other") is not None
    assert check(root) == []  # not done: nothing is expected of it any more


def test_what_is_not_done_or_holds_no_accepted_photo_may_be_missing(tmp_path):
    root, url = _store(tmp_path)
    coll = Collection(root, "puppet")
    prov = _prov("texture")
    coll.create("texture/rgb", (32, 32, 3), np.uint8, ("photo", "y", "x", "channel"), prov, pending=True)
    assert check(root) == []  # pending: written later, not done yet
    coll.mark_done("texture/rgb", prov)
    assert [p.shard for p in check(root) if p.array == "puppet/texture/rgb"] == [0, 1, 2]


def test_arrays_from_before_checksums_still_open_and_are_not_counted(tmp_path):
    root, url = _store(tmp_path)
    old = root["puppet"].create_array("old", shape=(10, 4), dtype="float32", chunks=(4, 4))  # zarr's defaults
    old.attrs["provenance"] = _prov("old").model_dump()
    old[:4] = 1.0
    assert not has_checksums(old)
    assert open_store(url, mode="r")["puppet/old"][:4].sum() == 16
    assert check(root, read=True) == []


def test_unreadable_metadata_is_a_problem_and_recovery_deletes_the_array(tmp_path, capsys):
    root, url = _store(tmp_path)
    (url / "puppet/mean/zarr.json").write_text("{not json")
    (problem,) = check(root, read=True)
    assert str(problem).startswith("puppet/mean metadata cannot be read (JSONDecodeError")
    with pytest.raises(Exception, match="puppet/mean: its metadata cannot be read"):
        Collection(open_store(url, mode="r"), "puppet").array("mean")
    assert cli(["inspect", str(url)]) == 2  # an error that points to --verify, not a traceback
    assert "persona inspect --verify" in capsys.readouterr().err
    assert cli(["inspect", "--verify", str(url)]) == 1
    assert f"file {url}/puppet/mean/zarr.json" in capsys.readouterr().out
    (line,) = recover(root, [problem])
    assert "deleted it" in line and not (url / "puppet/mean").exists()
    # its key is unknown: the collection's arrays are all recomputed
    assert Collection(open_store(url, mode="r"), "puppet").provenance("photos/ids") is None


def test_the_unfinished_writes_of_a_killed_run_are_cleared(tmp_path):
    """Zarr's local store writes each file to a temporary ``*.partial`` and renames it into place; a run
    SIGKILLed mid-write leaves it (the chaos test's kill as a drive made its ``eyes`` group), and a group's
    leftover ``zarr.<uuid>.partial`` made zarr warn each time the group's members were listed. A run clears
    them before its stages start; the finished data stay."""
    from persona.stores.verify import clear_unfinished_writes

    root, path = _store(tmp_path)
    (path / "puppet" / "zarr.0123456789abcdef0123456789abcdef.partial").write_bytes(b'{"zarr_fo')
    (path / "puppet" / "warp" / "rgb" / "c" / "0" / "0" / "0" / "0.0123456789abcdef.partial").write_bytes(b"\0")
    with pytest.warns(UserWarning, match="not recognized as a component of a Zarr hierarchy"):
        dict(root["puppet"].members(max_depth=None))
    assert clear_unfinished_writes(root) == ["puppet/warp/rgb/c/0/0/0/0.0123456789abcdef.partial",
                                             "puppet/zarr.0123456789abcdef0123456789abcdef.partial"]
    assert not list(path.rglob("*.partial")) and "warp/rgb" in dict(root["puppet"].members(max_depth=None))
    assert check(root, read=True) == []

"""A run on a store with a lost or damaged shard gives the store of a run that never lost it."""

import io
import logging
import shutil

import pytest

from persona.dag.cli import main as cli
from persona.dag.runner import run_workflow
from persona.dag.workflow import load_workflow

from pipeline import assert_same_store, write_photos, write_workflow


@pytest.fixture(scope="module")
def finished(tmp_path_factory, synthetic_photos):
    """A finished run of 9 photos (shards of 4: the 3D shape and texture run too), its photos outside
    its folder, so that a copy of the folder is the same run."""
    base = tmp_path_factory.mktemp("verify")
    photos = write_photos(base / "photos", synthetic_photos[:9])
    run = base / "run"
    run.mkdir()
    write_workflow(run, str(photos), stages={"landmarks": {"backend": "sidecar"}})
    run_workflow(load_workflow(run / "wf.yaml"), scheduler="sync", progress=False)
    return run


@pytest.fixture
def copy(finished, tmp_path):
    folder = tmp_path / "copy"
    shutil.copytree(finished, folder)
    return folder


def _rerun(folder, scheduler="sync") -> str:
    """Run the workflow in ``folder`` again; what the runner logged (a handler of its own: a local Dask
    cluster sets the root logger's handlers, pytest's among them, to errors only)."""
    logger, lines = logging.getLogger("persona.dag.runner"), io.StringIO()
    handler = logging.StreamHandler(lines)
    handler.setLevel(logging.WARNING)
    logger.addHandler(handler)
    try:
        run_workflow(load_workflow(folder / "wf.yaml"), scheduler=scheduler, workers=2, progress=False)
    finally:
        logger.removeHandler(handler)
    return lines.getvalue()


def test_a_clean_store_verifies(finished, capsys):
    assert cli(["inspect", "--verify", str(finished / "run.zarr")]) == 0
    assert "every chunk of every array is there and reads back intact" in capsys.readouterr().out


def test_a_deleted_shard_is_recomputed_with_everything_after_it(finished, copy):
    (copy / "run.zarr/puppet/aligned/rgb/c/1/0/0/0").unlink()
    log = _rerun(copy)
    assert ("puppet/aligned/rgb: shard 1 (photos 4–7: ids photo0004, photo0005, photo0006, photo0007) missing; "
            "recomputing frontalize and everything after it") in log
    assert_same_store(copy / "run.zarr", finished / "run.zarr")  # the mean face, the 3D shape, the texture: all
    assert cli(["inspect", "--verify", str(copy / "run.zarr")]) == 0


def test_a_lost_shard_of_the_texture_cache_is_built_again_with_the_neutral_texture(finished, copy):
    """The texture cache has a provenance of its own (keyed without the frame params), from which the
    neutral texture's key chains: a shard of the cache lost, both lose their provenance, and the
    re-run's store is the one a run that never lost it made."""
    from persona.stores.layout import Collection, open_store
    from persona.stores.verify import check, recover

    (copy / "run.zarr/puppet/texture/detail_1/c/1/0/0/0").unlink()
    recover(open_store(str(copy / "run.zarr")), check(open_store(str(copy / "run.zarr"), mode="r")))
    puppet = Collection(open_store(str(copy / "run.zarr"), mode="r"), "puppet")
    assert puppet.provenance("texture/weighted_0") is None and puppet.provenance("texture/neutral") is None
    _rerun(copy)
    assert_same_store(copy / "run.zarr", finished / "run.zarr")
    assert cli(["inspect", "--verify", str(copy / "run.zarr")]) == 0


def test_a_damaged_chunk_is_named_by_verify_and_a_rerun_recovers(finished, copy, capsys):
    shard = copy / "run.zarr/puppet/aligned/rgb/c/2/0/0/0"
    data = bytearray(shard.read_bytes())
    data[len(data) // 2] ^= 0xFF
    shard.write_bytes(data)
    capsys.readouterr()
    assert cli(["inspect", "--verify", str(copy / "run.zarr")]) == 1
    out = capsys.readouterr().out
    assert "puppet/aligned/rgb: shard 2 (photo 8: ids photo0008) damaged (ValueError: Stored and computed checksum" in out
    assert f"file {copy / 'run.zarr'}/puppet/aligned/rgb/c/2/0/0/0" in out
    assert "would recompute: frontalize, screen, " in out and "align" in out and "texture" in out
    # the re-run meets it (the mean face reads every aligned face), recomputes, and goes on
    log = _rerun(copy)
    assert "puppet/aligned/rgb: shard 2 (photo 8: ids photo0008) damaged" in log
    assert "recomputing frontalize and everything after it" in log
    assert_same_store(copy / "run.zarr", finished / "run.zarr")
    assert cli(["inspect", "--verify", str(copy / "run.zarr")]) == 0


def test_a_damaged_chunk_read_outside_a_run_is_an_error_that_says_what_to_do(finished, copy, capsys):
    shard = copy / "run.zarr/puppet/pose/c/0/0"
    data = bytearray(shard.read_bytes())
    data[len(data) // 2] ^= 0xFF
    shard.write_bytes(data)
    capsys.readouterr()
    assert cli(["inspect", str(copy / "run.zarr")]) == 0  # the summary does not read poses
    from persona.stores.layout import Collection, open_store

    with pytest.raises(Exception) as caught:
        Collection(open_store(copy / "run.zarr", mode="r"), "puppet").array("pose")[:]
    message = str(caught.value)
    assert message.startswith("puppet/pose: shard 0 (photos 0–3) cannot be read")
    assert "persona inspect --verify" in message and "run the workflow again" in message.lower()


@pytest.mark.parametrize("scheduler", ["sync", "local"])
def test_a_damaged_chunk_of_an_array_no_stage_reads_again_is_recomputed_by_a_rerun(finished, copy, capsys,
                                                                                  scheduler):
    """B's neutral texture is the texture stage's last output: nothing in a run reads it back. Damaged, the
    re-run finds it before its stages start (it reads every chunk back, as ``inspect --verify`` does; on a
    cluster, its workers do), makes it again, and leaves a store that verifies, equal to the undamaged run's."""
    chunk = next((copy / "run.zarr/puppet/texture/neutral/c").rglob("*"))
    while chunk.is_dir():
        chunk = next(chunk.rglob("*"))
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(data)
    capsys.readouterr()
    assert cli(["inspect", "--verify", str(copy / "run.zarr")]) == 1
    log = _rerun(copy, scheduler)
    assert "puppet/texture/neutral" in log and "damaged" in log
    assert cli(["inspect", "--verify", str(copy / "run.zarr")]) == 0
    assert_same_store(copy / "run.zarr", finished / "run.zarr")

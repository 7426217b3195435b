"""Fixtures for pipeline tests."""

import shutil
import time

import pytest
import yaml

from persona.plugins.face import synthetic
from pipeline import Run, events, local_cluster, make_certificates, write_quick_people


@pytest.fixture(scope="session")
def synthetic_photos():
    """24 synthetic photos (seeded) with ground-truth landmarks."""
    return synthetic.make_collection(24, seed=7)


@pytest.fixture
def dask_cluster(tmp_path):
    """A real dask scheduler and two workers on 127.0.0.1, as separate processes."""
    yield from local_cluster(tmp_path)


@pytest.fixture
def tls_cluster(tmp_path):
    """The same speaking TLS only: the scheduler, the workers and the client present one
    certificate of a CA made here (:func:`make_certificates`). Yields (address, {ca_file, cert, key})."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed: it makes the test's certificates")
    from distributed.security import Security

    files = make_certificates(tmp_path / "tls")
    args = ["--tls-ca-file", files["ca_file"], "--tls-cert", files["cert"], "--tls-key", files["key"]]
    security = Security(tls_ca_file=files["ca_file"], tls_client_cert=files["cert"], tls_client_key=files["key"],
                        require_encryption=True)
    cluster = local_cluster(tmp_path, "tls", args, security)
    try:
        yield next(cluster), files
    finally:
        cluster.close()


@pytest.fixture(scope="session")
def batch(tmp_path_factory):
    """A small version-2 batch (bea and cy performing al's video, 8 frames in 2 shards; 8, 8 and 9 photos:
    about the fewest that give each a 3D shape, 8) and its uninterrupted run (`persona run`, its own local
    cluster of two workers): (folder, workflow, timeline, end). Its store, ``folder/reference.zarr``, is
    the one every interrupted or otherwise placed run of the batch must end with (test_chaos.py,
    test_runner.py's worker kills, test_slurm.py, test_people.py's run in this process); its progress
    lines, with when each came from the first (``timeline``, up to ``end`` seconds), are the timeline the
    chaos test draws its kill points on and show test_people.py two people built at once. The folder is
    shared: a test writes its own store, output and files elsewhere."""
    folder = tmp_path_factory.mktemp("batch")
    data = folder / "data"
    write_quick_people(data, {"bea": (8, 0), "cy": (8, 7), "al": (9, 1)}, "al", 8)
    workflow = folder / "batch.yaml"
    workflow.write_text(yaml.safe_dump({
        "version": 2, "name": "batch", "store": "run.zarr", "output": "out",
        "people": {"bea": {"photos": "data/bea/*.png"}, "cy": {"photos": "data/cy/*.png"},
                   "al": {"photos": "data/al/*.png"}},
        "drives": [{"puppet": ["bea", "cy"], "driver": "al", "video": "data/al.mp4"}],
        "photos_per_shard": 4, "stages": {"pose": {"params": {"focal_factor": 2.0}}},
        "evaluate": {"identity_frames": 2, "collection_sample": 4},  # dlib's descriptors: the slowest figures
        "cluster": {"scheduler": "local", "workers": 2}}, sort_keys=False))

    start = time.monotonic()
    run = Run(workflow, folder / "reference.zarr", folder / "reference", folder / "reference.log")
    assert run.wait() == 0, f"the uninterrupted run failed:\n{run.tail()}"
    seconds = time.monotonic() - start
    timeline: dict[str, float] = {}
    first = next(t for t, line in run.lines if events(line))
    for t, line in run.lines:
        for event in events(line):
            timeline.setdefault(event, t - first)
    end = run.lines[-1][0] - first
    print(f"\nuninterrupted run of the batch: {seconds:.0f} s, {end:.0f} s from its first progress line; "
          f"{len(timeline)} progress events")
    return folder, workflow, timeline, end

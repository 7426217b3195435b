"""A run whose store, photos and output are in object storage (s3:// URLs on moto's S3 server on
127.0.0.1), by Dask workers in processes of their own that reach the bucket with the workflow's
storage options and share no folder with the client."""

import json
import re

import pytest
import s3fs

from persona.dag.cli import main as cli
from persona.dag.runner import run_workflow
from persona.dag.workflow import load_workflow

from pipeline import assert_same_store, write_photos, write_workflow


@pytest.mark.slow  # 2 to 3 minutes: moto answers each of the store's many small requests in tens of ms
def test_a_run_in_a_bucket_gives_the_store_and_outputs_of_a_local_run(tmp_path, synthetic_photos, s3_bucket,
                                                                       dask_cluster):
    bucket, options = s3_bucket
    fs = s3fs.S3FileSystem(**options, skip_instance_cache=True)
    photos = write_photos(tmp_path / "photos", synthetic_photos[:8])
    fs.put(f"{photos}/", f"{bucket}/photos/", recursive=True)  # the photos and their landmark sidecars
    stages = {"landmarks": {"backend": "sidecar"}, "integrate": {"backend": "frankot_chellappa"}}  # the fast ones
    local, remote = tmp_path / "local", tmp_path / "remote"
    local.mkdir()
    remote.mkdir()
    run_workflow(load_workflow(write_workflow(local, str(photos), stages=stages)), scheduler="sync", progress=False)
    write_workflow(remote, f"s3://{bucket}/photos", store=f"s3://{bucket}/run.zarr", output=f"s3://{bucket}/out",
                   storage_options=options, stages=stages)

    assert cli(["run", str(remote / "wf.yaml"), "--scheduler", dask_cluster, "--quiet"]) == 0

    assert_same_store(f"s3://{bucket}/run.zarr", local / "run.zarr")
    written = sorted(name.rsplit("/", 1)[1] for name in fs.ls(f"{bucket}/out"))
    assert written == sorted(p.name for p in (local / "out").iterdir())
    assert {"metrics.json", "report.html", "puppet_mean_face.png", "puppet_contact_sheet.png"} <= set(written)
    metrics = json.loads(fs.cat(f"{bucket}/out/metrics.json"))
    assert metrics["collections"]["puppet"]["accepted"] == 8
    assert metrics["store"] == f"s3://{bucket}/run.zarr"
    for key in [*fs.find(f"{bucket}/run.zarr"), *fs.find(f"{bucket}/out")]:  # no credentials anywhere
        data = fs.cat(key)
        assert options["secret"].encode() not in data and options["key"].encode() not in data, key


def test_a_missing_bucket_or_key_is_named_before_any_work(tmp_path, synthetic_photos, s3_bucket, capsys):
    bucket, options = s3_bucket
    photos = write_photos(tmp_path / "photos", synthetic_photos[:2])
    fs = s3fs.S3FileSystem(**options, skip_instance_cache=True)
    cases = [({"store": "s3://no-such-bucket/run.zarr", "output": f"s3://{bucket}/out"},
              "store s3://no-such-bucket/run.zarr: bucket 'no-such-bucket' does not exist.*endpoint_url"),
             ({"store": f"s3://{bucket}/run.zarr", "output": "s3://missing-too/out"},
              "output s3://missing-too/out: bucket 'missing-too' does not exist.*endpoint_url"),
             ({"store": f"s3://{bucket}/run.zarr", "puppet": {"photos": f"s3://{bucket}/nothing/*.png"}},
              f"glob pattern 's3://{bucket}/nothing/\\*.png' matches no files")]
    for extra, message in cases:
        path = write_workflow(tmp_path, str(photos), storage_options=options, **extra)
        for command in ("validate", "run"):
            assert cli([command, str(path), "--scheduler", "sync", "--quiet"][:2 if command == "validate" else 5]) == 2
            err = capsys.readouterr().err
            assert re.search(message, err), err
    assert fs.ls(bucket) == [] and not (tmp_path / "out").exists()  # nothing created

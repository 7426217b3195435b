"""Object storage: photos, sidecars, videos and outputs read and written through s3:// URLs on a real
S3 server (moto's, on 127.0.0.1), the same as from a local folder; clear errors when the bucket,
the key or the endpoint is not there."""

import os
import socket

import numpy as np
import pytest
import s3fs

from persona.dag.demo import write_collection
from persona.plugins.face import synthetic
from persona.stores import media, storage
from persona.stores.errors import InputError, StorageError
from persona.stores.layout import StoreError, open_store


@pytest.fixture(scope="module")
def photos():
    return synthetic.make_collection(3, seed=11)


def _upload(local_folder, url, options):
    fs = s3fs.S3FileSystem(**options, skip_instance_cache=True)
    for f in sorted(local_folder.iterdir()):
        fs.put_file(str(f), f"{url.removeprefix('s3://')}/{f.name}")


def test_inputs_in_a_bucket_resolve_and_read_as_from_a_folder(tmp_path, photos, s3_bucket):
    bucket, options = s3_bucket
    local = tmp_path / "photos"
    write_collection(local, photos)
    media.write_video_mp4(local / "clip.mp4", [p.image for p in photos], fps=10)
    (local / ".hidden.png").write_bytes(b"not listed")
    url = f"s3://{bucket}/in/photos"
    _upload(local, url, options)

    for spec in ("photos", "photos/*.png", "photos/photo0001.png", "photos/clip.mp4",
                 {"video": "photos/clip.mp4", "start": 1, "step": 2}):
        remote_spec = ({**spec, "video": f"s3://{bucket}/in/{spec['video']}"} if isinstance(spec, dict)
                       else f"s3://{bucket}/in/{spec}")
        here, there = media.resolve_sources(spec, tmp_path), media.resolve_sources(remote_spec, "/nowhere")
        assert [(s.id, s.frame) for s in here] == [(s.id, s.frame) for s in there], spec
        assert all(s.path.startswith(f"s3://{bucket}/in/photos/") for s in there)

    for name in ("photo0000.png", "photo0002.png"):
        here, there = str(local / name), f"{url}/{name}"
        np.testing.assert_array_equal(media.decode_image(here), media.decode_image(there))
        np.testing.assert_array_equal(media.read_landmark_sidecar(here), media.read_landmark_sidecar(there))
        assert media.sha256_file(here) == media.sha256_file(there)
        assert media.probe_image(here) == media.probe_image(there)
        assert storage.signature(there)[0] == storage.signature(here)[0]
    with media.VideoReader(local / "clip.mp4") as a, media.VideoReader(f"{url}/clip.mp4") as b:
        assert (a.n_frames, a.fps, a.width, a.height) == (b.n_frames, b.fps, b.width, b.height)
        for (i, x), (j, y) in zip(a.frames(), b.frames(), strict=True):
            assert i == j
            np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(media.read_video_frame(local / "clip.mp4", 2),
                                  media.read_video_frame(f"{url}/clip.mp4", 2))


def test_outputs_are_written_into_the_bucket(tmp_path, photos, s3_bucket):
    import open3d as o3d

    from persona.stores.meshes import write_mesh

    bucket, options = s3_bucket
    out = f"s3://{bucket}/out"
    media.write_png(storage.join(out, "face.png"), photos[0].image)
    media.write_video_mp4(storage.join(out, "clip.mp4"), [p.image for p in photos], fps=10)
    written = write_mesh(storage.join(out, "meshes"), "box", o3d.geometry.TriangleMesh.create_box())
    fs = s3fs.S3FileSystem(**options, skip_instance_cache=True)
    assert sorted(fs.ls(f"{bucket}/out")) == [f"{bucket}/out/{n}" for n in ("clip.mp4", "face.png", "meshes")]
    assert sorted(written) == ["obj", "ply"] and all(storage.isfile(p) for p in written.values())
    np.testing.assert_array_equal(media.decode_image(storage.join(out, "face.png")), photos[0].image)
    with media.VideoReader(storage.join(out, "clip.mp4")) as reader:
        assert reader.n_frames == len(photos)
    assert not list(tmp_path.iterdir())  # nothing written beside the test's own folder either


def test_a_missing_bucket_key_or_endpoint_is_named_with_what_to_check(tmp_path, s3_bucket):
    bucket, options = s3_bucket
    with pytest.raises(StorageError, match="s3://no-such-bucket/run.zarr: bucket 'no-such-bucket' does not exist.*endpoint_url"):
        open_store("s3://no-such-bucket/run.zarr")
    with pytest.raises(StoreError, match=f"no Persona store at s3://{bucket}/run.zarr"):
        open_store(f"s3://{bucket}/run.zarr", mode="r")
    with pytest.raises(StorageError, match="input s3://no-such-bucket/photos: bucket 'no-such-bucket' does not exist"):
        media.resolve_sources("s3://no-such-bucket/photos", tmp_path)
    with pytest.raises(InputError, match=f"'s3://{bucket}/photos' does not exist: check the URL"):
        media.resolve_sources(f"s3://{bucket}/photos", tmp_path)
    with pytest.raises(InputError, match=f"glob pattern 's3://{bucket}/photos/\\*.png' matches no files"):
        media.resolve_sources(f"s3://{bucket}/photos/*.png", tmp_path)
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    storage.configure({**options, "endpoint_url": f"http://127.0.0.1:{port}", "config_kwargs": {"retries": {"max_attempts": 1}}})
    with pytest.raises(StorageError, match=f"output s3://{bucket}/out: cannot reach it .*endpoint_url"):
        storage.check(f"s3://{bucket}/out", "output")


def test_signature_follows_content_not_modification_time(tmp_path):
    """Provisioning the same photo again (a new modification time) keeps its cache key; new
    bytes of the same size change it."""
    photo = tmp_path / "a.jpg"
    photo.write_bytes(b"abcd")
    before = storage.signature(photo)
    os.utime(photo, ns=(1, 1))
    assert storage.signature(photo) == before
    photo.write_bytes(b"abce")
    os.utime(photo, ns=(2, 2))
    assert storage.signature(photo) != before
    assert storage.signature(tmp_path / "missing.jpg") == (-1, -1)

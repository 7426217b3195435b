"""Every stage on real photo collections (../shared/data; skipped when absent).

One run (Bush as the puppet; Obama's photos and 100 frames of his address as the driver) is shared by the
tests of this module. Bush's model (alignment, 3D shape, texture) is built from every 4th of his 530 photos
(133): those steps take time in proportion to the photos, and the tests here judge what comes out of the
model, not the collection's size. The landmark rate is measured on all 530, whose per-photo stages run in
a store of their own (a tenth of the run's time).
"""

import numpy as np
import pytest
import yaml

from persona.dag.executor import executor_for
from persona.dag.inputs import resolve_inputs
from persona.dag.runner import Runner, run_workflow
from persona.dag.workflow import load_workflow
from persona.plugins.builtin.landmarks import DlibLandmarks
from persona.plugins.face.template import generic_template
from persona.stores.layout import OK, REJECTED, Collection, open_store, summarize

pytestmark = [pytest.mark.realdata, pytest.mark.slow]


def _workflow(folder, puppet, **more):
    path = folder / "wf.yaml"
    path.write_text(yaml.safe_dump({
        "version": 1, "name": "real", "store": str(folder / "run.zarr"), "output": str(folder / "out"),
        "puppet": {"photos": puppet}, "cluster": {"scheduler": "local", "workers": 2}, **more}))
    return load_workflow(path)


@pytest.fixture(scope="module")
def real_run(shared_data, tmp_path_factory):
    folder = tmp_path_factory.mktemp("real")
    bush = sorted(str(p) for p in (shared_data / "collections" / "george_w_bush").glob("*.jpg"))
    wf = _workflow(folder, bush[::4], driver={
        "photos": str(shared_data / "collections" / "barack_obama"),
        "video": {"video": str(shared_data / "videos" / "obama_address.mov"), "start": 900, "stop": 1000}},
        # identity judged on every 4th frame (dlib's descriptors: half the evaluation's time); the
        # other figures on every frame
        evaluate={"identity_frames": 25})
    report = run_workflow(wf, progress=False)
    return folder, report


@pytest.fixture(scope="module")
def all_of_bush(shared_data, tmp_path_factory):
    """The per-photo stages (ingest, landmarks, pose, frontalize, screen) of every one of Bush's 530
    photos, with the run's settings, in a store of their own: the puppet collection there."""
    folder = tmp_path_factory.mktemp("bush")
    wf = _workflow(folder, str(shared_data / "collections" / "george_w_bush"))
    with executor_for(wf) as ex:
        runner = Runner(wf, ex, progress=False)
        coll, video = runner.collection("puppet", resolve_inputs(wf)["puppet"])
        runner.run_photo_stages(coll, video)
    return folder / "run.zarr"


def landmark_rate(store, path):
    coll = Collection(open_store(store, mode="r"), path)
    state = coll.state("landmarks")
    ingest = coll.state("ingest")
    return (state == OK).mean(), coll, state, ingest


def test_bush_landmarks_found_in_97_percent(all_of_bush):
    rate, coll, state, ingest = landmark_rate(all_of_bush, "puppet")
    assert coll.n == 530
    assert rate >= 0.97, rate
    reasons = coll.reasons("landmarks")
    assert all(reasons[i] for i in np.flatnonzero(state == REJECTED))


def test_obama_tight_crops_landmarks_found_in_92_percent(real_run):
    folder, _ = real_run
    rate, coll, state, _ = landmark_rate(folder / "run.zarr", "driver")
    assert coll.n == 252
    assert rate >= 0.92, rate


def test_video_frames_ingested_with_fps_and_aligned(real_run):
    folder, _ = real_run
    coll = Collection(open_store(folder / "run.zarr", mode="r"), "driver/frames")
    assert coll.n == 100
    assert coll.attrs["fps"] == pytest.approx(25)
    assert list(coll.array("photos/frame")[:3]) == [900, 901, 902]
    assert (coll.state("frontalize") == OK).mean() >= 0.95


def test_every_photo_accounted_for(real_run, all_of_bush):
    folder, _ = real_run
    for store in (folder / "run.zarr", all_of_bush):
        summary = summarize(str(store))
        for path, c in summary["collections"].items():
            assert c["accepted"] + c["rejected"] == c["n_photos"], (store, path)
            assert sum(c["rejected_by_reason"].values()) == c["rejected"], (store, path)


def test_bush_mean_face_is_a_face_with_landmarks_where_the_frame_puts_them(real_run):
    """dlib finds the mean aligned face; its 68 landmarks lie within 5 % of the
    inter-ocular distance (median) of the canonical frame's landmarks."""
    folder, report = real_run
    coll = Collection(open_store(folder / "run.zarr", mode="r"), "puppet")
    mean = np.clip(coll.array("aligned/mean")[:], 0, 255).round().astype(np.uint8)
    found = DlibLandmarks().detect(mean)
    canonical = generic_template().landmarks3d[:, :2]
    iod = np.linalg.norm(canonical[36:42].mean(0) - canonical[42:48].mean(0))
    error = np.linalg.norm(found.points - canonical, axis=1)
    assert np.median(error) / iod < 0.05, np.median(error) / iod
    assert (folder / "out" / "puppet_mean_face.png").is_file()
    assert (folder / "out" / "puppet_contact_sheet.png").is_file()


def test_3d_drive_carries_the_drivers_expressions_onto_the_puppet(real_run):
    """Bush driven by frames 900-999 of Obama's address (the 3D method, the default): A's per-frame
    meshes and B's transferred meshes follow A's mouth (dlib's landmarks on A's frames), and the
    output is Bush, not Obama (in 90 % of the 25 frames whose identity is judged)."""
    _, report = real_run
    evaluation = report["evaluation"]
    print("\nmotion:", evaluation["motion"], "\nexpression:", evaluation["expression"])
    for meshes in ("driver_meshes", "puppet_meshes"):
        assert evaluation["motion"][meshes]["mouth_open"]["r"] > 0.8, meshes
    assert evaluation["identity"]["fraction_b_not_a"] >= 0.9


def test_a_real_run_opens_everywhere(real_run):
    """What a user opens from a real run: every group of the store in xarray; the three videos with
    the address's sound cut to frames 900-999 (4 s, within a frame of the video's length); the
    average meshes in metres, centred between the eyes, a face 12-25 cm wide."""
    import av
    import open3d as o3d
    import xarray as xr
    import zarr

    folder, report = real_run
    store = str(folder / "run.zarr")

    def walk(group, path):
        if any(True for _ in group.array_keys()):
            xr.open_zarr(store, group=path or None, consolidated=False)
        for name, child in group.groups():
            walk(child, f"{path}/{name}" if path else name)

    walk(zarr.open_group(store, mode="r"), "")
    for name in ("composite", "puppet", "side_by_side"):
        with av.open(str(folder / "out" / f"{name}.mp4")) as container:
            video, sound = container.streams.video[0], container.streams.audio[0]
            seconds = [float(s.duration * s.time_base) for s in (video, sound)]
        assert abs(seconds[0] - 4.0) < 1e-6 and abs(seconds[1] - seconds[0]) < 1 / 25, (name, seconds)
    for actor in ("puppet", "driver"):
        vertices = np.asarray(o3d.io.read_triangle_mesh(report["collections"][actor]["pictures"]["mesh_ply"]).vertices)
        width = np.ptp(vertices[:, 0])
        assert 0.12 < width < 0.25 and abs(vertices[:, 0].min() + vertices[:, 0].max()) / 2 < 0.01, (actor, width)

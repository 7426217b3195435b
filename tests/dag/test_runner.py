import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from persona.dag.cli import main as cli
from persona.dag.runner import run_workflow
from persona.dag.workflow import load_workflow
from persona.stores.layout import PENDING, Collection, open_store, summarize

from pipeline import Run, assert_same_store, local_cluster, write_photos, write_workflow

PERSONA = str(Path(sys.executable).with_name("persona"))


def test_sidecar_pipeline_recovers_the_canonical_landmarks(tmp_path, synthetic_photos):
    """With ground-truth landmarks, pose-corrected landmarks land near the template's."""
    from persona.plugins.face.template import generic_template

    write_photos(tmp_path / "photos", synthetic_photos[:8])
    wf = load_workflow(write_workflow(tmp_path, "photos", stages={"landmarks": {"backend": "sidecar"}}))
    report = run_workflow(wf, scheduler="sync", progress=False)
    assert report["collections"]["puppet"]["accepted"] == 8
    coll = Collection(open_store(wf.store, mode="r"), "puppet")
    aligned = coll.array("aligned/landmarks")[:]
    template = generic_template().landmarks3d[:, :2]
    iod = np.linalg.norm(template[36:42].mean(0) - template[42:48].mean(0))
    inner = np.linalg.norm(aligned[:, 17:] - template[17:], axis=2)
    # identities and expressions differ from the template: a few % of the eye distance
    assert np.nanmedian(inner) < 0.08 * iod
    assert (tmp_path / "out" / "puppet_mean_face.png").is_file()
    mask = coll.array("aligned/mask")[:]
    assert mask.mean(axis=(1, 2)).min() > 0.3


def test_a_photo_whose_fiducials_fail_is_screened_out_and_moves_no_statistic(tmp_path, synthetic_photos):
    """One photo whose landmarks are wrong (a mouth 2.5 times too large: the pose still fits)
    is rejected by the screen with its distance as the reason, and the collection's mean
    fiducials are those of the clean collection, within 0.5 px."""
    from persona.stores import media

    clean, dirty = tmp_path / "clean", tmp_path / "dirty"
    write_photos(clean / "photos", synthetic_photos[:12])
    write_photos(dirty / "photos", synthetic_photos[:12])
    bad = dirty / "photos" / "photo9999.png"
    image = synthetic_photos[0].image.copy()
    image[0, 0] ^= 1  # another file than photo0000 (a byte-identical copy would be screened as one)
    media.write_png(bad, image)
    wrong = synthetic_photos[0].landmarks.astype(np.float64).copy()
    centre = wrong[48:68].mean(axis=0)
    wrong[48:68] = centre + 2.5 * (wrong[48:68] - centre)
    media.write_landmark_sidecar(bad, wrong)
    means = {}
    for folder in (clean, dirty):
        # synthetic faces vary less than real ones (≤ 2.1 px RMS here): a tolerance to match
        wf = load_workflow(write_workflow(folder, "photos", stages={"landmarks": {"backend": "sidecar"},
                                                                     "screen": {"params": {"max_distance": 6}}}))
        run_workflow(wf, scheduler="sync", progress=False)
        means[folder.name] = Collection(open_store(wf.store, mode="r"), "puppet").array("aligned/mean_fiducials")[:]
        summary = summarize(wf.store)["collections"]["puppet"]
    assert np.abs(means["dirty"] - means["clean"]).max() < 0.5
    assert summary["accepted"] == 12
    (reason,) = summary["rejections"].values()
    assert reason.startswith("screen: fiducials") and "median shape" in reason


def test_bad_input_collection_runs_to_completion(tmp_path, synthetic_photos):
    import badinput

    from persona.stores import media

    folder = tmp_path / "photos"
    folder.mkdir()
    faces = [p.image for p in synthetic_photos[:3]]
    expected = badinput.make_bad_collection(folder, faces)
    rng = np.random.default_rng(0)
    noise = (rng.random((40, 40, 3)) * 255).astype(np.uint8)
    media.write_png(folder / "no_face.png", np.kron(noise, np.ones((6, 6, 1), np.uint8)))
    three = np.concatenate([synthetic_photos[i].image for i in (3, 4, 5)], axis=1)
    media.write_png(folder / "three_faces.png", three)
    wf = load_workflow(write_workflow(tmp_path, "photos"))
    report = run_workflow(wf, scheduler="sync", progress=False)

    summary = summarize(wf.store)["collections"]["puppet"]
    rejections = summary["rejections"]
    # metrics.json and the report list the same rejections, by reason, with the photos' names
    by_reason = report["collections"]["puppet"]["rejections"]
    assert {photo: reason for reason, photos in by_reason.items() for photo in photos} == rejections
    assert json.loads((Path(wf.output) / "metrics.json").read_text())["collections"]["puppet"]["rejections"] == by_reason
    page = (Path(wf.output) / "report.html").read_text()
    assert "Rejected photos" in page and "no_face" in page and "empty file" in page
    ids = {media.printable(Path(name).stem): name for name in expected}
    assert "bad\\xff\\xfename" in ids  # a name that is not UTF-8: its photo keeps a readable id
    for name, outcome in expected.items():
        stem = media.printable(Path(name).stem)
        if outcome == "ok":
            assert stem not in rejections, (name, rejections.get(stem))
        else:
            assert outcome in rejections[stem], (name, rejections[stem])
            assert rejections[stem].startswith("ingest: ")
    assert "no face found" in rejections["no_face"]
    assert "three_faces" not in rejections
    coll = Collection(open_store(wf.store, mode="r"), "puppet")
    i = list(coll.array("photos/ids")[:]).index("three_faces")
    assert coll.array("landmarks/n_faces")[i] == 3
    box = coll.array("landmarks/box")[i]
    assert three.shape[1] / 3 < (box[0] + box[2]) / 2 < 2 * three.shape[1] / 3  # the centre face
    assert summary["accepted"] == sum(v == "ok" for v in expected.values()) + 1
    assert summary["accepted"] + summary["rejected"] == summary["n_photos"] == len(ids) + 2
    assert set(ids) <= set(coll.array("photos/ids")[:])  # the not-UTF-8 name among them, accepted above
    # the CLI shows every reason
    assert cli(["inspect", wf.store]) == 0


def test_changed_params_rerun_only_what_depends_on_them(tmp_path, synthetic_photos):
    write_photos(tmp_path / "photos", synthetic_photos[:6])
    path = write_workflow(tmp_path, "photos", stages={"landmarks": {"backend": "sidecar"}})
    first = run_workflow(load_workflow(path), scheduler="sync", progress=False)
    again = run_workflow(load_workflow(path), scheduler="sync", progress=False)
    per_photo = [r for r in again["stages"] if "n_done" in r]  # collection-level steps have a wall time only
    assert len(per_photo) >= 5 and all(r["n_done"] == 0 for r in per_photo), again["stages"]
    assert "no 3D shape: shape: 6 images, need at least 8" in again["warnings"][0]  # too few, said, not fatal
    changed = run_workflow(load_workflow(path, ["stages.pose.params.focal_factor=2.0"]),
                           scheduler="sync", progress=False)
    done = {r["stage"]: r["n_done"] for r in changed["stages"] if "n_done" in r}
    assert done == {"ingest": 0, "landmarks": 0, "pose": 6, "frontalize": 6, "screen": 6, "align": 6}
    assert first["stages"][0]["n_done"] == 6


def test_a_shape_that_cannot_be_built_again_leaves_none_behind(tmp_path, synthetic_photos):
    """A re-run with too few photos for a shape says so and clears the earlier run's shape and
    texture: nothing downstream (a drive, `persona evaluate`) can take them for this run's."""
    photos = write_photos(tmp_path / "photos", synthetic_photos[:9])
    path = write_workflow(tmp_path, "photos", stages={"landmarks": {"backend": "sidecar"}})
    run_workflow(load_workflow(path), scheduler="sync", progress=False)
    puppet = Collection(open_store(tmp_path / "run.zarr", mode="r"), "puppet")
    assert puppet.has("shape/depth") and puppet.has("texture/neutral")
    for stem in sorted({f.stem for f in photos.iterdir()})[:3]:
        for f in photos.glob(stem + ".*"):
            f.unlink()
    again = run_workflow(load_workflow(path), scheduler="sync", progress=False)
    assert "puppet: no 3D shape: shape: 6 images, need at least 8" in again["warnings"][0]
    puppet = Collection(open_store(tmp_path / "run.zarr", mode="r"), "puppet")
    assert not puppet.has("shape/depth") and not puppet.has("texture/neutral")
    assert "mesh_ply" not in again["collections"]["puppet"]["pictures"]


def test_unknown_backend_fails_before_any_compute(tmp_path, capsys):
    (tmp_path / "photos").mkdir()
    path = write_workflow(tmp_path, "photos", stages={"landmarks": {"backend": "dlibb"}})
    assert cli(["run", str(path)]) == 2
    err = capsys.readouterr().err
    assert 'unknown landmarks backend "dlibb". Did you mean "dlib"?' in err
    assert not (tmp_path / "run.zarr").exists()


def test_empty_folder_is_a_clear_error(tmp_path, capsys):
    (tmp_path / "photos").mkdir()
    path = write_workflow(tmp_path, "photos")
    assert cli(["run", str(path), "--scheduler", "sync"]) == 2
    err = capsys.readouterr().err
    assert "photos" in err and "empty" in err.lower()
    assert "resume" not in err.lower()  # an input error: running again as it is cannot help


def _wait_for(predicate, timeout, interval=0.02):
    end = time.time() + timeout
    while time.time() < end:
        if predicate():
            return True
        time.sleep(interval)
    return False


def _landmark_states(store):
    try:
        coll = Collection(open_store(store, mode="r"), "puppet")
        return coll.state("landmarks") if coll.has("status/landmarks/state") else None
    except Exception:
        return None


@pytest.fixture(scope="module")
def twelve_photos(tmp_path_factory, synthetic_photos):
    """12 synthetic photos and the store of their run in this process (the default workflow): the store
    every run of them elsewhere must give."""
    folder = tmp_path_factory.mktemp("twelve")
    photos = write_photos(folder / "photos", synthetic_photos[:12])
    run_workflow(load_workflow(write_workflow(folder, str(photos))), scheduler="sync", progress=False)
    return photos, folder / "run.zarr"


def test_resume_after_sigkill_recomputes_nothing_finished(tmp_path, twelve_photos):
    """A run in this process (scheduler "sync") SIGKILLed part-way through the landmarks: the next run
    skips every shard that was finished, leaves its files as they were and decodes none of its photos
    again, and ends with the store of a run that was not killed."""
    photos, reference = twelve_photos  # 3 shards of 4
    write_workflow(tmp_path, str(photos))
    proc = subprocess.Popen([PERSONA, "run", str(tmp_path / "wf.yaml"), "--scheduler", "sync", "--quiet"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def some_done():
        state = _landmark_states(tmp_path / "run.zarr")
        return state is not None and (state != PENDING).sum() >= 4

    assert _wait_for(some_done, timeout=120), "the run never got into the landmarks stage"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    state = _landmark_states(tmp_path / "run.zarr")
    finished = int((state != PENDING).sum())
    assert 0 < finished < len(state), "the kill did not land part-way through landmarks"
    shard_file = tmp_path / "run.zarr" / "puppet" / "landmarks" / "points" / "c" / "0" / "0" / "0"
    before = shard_file.stat().st_mtime_ns

    resumed = run_workflow(load_workflow(tmp_path / "wf.yaml"), scheduler="sync", progress=False)
    landmarks = [r for r in resumed["stages"] if r["stage"] == "landmarks"][0]
    assert landmarks["n_skipped"] >= finished - finished % 4
    assert landmarks["n_done"] + landmarks["n_skipped"] == 12
    assert shard_file.stat().st_mtime_ns == before  # the first shard was not rewritten
    ingest = [r for r in resumed["stages"] if r["stage"] == "ingest"][0]
    assert ingest["n_skipped"] >= landmarks["n_skipped"]  # photos are not decoded again either
    assert_same_store(tmp_path / "run.zarr", reference)


def test_sigterm_stops_a_run_as_ctrl_c_does(tmp_path, twelve_photos):
    """SIGTERM (a batch system's cancel or time limit, `kill`, a timeout) to a run on local workers: it stops
    as on Ctrl-C, with exit status 143 and the line to resume with, and lets the store's lock go (Python's
    default ended the process at once and left it); resumed, it ends with the store of a run never stopped."""
    photos, reference = twelve_photos
    write_workflow(tmp_path, str(photos))
    proc = subprocess.Popen([PERSONA, "run", str(tmp_path / "wf.yaml"), "--scheduler", "local", "--workers", "1",
                             "--quiet"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        assert _wait_for(lambda: (tmp_path / "run.zarr" / ".persona-lock.json").exists(), timeout=120)
        proc.send_signal(signal.SIGTERM)
        err = proc.communicate(timeout=120)[1]
    finally:
        proc.kill()
    assert proc.returncode == 143, err
    assert "The run stopped. Finished work is kept in the store; resume with:" in err
    assert not (tmp_path / "run.zarr" / ".persona-lock.json").exists()
    run_workflow(load_workflow(tmp_path / "wf.yaml"), scheduler="sync", progress=False)
    assert_same_store(tmp_path / "run.zarr", reference)


def test_inspect_json(tmp_path, synthetic_photos, capsys):
    write_photos(tmp_path / "photos", synthetic_photos[:4])
    path = write_workflow(tmp_path, "photos", stages={"landmarks": {"backend": "sidecar"}})
    run_workflow(load_workflow(path), scheduler="sync", progress=False)
    capsys.readouterr()
    assert cli(["inspect", str(tmp_path / "run.zarr"), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    puppet = data["collections"]["puppet"]
    assert puppet["accepted"] == 4
    rgb = puppet["arrays"]["aligned/rgb"]
    assert rgb["dims"] == ["photo", "y", "x", "channel"] and rgb["shape"] == [4, 244, 194, 3]
    root = open_store(tmp_path / "run.zarr", mode="r")
    prov = root["puppet/aligned/rgb"].attrs["provenance"]
    assert prov["stage"] == "frontalize" and prov["backend"] == "template" and prov["key"]
    assert root["puppet/aligned/rgb"].chunks == (1, 244, 194, 3)
    assert root["puppet/aligned/rgb"].shards == (4, 244, 194, 3)


def test_a_collection_mixes_videos_video_ranges_and_photos(tmp_path, synthetic_photos):
    """The paper builds collections from many films: a list of two videos' frame ranges and a
    photo folder is one collection, each frame decoded exactly (the frame itself, by index)."""
    from persona.stores import media

    write_photos(tmp_path / "photos", synthetic_photos[:3])
    frames = [p.image for p in synthetic_photos[3:9]]
    media.write_video_mp4(tmp_path / "a.mp4", frames[:4], fps=25)
    media.write_video_mp4(tmp_path / "b.mp4", frames[4:], fps=25)
    spec = ["photos", {"video": "a.mp4", "start": 1, "step": 2}, "b.mp4"]
    wf = load_workflow(write_workflow(tmp_path, spec))
    assert cli(["validate", str(tmp_path / "wf.yaml")]) == 0
    run_workflow(wf, scheduler="sync", progress=False)
    coll = Collection(open_store(wf.store, mode="r"), "puppet")
    assert list(coll.array("photos/frame")[:]) == [-1, -1, -1, 1, 3, 0, 1]
    rgb, size = coll.array("photos/rgb")[:], coll.array("photos/size")[:]
    for row, (video, index) in zip(range(3, 7), (("a.mp4", 1), ("a.mp4", 3), ("b.mp4", 0), ("b.mp4", 1))):
        with media.VideoReader(tmp_path / video) as reader:
            (_, expected), = reader.frames(index, index + 1)
        h, w = size[row]
        np.testing.assert_array_equal(rgb[row][:h, :w], expected)
    assert (coll.state("ingest") == 1).all()


def test_progress_in_a_log_file_is_one_timestamped_line_per_start_and_end(capsys):
    """stderr is not a terminal under pytest's capture, as in a log file or a batch job: no carriage
    returns, a line when the step starts and one when it ends, in the step's own unit."""
    from persona.dag.progress import progress

    with progress("drive render3d", 12, "frame") as bar:
        for _ in range(3):
            bar.update(4)
    with progress("puppet landmarks", 5, "photo", initial=2) as bar:
        bar.update(3)
    with progress("hidden", 3, enabled=False) as bar:
        bar.update(3)
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert "\r" not in err and len(lines) == 4, err
    assert re.fullmatch(r"\d\d:\d\d:\d\d drive render3d: started: 12 frames", lines[0]), lines[0]
    assert re.fullmatch(r"\d\d:\d\d:\d\d drive render3d: done: 12 of 12 frames in \d+\.\d s", lines[1]), lines[1]
    assert lines[2].endswith("puppet landmarks: started: 5 photos, 2 done before")
    assert "done: 5 of 5 photos" in lines[3]
    with pytest.raises(KeyboardInterrupt), progress("driver align", 10, "photo") as bar:
        bar.update(2)
        raise KeyboardInterrupt  # the run stops mid-step: its line says so, not "done"
    assert "driver align: stopped: 2 of 10 photos in" in capsys.readouterr().err


def test_the_local_cluster_listens_on_loopback_only():
    """The scheduler and its dashboard run whatever code reaches them: the local cluster binds
    them to 127.0.0.1, never to every interface."""
    from persona.dag.executor import Executor

    ex = Executor("local", 1)
    try:
        scheduler = ex._cluster.scheduler
        assert scheduler.address.startswith("tcp://127.0.0.1:")
        # the dashboard's link names 127.0.0.1 whatever it binds; its sockets say where it listens
        # (tornado's HTTPServer keeps them in _sockets; 0.0.0.0 before this was fixed)
        bound = [sock.getsockname()[0] for sock in scheduler.http_server._sockets.values()]
        assert bound and set(bound) == {"127.0.0.1"}, bound
    finally:
        ex.close()


def test_the_workers_sample_no_profile():
    """Dask's workers sample every thread's stack (sys._current_frames()) every 10 ms; on CPython
    3.11 before 3.11.9 that can deadlock the worker for good against a thread being started (GC
    inside the sampling waits for the GIL while holding the runtime lock; python/cpython#106883,
    dask/distributed#8616): a run of benchmarks/kill_resume.py hung so in a worker's mean-face
    task (zarr starting a decoder thread). Persona's workers sample nothing."""
    from persona.dag.executor import Executor

    ex = Executor("local", 1)
    try:
        list(ex.run(time.sleep, [(1.2,)]))  # busy for longer than the profile's cycle (1 s)
        assert ex.client.profile()["count"] == 0
    finally:
        ex.close()


PLUGIN = """
from persona.plugins.base import Params
from persona.plugins.hookspecs import hookimpl
from persona.plugins.kinds import LandmarkBackend


class Elsewhere(LandmarkBackend):
    name = "elsewhere"
    description = "a third party's landmarks, installed beside the test"

    class Params(Params):
        pass


@hookimpl
def persona_register_backends(register):
    register(Elsewhere)


def landmark_backends():  # those of the process this runs in (importing this module registers nothing)
    from persona.plugins.manager import default_registry

    return default_registry().names("landmarks")
"""


@pytest.fixture
def installed_plugin(tmp_path, monkeypatch):
    """A third-party plugin installed as pip would (its module and a .dist-info naming its ``persona``
    entry point ``elsewhere``) on a folder this process and the processes it starts import from."""
    site = tmp_path / "site"
    info = site / "persona_elsewhere-1.0.dist-info"
    info.mkdir(parents=True)
    (site / "persona_elsewhere.py").write_text(PLUGIN)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: persona-elsewhere\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[persona]\nelsewhere = persona_elsewhere\n")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.syspath_prepend(str(site))
    return "elsewhere"


def test_the_workers_load_the_plugins_the_run_chose(installed_plugin, dask_cluster, monkeypatch):
    """Workers started with PERSONA_PLUGINS empty (as tests/pipeline.py starts them; on a cluster, whatever
    their machine's environment says) load the plugins the run's own process chose."""
    from persona.dag.executor import Executor
    from persona.plugins import manager

    from persona_elsewhere import landmark_backends

    monkeypatch.setenv("PERSONA_PLUGINS", installed_plugin)
    manager.default_registry.cache_clear()
    assert installed_plugin in landmark_backends()
    ex = Executor(dask_cluster, None)
    try:
        seen = list(ex.run(landmark_backends, [()] * 4))
        assert all(installed_plugin in names for names in seen), seen
    finally:
        ex.close()
        manager.default_registry.cache_clear()


def _tasks_on_scheduler(dask_scheduler):
    return list(dask_scheduler.tasks)


def _first_value_plus(value, array):
    return value + float(array[0])


def test_an_array_every_task_takes_is_sent_once_and_each_task_let_go_when_taken():
    """An array that every task takes goes to the cluster as one task (sent with each, the client
    held a copy per task: 1.1 MB each); a task whose result was taken is let go (its result no longer
    held by a worker), so neither side grows with the number of tasks. The results are unchanged."""
    from persona.dag.executor import Executor

    big = np.arange(100_000, dtype=np.float64) + 0.5  # 800 kB, above shared_bytes
    small = np.arange(4.0)
    ex = Executor("local", 1)
    try:
        results, seen = [], []
        for result in ex.run(_first_value_plus, [(i, big) for i in range(20)] + [(100, small)]):
            results.append(result)
            seen.append(ex.client.run_on_scheduler(_tasks_on_scheduler))
            if len(results) == 21:  # the 20 taken before are let go while the last is held
                deadline = time.monotonic() + 10
                while len(seen[-1]) > 2 and time.monotonic() < deadline:
                    time.sleep(0.1)
                    seen.append(ex.client.run_on_scheduler(_tasks_on_scheduler))
        assert sorted(results) == [i + 0.5 for i in range(20)] + [100.0]
        on_scheduler = set().union(*seen)
        assert sum(key.startswith("_identity") for key in on_scheduler) == 1  # the big array, once
        assert sum(key.startswith("_first_value_plus") for key in on_scheduler) == 21
        assert sum(key.startswith("_first_value_plus") for key in seen[-1]) == 1, seen[-1]
    finally:
        ex.close()


def _models_loaded() -> bool:
    from persona.plugins.builtin.landmarks import dlib_models

    return dlib_models.cache_info().currsize == 1


def test_the_evaluations_models_are_loaded_on_every_worker_without_waiting_for_them():
    """A drive starts by sending the evaluation's warm-up to every worker (``Executor.warm``): the call
    returns at once (a warm-up of 3 s does not hold it), and both workers soon hold dlib's models, which
    they had not loaded before. In one process there is nothing to send."""
    from persona.dag.evaluate import warm_up
    from persona.dag.executor import Executor

    ex = Executor("local", 2)
    try:
        assert not any(ex.client.run(_models_loaded).values())
        t0 = time.perf_counter()
        ex.warm(time.sleep, 3)
        ex.warm(warm_up)
        assert time.perf_counter() - t0 < 2
        deadline = time.monotonic() + 60
        while not all((loaded := ex.client.run(_models_loaded)).values()) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert len(loaded) == 2 and all(loaded.values()), loaded
    finally:
        ex.close()
    Executor("sync", None).warm(_first_value_plus)  # not called: it would fail without its arguments


def test_a_connection_closed_while_a_result_comes_back_is_a_lost_scheduler():
    """The scheduler SIGKILLed just as a finished task's result is fetched: distributed raises
    CommClosedError there (seen once in CI under load, a raw traceback and exit 1); the run says it
    lost its scheduler. A task's own OSError still passes as it is."""
    from distributed.comm.core import CommClosedError

    from persona.dag.errors import RunError
    from persona.dag.executor import Executor

    def closed():
        raise CommClosedError("in <TCP (closed) ConnectionPool.gather>: ConnectionResetError")

    def missing():
        raise FileNotFoundError("a task's own error")

    ex = Executor("local", 1)
    try:
        with pytest.raises(RunError, match="lost the connection to its Dask scheduler"):
            ex._result(closed)
        with pytest.raises(FileNotFoundError, match="a task's own error"):
            ex._result(missing)
    finally:
        ex.close()


def test_a_run_whose_workers_are_all_gone_stops_with_a_clear_error():
    """With every worker gone the run stops, naming the scheduler and how to resume, instead of
    waiting forever."""
    from persona.dag.errors import RunError
    from persona.dag.executor import Executor

    executor = Executor("local", workers=1)
    try:
        executor.workerless_seconds = 1.0
        executor._cluster.scale(0)
        deadline = time.monotonic() + 30
        while executor.client.scheduler_info(n_workers=1)["workers"] and time.monotonic() < deadline:
            time.sleep(0.2)
        start = time.monotonic()
        with pytest.raises(RunError, match="every Dask worker left the scheduler .* re-run the workflow to resume"):
            list(executor.run(time.sleep, [(0.1,)]))
        assert time.monotonic() - start < 20
    finally:
        executor.close()


def die_with_its_worker():
    os.kill(os.getpid(), signal.SIGKILL)


def test_a_task_that_kills_its_workers_stops_the_run_with_a_clear_error():
    """A task whose every worker dies under it (as one out of memory does): after Dask's allowed
    failures the run stops with a RunError that says what likely happened and how to resume,
    not with distributed's KilledWorker traceback."""
    import dask

    from persona.dag.errors import RunError
    from persona.dag.executor import Executor

    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):  # the scheduler runs in this process
        executor = Executor("local", workers=1)
        try:
            with pytest.raises(RunError, match=r"2 Dask workers in turn died while running one task \(die_with_its_worker; .*"
                                               r"out of memory.* re-run the workflow to resume"):
                list(executor.run(die_with_its_worker, [()]))
        finally:
            executor.close()


def test_a_byte_identical_copy_of_a_photo_is_used_once_and_reported(tmp_path, synthetic_photos):
    """The same file twice under two names: the first is used, the copy rejected naming it; the
    collection's mean face is that of the photos without the copy."""
    import shutil

    for folder, copy in (("once", False), ("twice", True)):
        write_photos(tmp_path / folder / "photos", synthetic_photos[:6])
        if copy:
            for suffix in (".png", ".pts"):
                shutil.copy(tmp_path / folder / "photos" / f"photo0002{suffix}",
                            tmp_path / folder / "photos" / f"zcopy{suffix}")
        wf = load_workflow(write_workflow(tmp_path / folder, "photos", stages={"landmarks": {"backend": "sidecar"}}))
        run_workflow(wf, scheduler="sync", progress=False)
    summary = summarize(str(tmp_path / "twice" / "run.zarr"))["collections"]["puppet"]
    assert summary["accepted"] == 6
    (reason,) = summary["rejections"].values()
    assert "byte-identical copy of photo0002" in reason, reason
    means = [Collection(open_store(str(tmp_path / f / "run.zarr"), mode="r"), "puppet").array("aligned/mean")[:]
             for f in ("once", "twice")]
    assert np.array_equal(means[0], means[1])


def test_every_decodable_frame_of_a_truncated_video_is_kept(tmp_path):
    """A video cut off part-way through a shard: the frames decoded before the cut are ingested,
    the frames the container promised but did not deliver are rejected with the reason."""
    from persona.dag.demo import driver_identity
    from persona.dag.executor import Executor
    from persona.dag.inputs import resolve_inputs
    from persona.dag.runner import Runner
    from persona.plugins.face import synthetic
    from persona.stores import media

    full, cut = tmp_path / "full.mp4", tmp_path / "cut.mp4"
    media.write_video_mp4(full, [f.image for f in synthetic.make_driver_video(16, seed=2, identity=driver_identity(0))],
                          fps=25)
    data = full.read_bytes()
    for share in (0.8, 0.75, 0.85, 0.7, 0.9):  # where a shard's frames end depends on the encoder's bytes
        cut.write_bytes(data[:int(share * len(data))])
        with media.VideoReader(cut) as reader:
            decodable = [i for i, _ in reader.frames()]
        if 0 < len(decodable) < 16 and len(decodable) % 4:  # a shard (4 frames) delivered in part
            break
    else:
        pytest.fail(f"no cut of {full.name} ends inside a shard of 4 frames")
    wf = load_workflow(write_workflow(tmp_path, {"video": "cut.mp4"}))
    runner = Runner(wf, Executor("sync", None), progress=False)
    coll, video = runner.collection("puppet", resolve_inputs(wf)["puppet"])
    assert video
    runner.run_photo_stages(coll, video)
    ingested = coll.state("ingest")
    assert list(np.flatnonzero(ingested == 1)) == decodable
    reasons = coll.array("status/ingest/reason")[:]
    assert all(reasons[i] == "frame could not be decoded" for i in range(16) if i not in decodable)
    assert coll.array("photos/rgb")[decodable[-1]].any()  # the last decoded frame itself, not zeros


@pytest.fixture
def small_disk(tmp_path):
    """A 1 MiB tmpfs at tmp_path/disk (root only), resized with ``resize(mebibytes)``."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(disk)], capture_output=True).returncode:
        pytest.skip("mounting a tmpfs needs root")

    def resize(mebibytes):
        subprocess.run(["mount", "-o", f"remount,size={mebibytes}m", str(disk)], check=True)

    yield disk, resize
    subprocess.run(["umount", str(disk)], check=False)


def test_a_full_disk_stops_with_a_clear_error_and_the_run_resumes(tmp_path, synthetic_photos, small_disk, capsys):
    """The store's disk fills up part-way: the run stops with exit status 2 and a message that says so
    and what to do (no traceback); with space again the same command finishes, and the store is
    the one an uninterrupted run makes."""
    disk, resize = small_disk
    photos = write_photos(tmp_path / "photos", synthetic_photos[:12])
    clean = tmp_path / "clean"
    clean.mkdir()
    for folder in (tmp_path, clean):
        write_workflow(folder, str(photos), stages={"landmarks": {"backend": "sidecar"}})
    command = ["run", str(tmp_path / "wf.yaml"), "--scheduler", "sync", "--quiet", "--set", f"store={disk / 'run.zarr'}"]
    assert cli(command) == 2
    err = capsys.readouterr().err
    assert "error: the disk is full (No space left on device)" in err and "run again" in err, err
    assert "Traceback" not in err
    resize(200)
    assert cli(command) == 0
    run_workflow(load_workflow(clean / "wf.yaml"), scheduler="sync", progress=False)
    assert_same_store(disk / "run.zarr", clean / "run.zarr")


def test_a_worker_killed_in_each_kind_of_step_leaves_the_run_to_the_others(batch, tmp_path):
    """The first drive of conftest.py's batch (bea performing al's video: bea, al and the video built, not
    cy) on an existing Dask cluster (a scheduler and two `dask worker`s, each with its nanny), one person
    built at a time (cluster.builds 1: each step's tasks are the only ones running). A worker is SIGKILLed
    while it runs a task of each kind of step: the per-photo chain (bea's landmarks), a step of one task
    (bea's 3D shape), a fold over shards (bea's texture cache) and the per-frame chain (the drive's
    dynamics), each once the nanny's new worker has joined. Dask gives each task to another worker: the
    run exits 0, prints no traceback and no step stopped or failed, and every array it made is the
    uninterrupted run's."""
    from distributed import Client

    folder, workflow, _, _ = batch
    store = tmp_path / "run.zarr"
    steps = (("people/bea landmarks: started", "run_chain"), ("people/bea shape: started", "photometric_stereo"),
             ("people/bea tex. cache: started", "on_shard"), ("drives/bea_al_al dynamics: started", "run_chain"))
    cluster = local_cluster(tmp_path)
    address = next(cluster)
    first_drive = ["--set", "people={bea: {photos: data/bea/*.png}, al: {photos: data/al/*.png}}",
                   "--set", "drives=[{puppet: bea, driver: al, video: data/al.mp4}]"]
    run = Run(workflow, store, tmp_path / "out", tmp_path / "run.log",
              ["--scheduler", address, "--set", "cluster.builds=1", *first_drive])
    try:
        with Client(address, timeout="30s") as client:
            for step, task in steps:
                assert _wait_for(lambda: run.seen(step) or run.proc.poll() is not None, timeout=300), step
                assert run.proc.poll() is None, f"the run ended before {step!r}:\n{run.text()}"

                def busy():  # a worker running a task of the step (each worker runs one task at a time)
                    return next((w for w, keys in client.processing().items()
                                 if any(str(k).startswith(task) for k in keys)), None)

                assert _wait_for(lambda: busy() is not None, timeout=60, interval=0.01), \
                    f"no {task} task seen after {step!r}:\n{run.tail()}"
                worker = busy()
                os.kill(client.run(os.getpid, workers=[worker])[worker], signal.SIGKILL)
                _wait_for(lambda: len(client.scheduler_info()["workers"]) == 2, timeout=60)  # the nanny's new one
            assert run.wait() == 0, run.text()
    finally:
        if run.proc.poll() is None:
            run.kill()
        cluster.close()
    text = run.text()
    assert "Traceback" not in text, text
    # (a step that "stopped" in a run that went on: a lost task, done again, counted as undone)
    assert not [line for _, line in run.lines if line.startswith("error:") or "failed:" in line
                or ": stopped: " in line], text
    assert_same_store(store, folder / "reference.zarr", within=("people/bea", "people/al", "videos/al",
                                                                "drives/bea_al_al"))


def test_a_lost_cluster_stops_a_batch_rather_than_failing_its_drives_one_by_one():
    """In a version-2 batch, a person's build that failed fails only the drives that need it; one that lost
    the run's scheduler (or every worker) stops the whole run with that message, as a full disk does, instead
    of each later drive failing in turn and the run ending "the others are done" with nothing done."""
    from concurrent.futures import Future

    from persona.dag.errors import ClusterLost, RunError
    from persona.dag.executor import Executor
    from persona.dag.schedule import built as _built

    def failed(exc):
        future = Future()
        future.set_exception(exc)
        return future

    assert _built(failed(RunError("no photo of bea was accepted"))) == "no photo of bea was accepted"
    lost = Executor.__new__(Executor)
    lost.scheduler = "tcp://127.0.0.1:8786"
    with pytest.raises(ClusterLost, match="lost the connection to its Dask scheduler"):
        _built(failed(lost._lost()))


def test_a_lost_scheduler_stops_the_run_clearly_and_a_new_one_resumes_it(tmp_path, twelve_photos):
    """The scheduler SIGKILLed mid-run (a version-1 run): the run exits 2 within seconds, saying it lost the
    scheduler and how to resume; with a new scheduler and workers the re-run gives the uninterrupted store
    (that of the run in this process: every stage, on one cluster or the other, gives what it gives here)."""
    from distributed import Client

    photos, reference = twelve_photos
    write_workflow(tmp_path, str(photos))
    first = local_cluster(tmp_path)
    address = next(first)
    with Client(address, timeout="30s") as client:
        scheduler = client.run_on_scheduler(os.getpid)

    def aligned():
        try:
            return (Collection(open_store(tmp_path / "run.zarr", mode="r"), "puppet").state("frontalize") != PENDING).sum()
        except Exception:
            return 0

    proc = subprocess.Popen([PERSONA, "run", str(tmp_path / "wf.yaml"), "--scheduler", address, "--quiet"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        assert _wait_for(lambda: aligned() >= 1, timeout=300), "the run never got going"
        os.kill(scheduler, signal.SIGKILL)
        _, err = proc.communicate(timeout=120)
    finally:
        first.close()
    assert proc.returncode == 2, err
    assert "the run lost the connection to its Dask scheduler" in err and "re-run the workflow to resume" in err
    assert "Traceback" not in err, err
    second = local_cluster(tmp_path)
    try:
        assert cli(["run", str(tmp_path / "wf.yaml"), "--scheduler", next(second), "--quiet"]) == 0
    finally:
        second.close()
    assert_same_store(tmp_path / "run.zarr", reference)
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["collections"]["puppet"]["accepted"] >= 10


def test_a_1080p_clip_keeps_its_size(tmp_path):
    """The frames of a 1920 x 1080 video are stored at that size (the output videos are the driver's;
    ingest's ``max_side`` was 1600, which made them 1600 x 900), and a larger one is brought down to it."""
    from persona.dag.executor import Executor
    from persona.dag.inputs import resolve_inputs
    from persona.dag.runner import Runner
    from persona.stores import media

    for name, (h, w) in (("hd.mp4", (1080, 1920)), ("qhd.mp4", (1440, 2560))):
        frame = np.zeros((h, w, 3), np.uint8)
        frame[:, : w // 2] = 200
        media.write_video_mp4(tmp_path / name, [frame, frame], fps=25)
    for name, expected in (("hd.mp4", [1080, 1920]), ("qhd.mp4", [1080, 1920])):
        wf = load_workflow(write_workflow(tmp_path, {"video": name}))
        runner = Runner(wf, Executor("sync", None), progress=False)
        coll, video = runner.collection("puppet", resolve_inputs(wf)["puppet"])
        runner.run_photo_stages(coll, video)
        assert coll.attrs["canvas"] == expected
        assert [list(s) for s in coll.array("photos/size")[:]] == [expected, expected]


def test_a_failure_the_run_handles_is_one_line_not_a_workers_traceback(tmp_path, synthetic_photos, capfd):
    """Five photos, too few for a shape, on two local Dask workers: the run says so in one line, and the
    worker's "Compute Failed" dump of the task, its exception and its traceback is not printed before it."""
    write_photos(tmp_path / "photos", synthetic_photos[:5])
    path = write_workflow(tmp_path, "photos", stages={"landmarks": {"backend": "sidecar"}},
                          cluster={"scheduler": "local", "workers": 2})
    assert cli(["run", str(path), "--quiet"]) == 0
    captured = capfd.readouterr()
    assert "warning: puppet: no 3D shape: shape: 5 images, need at least 8" in captured.out
    assert "Compute Failed" not in captured.out + captured.err and "Traceback" not in captured.err

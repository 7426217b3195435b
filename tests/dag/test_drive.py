"""End to end on synthetic faces: a puppet video, its evaluation and its report."""

import contextlib
import io
import json
import re
import shutil
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from persona.dag.cli import main as cli
from persona.dag.demo import driver_identity, make_demo_data
from persona.dag.runner import run_workflow
from persona.dag.workflow import load_workflow
from persona.plugins.face import synthetic
from persona.stores import media


@pytest.fixture(scope="module")
def drive_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("drive")
    path = make_demo_data(folder, n_photos=10, n_frames=16)
    frames = [f.image for f in synthetic.make_driver_video(16, seed=2, identity=driver_identity(0))]
    frames[6] = np.full_like(frames[6], 90)  # the driver leaves the frame: no face
    media.write_video_mp4(folder / "data" / "driver.mp4", frames, fps=25)
    wf = yaml.safe_load(path.read_text())
    wf["photos_per_shard"] = 4
    path.write_text(yaml.safe_dump(wf))
    with contextlib.redirect_stderr(io.StringIO()) as log:  # not a terminal: progress as lines, as in a log file
        report = run_workflow(load_workflow(path), scheduler="sync", progress=True)
    (folder / "run.log").write_text(log.getvalue())
    return folder, path, report


def test_every_stage_says_when_it_starts_and_ends(drive_run):
    """Nothing runs silent: each stage of the timing table, per-person and per-drive steps
    included (shape, texture, motion, videos), has a line when it starts and one when it ends."""
    folder, _, report = drive_run
    log = (folder / "run.log").read_text()
    assert {"shape", "texture", "motion", "render3d", "videos"} <= {r["stage"] for r in report["stages"]}
    for record in report["stages"]:
        what = f"{record['collection']} {record['stage']}:"
        assert f"{what} started:" in log and f"{what} done:" in log, what
    assert re.search(r"puppet shape: done: 1 of 1 step in \d+\.\d s", log)


def test_the_plan_shows_every_stage_the_run_runs(drive_run, capsys):
    """`persona run --dry-run` lists, under each collection and the drive, every stage that the
    run's timing table shows there, the steps over a whole collection included."""
    folder, path, report = drive_run
    assert cli(["run", str(path), "--dry-run"]) == 0
    plan, where = {}, None
    for line in capsys.readouterr().out.splitlines():
        if re.match(r"  \S", line):  # a collection's or the drive's heading
            where = line.split(":")[0].strip()
        elif re.match(r"    \S", line):  # a stage under it (its settings are indented further)
            plan.setdefault(where, []).append(re.match(r"(frame textures|\S+)", line[4:]).group(1))
    for record in report["stages"]:
        assert record["stage"].replace("render3d", "render") in plan[record["collection"]], record
    assert plan["drive"] == ["retarget", "gaze", "frame textures", "dynamics", "motion", "teeth", "render", "light", "composite",
                             "videos", "evaluate"]
    assert plan["puppet"][-4:] == ["align", "shape", "texture", "mouth"]


def test_outputs_keep_the_drivers_timing(drive_run):
    folder, _, report = drive_run
    out = folder / "output"
    with media.VideoReader(out / "puppet.mp4") as puppet, media.VideoReader(out / "side_by_side.mp4") as both:
        assert puppet.n_frames == both.n_frames == 16
        assert puppet.fps == pytest.approx(25) and both.fps == pytest.approx(25)
        assert both.width == 2 * puppet.width
    assert report["evaluation"]["bridged_frames"] >= 1  # the blank frame was bridged, not dropped


def test_every_chunk_of_a_finished_run_is_there_and_intact(drive_run, capsys):
    """Every stage, the drive's too, leaves every chunk its arrays call for (docs/store.md)."""
    from persona.stores.layout import open_store
    from persona.stores.verify import check

    folder, _, _ = drive_run
    assert check(open_store(str(folder / "run.zarr"), mode="r"), read=True) == []
    assert cli(["inspect", "--verify", str(folder / "run.zarr")]) == 0


def test_metrics_json_has_counts_times_and_figures(drive_run):
    folder, _, _ = drive_run
    metrics = json.loads((folder / "output" / "metrics.json").read_text())
    assert metrics["collections"]["puppet"]["n_photos"] == 10
    assert {"accepted", "rejected"} <= set(metrics["collections"]["driver"])
    assert metrics["speed"]["ms_per_driver_frame"] > 0
    assert {r["stage"] for r in metrics["stages"]} >= {"ingest", "landmarks", "pose", "frontalize", "dynamics", "shape",
                                                       "texture", "frame textures", "motion", "mouth", "videos",
                                                       "render3d"}
    ev = metrics["evaluation"]
    assert set(ev["expression"]) == set(ev["amplitude"]) == {"mouth_open", "eye_open", "brow_height", "mouth_width",
                                                           "mouth_corners"}
    assert 0 <= ev["identity"]["fraction_b_not_a"] <= 1
    assert ev["stability"]["jitter_ratio"] > 0 and ev["stability"]["jitter_ratio_composite"] > 0


def test_shape_stage_writes_meshes_and_previews(drive_run):
    import open3d as o3d

    from persona.stores.layout import Collection, open_store

    folder, path, report = drive_run
    out = folder / "output"
    for actor in ("puppet", "driver"):
        pictures = report["collections"][actor]["pictures"]
        mesh = o3d.io.read_triangle_mesh(pictures["mesh_ply"])
        assert len(mesh.triangles) > 10000 and mesh.has_vertex_colors()
        assert (out / f"{actor}_mesh.obj").is_file() and (out / f"{actor}_mesh.png").is_file()
        # metres, origin between the eyes (what Blender and MeshLab open at the right size)
        vertices = np.asarray(mesh.vertices)
        width = np.ptp(vertices[:, 0])
        assert 0.10 < width < 0.25, width
        assert abs(vertices[:, 0].min() + vertices[:, 0].max()) / 2 < 0.01  # centred left-right
        assert (out / f"{actor}_mesh.obj").read_text().startswith("# units: metres")
        previews = media.decode_image(pictures["mesh_previews"])
        assert previews.shape[1] == 3 * previews.shape[0]  # three views side by side
        coll = Collection(open_store(str(folder / "run.zarr"), mode="r"), actor)
        assert coll.array("subspace/basis").shape == (4, 244, 194, 3)
        assert (coll.state("align") == 1).sum() >= 8
        depth, mask = coll.array("shape/depth")[...], coll.array("shape/mask")[...]
        assert np.isfinite(depth[mask]).all() and mask.sum() > 20000
        assert coll.array("collection/map").shape[1:] == (244, 194, 2)


def test_puppet_texture_follows_each_frames_expression(drive_run):
    from persona.plugins.face.blend import expression_weights
    from persona.stores.layout import Collection, open_store

    folder, path, report = drive_run
    root = open_store(str(folder / "run.zarr"), mode="r")
    puppet, drive = Collection(root, "puppet"), Collection(root, "drive")
    neutral = media.decode_image(report["collections"]["puppet"]["pictures"]["texture_neutral"])
    assert neutral.shape == (2 * 244, 2 * 194, 3)
    assert puppet.array("texture/weighted_0").shape[1:] == (244, 194, 3)
    textures = drive.array("texture/rgb")[:].astype(np.float32)
    assert textures.shape == (16, 244, 194, 3)
    # frames whose targets weigh the photos differently get different textures
    targets = drive.array("target")[:]
    fiducials = puppet.array("aligned/fiducials")[:]
    weights = np.array([expression_weights(fiducials, t, 10.0, relative=True) for t in targets])
    a, b = np.unravel_index(np.argmax(np.abs(weights[:, None] - weights[None]).sum(-1)), (16, 16))
    assert np.abs(textures[a] - textures[b]).mean() > 0.5
    assert drive.provenance("render/rgb").inputs["texture"] == drive.provenance("texture/rgb").key


def test_report_is_one_self_contained_page(drive_run):
    folder, _, _ = drive_run
    page = (folder / "output" / "report.html").read_text()
    assert page.count("data:image/png;base64,") >= 5  # means, sheets, strip, plots
    assert page.count("data:video/mp4;base64,") == 3  # composite, puppet, side by side
    assert page.index("<h2>composite</h2>") < page.index("<h2>puppet</h2>") < page.index("<h2>Figures</h2>")
    assert "B and not A" in page and "composite seam (blend)" in page and "creases between the brows" in page
    assert 'src="http' not in page  # nothing fetched from elsewhere
    strip = media.decode_image(folder / "output" / "frames.png")  # driver, composite, puppet alone
    assert strip.shape[0] == 3 * 240 and strip.shape[1] % 240 == 0
    driver, puppet = strip[:240].astype(float), strip[480:].astype(float)
    assert np.abs(puppet - 128).max(axis=2).mean() < np.abs(driver - 128).max(axis=2).mean()  # grey around
    # the driver's expression peaks, each column at the frame where the driver's signal is at its extreme
    series = json.loads((folder / "output" / "series.json").read_text())
    assert f"widest mouth (frame {int(np.nanargmax(series['driver_mouth_open']))})" in page
    assert f"brows lowest (frame {int(np.nanargmin(series['driver_brow_height']))})" in page
    assert page.count("data:image/png;base64,") >= 6


def _benchmark(name: str):
    """The script benchmarks/<name>.py, loaded as a module (the benchmarks are not a package)."""
    import importlib.util

    script = Path(__file__).resolve().parents[2] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_texture_leak_benchmark_finds_the_mesh_on_its_targets(drive_run, capsys):
    """benchmarks/texture_leak.py on a finished drive: per expression signal, the frame textures' and B's meshes'
    slopes on the targets. The fiducial follower moves B's mesh so that its fiducials land on the targets, smoothed
    over half a frame in time (which takes some of this fast synthetic driver's amplitude): every signal the driver
    moves, the mesh follows with a slope of 0.75-1.1 and r over 0.95 (0.83-0.91 and 0.98-0.99 here); the script
    prints a line per signal."""
    from persona.stores.layout import Cast, open_store

    _, path, _ = drive_run
    module = _benchmark("texture_leak")
    found = module.slopes(open_store(load_workflow(path).store, mode="r"), Cast())
    moved = [name for name, figures in found.items() if figures["range"] > 0.02]
    assert moved, found
    for name in moved:
        slope, r = found[name]["mesh"]
        assert 0.75 < slope < 1.1 and r > 0.95, (name, found[name])
    capsys.readouterr()
    module.main([str(path)])
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 6 and all("mesh on target" in line for line in lines[1:]), lines


def test_the_self_reenactment_budget_moves_the_face_onto_the_real_one_and_pastes_its_features(drive_run):
    """benchmarks/self_reenactment_budget.py: on a textured face drawn 3 px right and 2 px down of the real one, the
    shift and the smoothed flow bring it back (within 1.5 grey levels RMS, measured 0.0 and 0.1; 46 as it is), and
    each feature pasted from the real frame is the real frame there; on a finished drive, a pasted feature never
    costs. A workflow that is not a self-reenactment is refused."""
    from persona.plugins.builtin.evaluate import masked_psnr
    from persona.plugins.face.template import generic_template
    from persona.stores.layout import Cast, open_store

    module = _benchmark("self_reenactment_budget")
    template = generic_template()
    rng = np.random.default_rng(0)
    real = cv2.GaussianBlur(rng.uniform(0, 255, (244, 194, 3)), (0, 0), 2.5)
    real = np.clip((real - real.mean()) * 6 + 128, 0, 255).astype(np.uint8)
    drawn = np.roll(real, (2, 3), axis=(0, 1))
    mask, points = template.mask, template.landmarks3d[:, :2]
    found = module.variants(real, drawn, mask, points)
    inner = cv2.erode(mask.astype(np.uint8), np.ones((15, 15), np.uint8)) > 0  # the roll's wrapped edge left out
    rms = {name: 255 / 10 ** (masked_psnr(image, real, inner) / 20) for name, image in found.items()}
    print({name: round(value, 2) for name, value in rms.items()})
    assert rms["as it is"] > 10 and rms["shift"] < 1.5 and rms["warp h/40"] < 1.5
    eyes = np.zeros(mask.shape, np.uint8)
    cv2.fillConvexPoly(eyes, cv2.convexHull(np.round(points[36:42]).astype(np.int32)), 1)
    assert np.array_equal(found["real eyes"][eyes > 0], real[eyes > 0])

    _, path, _ = drive_run
    scores = module.budget(open_store(load_workflow(path).store, mode="r"), Cast(), every=4)
    for feature in module.FEATURES:
        assert scores[f"real {feature}"][0] >= scores["as it is"][0], scores
    with pytest.raises(SystemExit, match="not a self-reenactment"):
        module.main([str(path)])


def test_the_series_carry_the_composites_signals_for_a_paired_comparison(drive_run, capsys):
    """series.json holds composite.mp4's expression signals beside the face alone's, whose gains are the
    evaluation's amplitude_composite; benchmarks/gain_difference.py --composite judges them (a run against
    itself: no difference)."""
    from persona.plugins.builtin.evaluate import amplitude

    folder, _, report = drive_run
    series = json.loads((folder / "output" / "series.json").read_text())
    driver, composited = (np.asarray(series[f"{who}_mouth_width"], float) for who in ("driver", "composite"))
    assert len(composited) == len(series["output_mouth_width"])
    figures = report["evaluation"]["amplitude_composite"]["mouth_width"]
    assert amplitude(driver, composited)["gain"] == pytest.approx(figures["gain"], nan_ok=True)
    creases = (np.asarray(series[f"{who}_creases"], float) for who in ("driver", "output"))  # between the brows
    between = report["evaluation"]["creases"]["face_alone"]
    assert amplitude(*creases)["gain"] == pytest.approx(between["gain"], nan_ok=True)
    module = _benchmark("gain_difference")
    capsys.readouterr()
    assert module.main([str(folder / "output"), str(folder / "output"), "--composite"]) == 0
    lines = capsys.readouterr().out.splitlines()[1:]
    assert len(lines) == 4 and all("+0.000 [+0.000, +0.000]" in line for line in lines)


def test_evaluate_command_prints_json(drive_run, capsys):
    _, path, report = drive_run
    capsys.readouterr()
    assert cli(["evaluate", str(path), "--json", "--scheduler", "sync"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["identity"]["fraction_b_not_a"] == pytest.approx(report["evaluation"]["identity"]["fraction_b_not_a"])
    assert result["expression"]["mouth_open"] == pytest.approx(report["evaluation"]["expression"]["mouth_open"], nan_ok=True)
    assert set(result["held"]) == set(result["amplitude"])  # each signal held: driver, face alone, composite
    assert all(set(h) == {"driver", "output", "composite"} for h in result["held"].values())
    # the synthetic puppet, its texture about the size the frame shows it, lighter than the driver: a little
    # softer than the driver's face (0.58-0.75 on its frames), not twice as sharp for being lighter
    assert all(0.4 < v < 1.2 for v in result["sharpness"].values()), result["sharpness"]
    # the creases between the brows, of the face alone and of composite.mp4 on the driver's
    assert set(result["creases"]) == {"face_alone", "composite"}
    assert all({"gain", "r", "driver_range"} <= set(a) for a in result["creases"].values())


def test_a_self_reenactment_gives_each_frames_psnr_and_shows_the_frame_least_like_the_real_one(drive_run):
    """Judged as a self-reenactment, the series hold each frame's PSNR against the driver's frame, the face
    alone's and the composite's, whose means are the evaluation's figures; the report plots them against their
    targets and puts the composite's worst frame among the peaks. A drive not judged so has neither."""
    from persona.dag.evaluate import evaluate
    from persona.dag.outputs import write_pictures
    from persona.dag.report import least_like_the_frame, plots
    from persona.dag.runner import executor_for

    folder, path, report = drive_run
    wf = load_workflow(path)
    with executor_for(wf, "sync", None) as ex:
        judged = evaluate(wf.store, ex, identity=wf.stage("identity"), self_reenactment=True)
    series, figures = judged["series"], judged["self_reenactment"]
    for name, figure in (("psnr_face_alone", "psnr_db"), ("psnr_composite", "psnr_db_composite")):
        psnr = np.asarray(series[name], float)
        assert len(psnr) == len(series["driver_mouth_open"]) and np.isfinite(psnr).sum() >= len(psnr) - 1
        assert np.nanmean(psnr) == pytest.approx(figures[figure])
    worst = int(np.nanargmin(series["psnr_composite"]))
    assert least_like_the_frame(series) == [("least like the real frame", worst)]
    assert "fidelity" in plots(series, 0.6, 25.0)
    unjudged = json.loads((folder / "output" / "series.json").read_text())
    assert "psnr_composite" not in unjudged and least_like_the_frame(unjudged) == []
    assert "fidelity" not in plots(unjudged, 0.6, 25.0)
    # where the composite missed, as a picture: the real frames' mean beside the error, which is 0 (blue)
    # far from the face the composite drew into the frame, and above it somewhere on the face; then the mean
    # difference, 0 (the scale's middle) far from the face
    picture = judged["pictures"]["error_map"]
    mean, heat, bias = np.split(picture, 3, axis=1)
    jet = cv2.cvtColor(cv2.applyColorMap(np.array([[0, 128]], np.uint8), cv2.COLORMAP_JET), cv2.COLOR_BGR2RGB)[0]
    assert (heat[0, 0] == jet[0]).all() and (heat != jet[0]).any(axis=-1).mean() > 0.1
    assert (bias[0, 0] == jet[1]).all() and (bias != jet[1]).any(axis=-1).mean() > 0.1
    assert not (folder / "output" / "error_map.png").exists()  # the run's drive was not judged so
    write_pictures(str(folder / "output"), judged["pictures"])
    assert (folder / "output" / "error_map.png").is_file()
    write_pictures(str(folder / "output"), {})  # judged again, not as a self-reenactment: no map left behind
    assert not (folder / "output" / "error_map.png").exists()


def test_a_puppet_driven_by_its_own_collection_judges_no_identity(drive_run):
    """Where the puppet is the driver (a self-reenactment from one collection) no descriptor is taken and
    identity is not judged (B is A); the expression figures are those of the same drive judged as two people."""
    from persona.dag.report import identity_caveat
    from persona.dag.runner import Runner, executor_for
    from persona.stores.layout import Cast

    _, path, report = drive_run
    wf = load_workflow(path)
    with executor_for(wf, "sync", None) as ex:
        own = Runner(wf, ex, progress=False).evaluate(Cast(driver="puppet"))
    faceless = report["evaluation"]["identity"]["frames_without_face"]
    assert own["identity"] == {"judged": False, "frames_judged": 0, "frames_without_face": faceless}
    assert np.isnan(own["series"]["distance_to_b"]).all() and np.isnan(own["series"]["distance_to_a"]).all()
    assert json.dumps(own["amplitude"]) == json.dumps(report["evaluation"]["amplitude"])
    assert "the puppet is the driver" in identity_caveat(own)


def test_identity_judged_on_a_few_frames_gives_every_frames_own_distances(drive_run):
    """evaluate.identity_frames: only every k-th frame is described, each with the distances it has when
    every frame is; the landmarks, and the figures made from them, stay every frame's."""
    from persona.dag.evaluate import identity_every
    from persona.dag.runner import Runner, executor_for

    _, path, _ = drive_run
    results = {}
    for frames in (0, 5):
        wf = load_workflow(path, [f"evaluate.identity_frames={frames}"])
        with executor_for(wf, "sync", None) as ex:
            results[frames] = Runner(wf, ex, progress=False).evaluate()
    every, n = identity_every(results[0]["frames"], 5), results[0]["frames"]
    assert (identity_every(16, 5), identity_every(15, 5), identity_every(4, 5), identity_every(1000, 0)) == (4, 3, 1, 1)
    assert results[5]["identity"]["frames_judged"] == len(range(0, n, every)) <= 5 < n
    full, few = results[0]["series"], results[5]["series"]
    judged = np.arange(n) % every == 0
    np.testing.assert_allclose(few["distance_to_b"][judged], full["distance_to_b"][judged])
    assert np.isnan(few["distance_to_b"][~judged]).all()
    assert json.dumps(results[5]["amplitude"]) == json.dumps(results[0]["amplitude"])
    assert results[5]["identity"]["frames_without_face"] == results[0]["identity"]["frames_without_face"]
    apart = results[0]["identity"]["distance_b_to_a"]  # the centroids of B's and A's photos: the frames do not matter
    assert np.isfinite(apart) and apart > 0 and results[5]["identity"]["distance_b_to_a"] == apart


def test_a_persons_centroid_is_kept_in_the_store_and_made_again_only_from_other_photos(drive_run, monkeypatch):
    """The centroid of a person's photo descriptors is kept in its collection: an evaluation after the
    run's own describes no photo; another sample of the photos describes them again; with the kept
    centroids gone, the photos are described again, to the same figures."""
    from persona.dag import evaluate as evaluation
    from persona.dag.runner import Runner, executor_for

    _, path, _ = drive_run
    described, describe = [], evaluation.describe_photos
    monkeypatch.setattr(evaluation, "describe_photos", lambda *task: described.append(task[1]) or describe(*task))
    wf = load_workflow(path, ["evaluate.identity_frames=2"])
    with executor_for(wf, "sync", None) as ex:
        kept = Runner(wf, ex, progress=False).evaluate()
        assert described == []  # the run kept both people's centroids
        Runner(load_workflow(path, ["evaluate.identity_frames=2", "evaluate.collection_sample=3"]), ex,
               progress=False).evaluate()
        assert sorted(described) == ["driver", "driver", "puppet", "puppet"]  # two tasks each
        for person in ("puppet", "driver"):
            shutil.rmtree(Path(wf.store) / person / "identity")
        again = Runner(wf, ex, progress=False).evaluate()
    assert len(described) == 8
    assert json.dumps(again["identity"]) == json.dumps(kept["identity"])


def test_evaluating_a_store_from_before_the_screen_says_to_run_again(drive_run, tmp_path, capsys):
    """A store written before the collection's screen existed has no accepted photos by today's
    rule: the evaluation says so and what to do, rather than judging identity against nothing."""
    folder, path, _ = drive_run
    wf = yaml.safe_load(path.read_text())
    old = tmp_path / "old.zarr"
    shutil.copytree(path.parent / wf["store"], old)
    shutil.rmtree(old / "puppet" / "status" / "screen")
    wf.update(store=str(old), output=str(tmp_path / "out"))
    copy = folder / "old.yaml"
    copy.write_text(yaml.safe_dump(wf))
    capsys.readouterr()
    assert cli(["evaluate", str(copy), "--json", "--scheduler", "sync"]) != 0
    err = capsys.readouterr().err
    assert "older Persona" in err and "persona run" in err and "puppet" in err


def test_texture_evaluation_holds_out_references_and_scores_every_method(drive_run, capsys):
    folder, path, _ = drive_run
    assert cli(["evaluate", str(path), "--texture", "--references", "2", "--scheduler", "sync", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert len(result["references"]) == 2 and result["collection_photos"] == 8
    table = result["table"]
    assert set(table) == {"static", "weighted", "prewarped", "multiscale", "reference"}
    for name in ("static", "weighted", "prewarped", "multiscale"):
        assert table[name]["detail_median"] > 0 and -1 <= table[name]["fidelity_median"] <= 1
    # one colour for every target (the coarsest level is shared) against the weighted average's drift
    assert table["multiscale"]["colour_spread_pct"] < table["weighted"]["colour_spread_pct"]
    grid = media.decode_image(result["grid"])
    assert grid.shape == (28 + 2 * 244, 5 * 194, 3)
    saved = json.loads((folder / "output" / "puppet_texture_evaluation.json").read_text())
    assert saved["table"] == table and saved["mode"] == "reference"
    # the same references with their fiducials alone as the target: another file, other figures
    # (and two of the methods only, each aligned with ours' flow)
    assert cli(["evaluate", str(path), "--texture", "--references", "2", "--scheduler", "sync", "--json",
                "--mode", "fiducials", "--methods", "multiscale,static"]) == 0
    fiducials = json.loads(capsys.readouterr().out)
    assert fiducials["mode"] == "fiducials" and fiducials["references"] == result["references"]
    assert set(fiducials["table"]) == {"static", "multiscale", "reference"}
    assert fiducials["methods"]["static"]["flow"] == fiducials["methods"]["multiscale"]["flow"]
    assert fiducials["table"]["multiscale"] != table["multiscale"]
    assert (folder / "output" / "puppet_texture_evaluation_fiducials.json").is_file()
    assert set(fiducials["paired_alignment"]) <= {"static"}


def test_texture_evaluation_pairs_methods_reference_by_reference():
    from persona.dag.texture_eval import paired

    # ours beats (ii) on 3 of 4 references; the one dlib missed (NaN) is left out of (iii)'s pairs
    errors = {"multiscale": [1.0, 2.0, 3.0, 4.0], "static": [1.5, 2.5, 3.5, 3.0], "weighted": [2.0, np.nan, 4.0, 5.0]}
    rows = [{"methods": {m: {"alignment": e[i]} for m, e in errors.items()}} for i in range(4)]
    result = paired(rows)
    assert set(result) == {"static", "weighted"}
    assert result["static"]["ours_better"] == 3 and result["static"]["references"] == 4
    assert result["static"]["median"] == pytest.approx(-0.5) and result["static"]["mean"] == pytest.approx(-0.125)
    assert result["static"]["standard_error"] == pytest.approx(np.std([-0.5, -0.5, -0.5, 1.0], ddof=1) / 2)
    assert result["weighted"]["references"] == 3 and result["weighted"]["mean"] == pytest.approx(-1.0)


def test_3d_drive_moves_the_puppets_mesh_with_the_driver(drive_run):
    from persona.stores.layout import Collection, open_store

    folder, _, _ = drive_run
    root = open_store(str(folder / "run.zarr"), mode="r")
    drive, puppet = Collection(root, "drive"), Collection(root, "puppet")
    meshes = drive.array("mesh")[:]
    face = puppet.array("shape/mask")[...]
    assert meshes.shape == (16, 244, 194, 3) and np.isfinite(meshes[:, face]).all()
    assert np.isnan(meshes[:, ~face]).all()
    rest = np.stack(np.mgrid[0:244, 0:194][::-1], axis=-1)
    moved = np.linalg.norm(meshes[..., :2][:, face] - rest[face], axis=-1)
    assert 0.05 < np.median(moved) < 5  # the driver's motion moves B's mesh, which stays a face
    motion = np.linalg.norm(meshes[:, face] - meshes[:, face].mean(axis=0), axis=-1)
    assert motion.mean() > 0.05  # and differently in different frames
    phi = drive.array("motion/correspondence")[...]
    assert np.median(np.linalg.norm(phi[face] - rest[face], axis=-1)) < 10
    assert set(drive.state("dynamics")) <= {1, 2} and (drive.state("dynamics") == 1).mean() > 0.8


def test_2d_baseline_renders_into_the_same_store(drive_run, capsys):
    folder, path, _ = drive_run
    assert cli(["run", str(path), "--scheduler", "sync", "--quiet", "--set", "stages.render.backend=tps2d",
                "--set", "output=output_2d"]) == 0
    metrics = json.loads((folder / "output_2d" / "metrics.json").read_text())
    assert "render" in {r["stage"] for r in metrics["stages"]}
    assert metrics["evaluation"]["frames"] == 16
    assert media.VideoReader(folder / "output_2d" / "puppet.mp4").n_frames == 16


def test_the_drivers_neutral_from_its_collection_retargets_again(drive_run, tmp_path):
    """``neutral: collection`` measures the driver's offsets from its photo collection's mean rather than
    its clip's: the retarget runs again rather than keep the clip's targets, and at the brows and the nose
    (no lid or lip rule moves them) each target is B's mean plus the frame's offset from the collection's
    mean, scaled by the faces' proportions, to 1e-6 px."""
    from persona.dag.stages import accepted
    from persona.plugins.face.fiducials import mean_shape
    from persona.plugins.face.warp import eye_mouth_scale
    from persona.stores.layout import Collection, open_store

    folder = tmp_path / "copy"  # a copy: the other tests read the run's own targets
    shutil.copytree(drive_run[0], folder)
    path = folder / drive_run[1].name

    def read():
        root = open_store(str(folder / "run.zarr"), mode="r")
        return root, Collection(root, "drive").array("target")[:]
    root, clip_targets = read()
    assert cli(["run", str(path), "--scheduler", "sync", "--quiet", "--set", "stages.render.backend=tps2d",
                "--set", "stages.motion.params.neutral=collection", "--set", "output=output_neutral"]) == 0
    root, targets = read()
    frames, puppet = Collection(root, "driver/frames"), Collection(root, "puppet")
    mean = puppet.array("aligned/mean_fiducials")[...]
    clip = mean_shape(frames.array("aligned/fiducials")[:][accepted(frames)])
    collection = Collection(root, "driver").array("aligned/mean_fiducials")[...]
    assert np.abs(clip - collection).max() > 0.5  # the two neutrals differ
    still = slice(0, 19)  # the brows and the nose among the 49
    offsets = (clip_targets - mean) / (eye_mouth_scale(mean) / eye_mouth_scale(clip)) + clip - collection
    expected = mean + offsets * (eye_mouth_scale(mean) / eye_mouth_scale(collection))
    np.testing.assert_allclose(targets[:, still], expected[:, still], atol=1e-6)
    assert Collection(root, "drive").provenance("target").params["neutral"] == "collection"


def test_auto_neutral_is_the_collection_only_where_the_driver_is_the_puppet():
    """``neutral: auto`` (the default) measures a self-reenactment's driver from its collection, the
    puppet's own, and every other drive from its clip, as the paper does; a named choice is kept."""
    from persona.dag.drive import driver_neutral
    from persona.stores.layout import Cast

    itself = Cast("people/bea", "people/bea", "videos/bea_rest", "drives/bea_bea_rest")
    other = Cast("people/bea", "people/al", "videos/al", "drives/bea_al")
    assert driver_neutral("auto", itself) == "collection" and driver_neutral("auto", other) == "clip"
    assert driver_neutral("auto", Cast()) == "clip"  # a format-1 store: puppet and driver apart
    assert driver_neutral("clip", itself) == "clip" and driver_neutral("collection", other) == "collection"


def test_3d_run_after_a_2d_run_renders_again(drive_run):
    """The 2D and 3D renderers write the same render/* arrays: after a 2D run into the store, the
    3D run's own finished render stage is stale and runs again (it once kept the 2D frames)."""
    from persona.stores.layout import Collection, open_store

    folder, path, _ = drive_run
    assert cli(["run", str(path), "--scheduler", "sync", "--quiet", "--set", "stages.render.backend=tps2d",
                "--set", "output=output_2d"]) == 0
    drive = Collection(open_store(str(folder / "run.zarr"), mode="r"), "drive")
    assert drive.provenance("render/rgb").stage == "render"
    assert cli(["run", str(path), "--scheduler", "sync", "--quiet", "--set", "output=output_3d"]) == 0
    drive = Collection(open_store(str(folder / "run.zarr"), mode="r"), "drive")
    assert drive.provenance("render/rgb").stage == "render3d"
    two_d = json.loads((folder / "output_2d" / "metrics.json").read_text())["evaluation"]
    three_d = json.loads((folder / "output_3d" / "metrics.json").read_text())["evaluation"]
    assert "motion" in three_d and "motion" not in two_d
    assert three_d["expression"] != two_d["expression"]


def test_the_texture_cache_made_a_shard_at_a_time_is_the_whole_collections(drive_run, monkeypatch):
    """The run builds B's texture cache in tasks over shards of 4 photos (each step's sums, the
    basis by a randomised SVD over the shards); done on all 10 photos at once in memory with the
    same steps, the pyramids agree to 1e-3 of their range and the neutral texture to 1 level of 255.
    A drive's textures read the cache a block at a time: with no room to keep any block between
    tasks they are the run's but for a value in 10,000 one level off (the matrix products' last bit
    depends on how BLAS splits them, which its threads change); in blocks of one shard each, kept one
    at a time, within a level (the sums add in another order)."""
    from persona.dag import texture as texture_module
    from persona.plugins.face.blend import seen_mean, seen_sums
    from persona.plugins.face.texture import to_grey, warped_basis
    from persona.stores.layout import OK, Collection, open_store

    folder, path, _ = drive_run
    root = open_store(str(folder / "run.zarr"), mode="r")
    puppet, drive = Collection(root, "puppet"), Collection(root, "drive")
    assert puppet.shard == 4 and not puppet.has("texture/warped_grey")  # the steps' own arrays are gone
    backend = texture_module.texture_backend(type("R", (), {"wf": load_workflow(path)})())[2]
    ok = np.flatnonzero(puppet.state("align") == OK)
    photos = texture_module.texture_photos(puppet, ok)
    target = puppet.array("aligned/mean_fiducials")[...].astype(np.float64)
    warped, maps = backend.params.warped(photos, target)
    fill = seen_mean(*seen_sums(warped.rgb, warped.valid))
    basis = warped_basis(to_grey(warped.rgb), warped.valid, fill, backend.params.rank)
    whole = backend.cache(backend.params.flowed(photos, warped, maps, basis), fill)
    for k in range(whole.levels):
        stored = puppet.rows(f"texture/weighted_{k}", ok)
        assert np.abs(stored - whole.weighted[k]).max() < 1e-3 * np.ptp(whole.weighted[k]), k
    neutral = backend.blend(whole, photos.fiducials, target, gazes=texture_module.load_cache(puppet)[2])
    assert np.abs(puppet.array("texture/neutral")[...].astype(float) - neutral).max() <= 1.0

    monkeypatch.setattr(texture_module, "CACHE_BYTES", 1)  # every task reads every block it needs
    texture_module._blocks.clear()
    name, params = load_workflow(path).stage("texture")
    for start, stop in drive.shard_ranges()[:2]:  # as the run's tasks made them: a shard of frames each
        again = texture_module.stored_textures(str(folder / "run.zarr"), "puppet", name, params, drive.array("target"),
                                               start, stop, gaze=drive.array("eyes/gaze")[start:stop])
        off = np.abs(again.round() - drive.array("texture/rgb")[start:stop])
        assert off.max() <= 1 and np.count_nonzero(off) <= 1e-4 * off.size, (off.max(), np.count_nonzero(off))
    monkeypatch.setattr(texture_module, "BLOCK_BYTES", 1)  # a block a shard of photos: three blocks
    texture_module._blocks.clear()
    again = texture_module.stored_textures(str(folder / "run.zarr"), "puppet", name, params, drive.array("target"),
                                           0, 4, gaze=drive.array("eyes/gaze")[:4])
    assert np.abs(again.round() - drive.array("texture/rgb")[:4]).max() <= 1
    assert len(texture_module._blocks) == 1


def test_a_worker_loads_the_cache_totals_and_the_photos_gazes_once(drive_run, monkeypatch):
    """Two shards of a drive's textures in one process: the cache's totals and where B's photos look are
    read once (kept as one entry, they once evicted each other and were made again for every shard: the
    frame textures took 251 ms a frame where they took 43), and where the photos look is never measured by
    a drive: the texture stage stored it."""
    from persona.dag import stages as st
    from persona.dag import texture as texture_module
    from persona.stores.layout import Collection, open_store

    folder, path, _ = drive_run
    calls = {"_totals": 0, "photo_looks": 0}
    for name in calls:
        real = getattr(texture_module, name)

        def counted(*args, _real=real, _name=name):
            calls[_name] += 1
            return _real(*args)
        monkeypatch.setattr(texture_module, name, counted)
    st._loaded.clear()
    name, params = load_workflow(path).stage("texture")
    root = open_store(str(folder / "run.zarr"), mode="r")
    targets, gaze = Collection(root, "drive").array("target"), Collection(root, "drive").array("eyes/gaze")
    for start, stop in ((0, 4), (4, 8)):
        texture_module.stored_textures(str(folder / "run.zarr"), "puppet", name, params, targets, start, stop,
                                       gaze=gaze[start:stop])
    assert calls == {"_totals": 1, "photo_looks": 0}


def test_a_workers_dynamics_shards_share_one_driver_model(drive_run, tmp_path, monkeypatch):
    """Two shards of the driver's dynamics made again in one process load the driver's model once (it
    was loaded for every shard, with its landmark spline and shading operators: 0.3 s a shard), and make
    the same flows to the bit."""
    import dataclasses

    from persona.dag import stages as st
    from persona.stores.layout import PENDING, Collection, open_store

    folder, _, _ = drive_run
    shutil.copytree(folder / "run.zarr", tmp_path / "run.zarr")
    url = str(tmp_path / "run.zarr")
    drive = Collection(open_store(url), "drive")
    before = drive.array("dynamics/flow")[0:8]
    loads = []

    def counted(root, path):
        loads.append(path)
        return st.driver_model(root, path)
    monkeypatch.setitem(st.PHOTO_STAGES, "dynamics", dataclasses.replace(st.DYNAMICS, context=counted))
    drive.write_status("dynamics", 0, np.full(8, PENDING, np.int8), [""] * 8)
    drive.array("dynamics/flow")[0:8] = 0
    st._loaded.clear()
    backend = drive.provenance("status/dynamics/state").backend
    for start, stop in ((0, 4), (4, 8)):
        st.run_chain(url, "drive", start, stop, [("dynamics", backend, drive.provenance("dynamics/flow").params)])
    assert loads == ["drive"]
    np.testing.assert_array_equal(drive.array("dynamics/flow")[0:8], before)


def test_a_shape_from_fewer_photos_than_the_collection_reads_only_those(drive_run):
    """With ``max_images`` 8 of the 10 photos, the shape's task reads 8 (the others get no lights),
    and the run goes on; back at the default, all 10 again."""
    from persona.stores.layout import Collection, open_store

    folder, path, _ = drive_run
    lights = lambda: Collection(open_store(str(folder / "run.zarr"), mode="r"), "puppet").array("shape/lighting")[:]
    assert cli(["run", str(path), "--scheduler", "sync", "--quiet", "--set", "stages.shape.params.max_images=8"]) == 0
    assert np.isfinite(lights()).all(axis=1).sum() == 8
    assert cli(["run", str(path), "--scheduler", "sync", "--quiet"]) == 0
    assert np.isfinite(lights()).all(axis=1).sum() == 10


def test_texture_backend_without_video_mode_falls_back_to_the_static_average(drive_run):
    from persona.stores.layout import Collection, open_store

    folder, path, _ = drive_run
    assert cli(["run", str(path), "--scheduler", "sync", "--quiet", "--set", "stages.texture.backend=static",
                "--set", "stages.render.backend=tps2d", "--set", "output=output_static"]) == 0
    root = open_store(str(folder / "run.zarr"), mode="r")
    puppet, drive = Collection(root, "puppet"), Collection(root, "drive")
    assert not puppet.has("texture/neutral")
    mean = np.clip(puppet.array("aligned/mean")[...], 0, 255).round().astype(np.uint8)
    textures = drive.array("texture/rgb")[:]
    assert (textures == mean).all()
    # and back to the default: the cache and the per-frame textures come back
    assert cli(["run", str(path), "--scheduler", "sync", "--quiet"]) == 0
    assert Collection(open_store(str(folder / "run.zarr"), mode="r"), "puppet").has("texture/neutral")


def test_every_group_of_the_store_opens_in_xarray(drive_run):
    """Each dimension name has one size within a group (49 fiducials are not 68 landmarks, each
    pyramid level has its own y and x), so xarray.open_zarr opens every group of a run's store."""
    import xarray as xr
    import zarr

    folder, _, _ = drive_run
    store = str(folder / "run.zarr")
    opened = []

    def walk(group, path):
        if any(True for _ in group.array_keys()):
            ds = xr.open_zarr(store, group=path or None, consolidated=False)
            opened.append(path)
            assert set(ds.data_vars) == set(group.array_keys()), path
        for name, child in group.groups():
            walk(child, f"{path}/{name}" if path else name)

    walk(zarr.open_group(store, mode="r"), "")
    for path in ("puppet/aligned", "puppet/landmarks", "puppet/texture", "drive", "drive/render"):
        assert path in opened, opened
    ds = xr.open_zarr(store, group="puppet/aligned", consolidated=False)
    assert ds.sizes["fiducial"] == 49 and ds.sizes["landmark"] == 68


def test_a_run_killed_during_the_frame_textures_resumes_to_complete_textures(tmp_path, monkeypatch):
    """A run interrupted after the first shard of per-frame textures (the issue: the array's key was
    written before its data, the next run skipped it and rendered black faces) resumes to textures
    equal to the backend's for every frame, none left black."""
    import persona.dag.texture as texture_module
    from persona.stores.layout import Collection, open_store

    path = make_demo_data(tmp_path, n_photos=10, n_frames=8)
    wf = yaml.safe_load(path.read_text())
    wf["photos_per_shard"] = 4
    path.write_text(yaml.safe_dump(wf))
    real = texture_module.frame_textures
    shards = []

    def dying(*args):
        shards.append(args[2])
        if len(shards) == 2:  # the first shard of 4 frames written, the second not
            raise KeyboardInterrupt
        return real(*args)

    monkeypatch.setattr(texture_module, "frame_textures", dying)
    with pytest.raises(KeyboardInterrupt):
        run_workflow(load_workflow(path), scheduler="sync", progress=False)
    root = open_store(str(tmp_path / "run.zarr"), mode="r")
    assert Collection(root, "drive").provenance("texture/rgb") is None  # not to be trusted
    monkeypatch.setattr(texture_module, "frame_textures", real)
    run_workflow(load_workflow(path), scheduler="sync", progress=False)
    root = open_store(str(tmp_path / "run.zarr"), mode="r")
    drive, puppet = Collection(root, "drive"), Collection(root, "puppet")
    textures = drive.array("texture/rgb")[:]
    assert textures.reshape(len(textures), -1).max(axis=1).min() > 0  # no black frame
    cache, fiducials, gazes = texture_module.load_cache(puppet)
    backend = texture_module.texture_backend(type("R", (), {"wf": load_workflow(path)})())[2]
    for t in (1, 5, 7):  # the stored bytes are the backend's blend rounded; the drive sums the photos a shard at
        # a time, so a value within float32 noise (1e-4) of a half level may round the other way
        exact = backend.blend(cache, fiducials, drive.array("target")[t], gaze=drive.array("eyes/gaze")[t],
                              gazes=gazes)
        assert np.abs(textures[t] - exact).max() <= 0.5 + 1e-3


def _small_run(folder, **texture):
    """A small workflow (10 photos, 8 frames, shards of 4) with the texture params ``texture``, run;
    returns its workflow file."""
    path = make_demo_data(folder, n_photos=10, n_frames=8)
    _run_with(path, **texture)
    return path


def _run_with(path, **texture):
    """Run the workflow ``path`` again with the texture params ``texture`` (the others at their defaults)."""
    wf = yaml.safe_load(path.read_text())
    wf["photos_per_shard"] = 4
    wf.setdefault("stages", {})["texture"] = {"params": texture}
    path.write_text(yaml.safe_dump(wf))
    run_workflow(load_workflow(path), scheduler="sync", progress=False)


def _cache_state(folder) -> dict:
    """Per array of the puppet's texture cache: its provenance key and time, and its files' mtimes."""
    from persona.dag.texture import _cache_arrays
    from persona.stores.layout import Collection, open_store

    puppet = Collection(open_store(str(folder / "run.zarr"), mode="r"), "puppet")
    state = {}
    for name in _cache_arrays(puppet):
        made = puppet.provenance(name)
        files = sorted((folder / "run.zarr" / "puppet" / name).rglob("*"))
        state[name] = (made and made.key, made and made.created, [(f.name, f.stat().st_mtime_ns) for f in files])
    return state


def test_a_frame_param_keeps_the_texture_cache_a_cache_param_builds_it_again(tmp_path, monkeypatch):
    """Changing params that act only on the blend of each frame (``detail_share``, ``sigma``: the
    backend's ``frame_params``) leaves every array of the texture cache as it was (provenance and
    files), and the neutral texture and every frame's texture are those of a fresh store made with
    the new params. Changing cache params (``levels``, ``detail_blur``) builds the cache again, no
    earlier level left over, and the frames' textures are made from the new cache (none from a copy
    of the old one that a process kept); a run killed while building it leaves no cache that counts
    as done."""
    import persona.dag.texture as texture_module
    from persona.plugins.builtin.texture import MultiscaleTexture
    from persona.stores.layout import Collection, open_store

    def arrays(folder):
        root = open_store(str(folder / "run.zarr"), mode="r")
        return Collection(root, "puppet"), Collection(root, "drive")

    path = _small_run(tmp_path / "a")
    before = _cache_state(tmp_path / "a")
    assert len(before) == 5 * 5 and all(key for key, _, _ in before.values())
    puppet, drive = arrays(tmp_path / "a")
    neutral, textures = puppet.array("texture/neutral")[...], drive.array("texture/rgb")[:]
    made = puppet.provenance("texture/neutral").key, drive.provenance("texture/rgb").key

    frame_only = {"detail_share": 1.0, "sigma": 5.0}
    assert set(frame_only) <= MultiscaleTexture.frame_params
    _run_with(path, **frame_only)
    assert _cache_state(tmp_path / "a") == before
    puppet, drive = arrays(tmp_path / "a")
    assert puppet.provenance("texture/neutral").key != made[0] and drive.provenance("texture/rgb").key != made[1]
    assert not np.array_equal(puppet.array("texture/neutral")[...], neutral)
    assert not np.array_equal(drive.array("texture/rgb")[:], textures)
    _small_run(tmp_path / "b", **frame_only)
    fresh_puppet, fresh_drive = arrays(tmp_path / "b")
    np.testing.assert_array_equal(puppet.array("texture/neutral")[...], fresh_puppet.array("texture/neutral")[...])
    np.testing.assert_array_equal(drive.array("texture/rgb")[:], fresh_drive.array("texture/rgb")[:])

    cache_change = {"levels": 4, "detail_blur": 2.0}  # every level's weights change, one level goes
    real, shards = texture_module.cache_shard, []

    def dying(*args):  # the second shard's pyramids not written
        shards.append(args[2])
        if len(shards) == 2:
            raise KeyboardInterrupt
        return real(*args)

    monkeypatch.setattr(texture_module, "cache_shard", dying)
    with pytest.raises(KeyboardInterrupt):
        _run_with(path, **cache_change, **frame_only)
    puppet, _ = arrays(tmp_path / "a")
    assert puppet.provenance(texture_module.CACHE_DONE) is None and not puppet.has("texture/neutral")
    monkeypatch.setattr(texture_module, "cache_shard", real)
    _run_with(path, **cache_change, **frame_only)
    after = _cache_state(tmp_path / "a")
    assert sorted(after) == sorted(name for name in before if not name.endswith("_4"))
    assert all(after[name][0] != before[name][0] and after[name][1] != before[name][1] for name in after)
    puppet, drive = arrays(tmp_path / "a")
    cache, fiducials, gazes = texture_module.load_cache(puppet)
    assert cache.levels == 4
    backend = texture_module.texture_backend(type("R", (), {"wf": load_workflow(path)})())[2]
    for t in (0, 3, 7):  # summed a shard of photos at a time, the detail restored: to 1 level of 255
        expect = backend.blend(cache, fiducials, drive.array("target")[t], gaze=drive.array("eyes/gaze")[t],
                               gazes=gazes)
        assert np.abs(drive.array("texture/rgb")[t] - expect).max() <= 1.0, t


def test_a_texture_evaluation_joins_the_report(drive_run):
    """`persona evaluate --texture` writes its table and grid into the output folder and makes the
    report again (plots from series.json included): the page then shows the Fig. 5 table."""
    from persona.dag.cli import _refresh_report

    folder, path, _ = drive_run
    out = folder / "output"
    assert (out / "series.json").is_file()
    grid = np.full((60, 200, 3), 200, np.uint8)
    media.write_png(out / "puppet_texture_grid.png", grid)
    table = {m: {"alignment_median_pct_iod": 2.0, "no_face_found": 0, "detail_median": 0.8, "fidelity_median": 0.7,
                 "colour_spread_pct": 1.0} for m in ("static", "multiscale")}
    (out / "puppet_texture_evaluation.json").write_text(json.dumps({
        "collection": "puppet", "mode": "reference", "references": [1, 2, 3], "collection_photos": 7,
        "table": table, "grid": str(out / "puppet_texture_grid.png")}))
    try:
        page = _refresh_report(load_workflow(path)).read_text()
        assert "Texture synthesis (paper Fig. 5): 3 held-out references" in page and "ours (multiscale)" in page
        assert page.count("data:image/png;base64,") >= 6  # the grid, besides the plots and pictures
    finally:
        (out / "puppet_texture_evaluation.json").unlink()
        (out / "puppet_texture_grid.png").unlink()
        _refresh_report(load_workflow(path))


def test_a_new_output_folder_gets_the_meshes_from_the_stored_shape(drive_run):
    """The shape is in the store; a run into a new output folder writes its mesh files from it
    instead of computing the shape again (it once took a minute on a real collection)."""
    folder, path, _ = drive_run
    depth = folder / "run.zarr" / "puppet" / "shape" / "depth" / "zarr.json"
    written = depth.stat().st_mtime_ns
    assert cli(["run", str(path), "--scheduler", "sync", "--quiet", "--set", "output=output_new"]) == 0
    for name in ("puppet_mesh.ply", "puppet_mesh.obj", "puppet_mesh_previews.png", "driver_mesh.ply"):
        assert (folder / "output_new" / name).stat().st_size > 0, name
    assert depth.stat().st_mtime_ns == written  # not computed again


def test_a_video_decoded_before_is_not_decoded_again(drive_run):
    """A re-run skips the decoding of a video collection whose frames are all in the store (it once
    decoded the whole video again and counted its frames twice: "done: 1800 of 900 frames")."""
    from persona.dag import stages as st

    folder, _, _ = drive_run
    summary = st.ingest_video(str(folder / "run.zarr"), "driver/frames", {})["ingest"]
    assert summary["skipped"] and summary["n"] == 16


def test_a_drive_made_again_reports_its_own_speed(drive_run):
    """The drive removed from the store and made again (the same frames, so the videos and the
    evaluation are kept): metrics.json gives this run's speed, not the last one's (benchmarks/
    drive_speed.py does exactly this; it once printed the first run's figure every time)."""
    folder, path, _ = drive_run
    metrics = folder / "output" / "metrics.json"
    first = metrics.read_text()
    before = json.loads(first)
    shutil.rmtree(folder / "run.zarr" / "drive")  # made again below, the same bytes
    try:
        assert cli(["run", str(path), "--scheduler", "sync", "--quiet"]) == 0
        after = json.loads(metrics.read_text())
    finally:
        metrics.write_text(first)  # as the other tests of the module know it
    assert after["outputs_key"] == before["outputs_key"]  # the same frames: videos and evaluation kept
    assert "videos" not in {r["stage"] for r in after["stages"]}
    assert after["evaluation"] == before["evaluation"]
    assert after["speed"]["ms_per_driver_frame"] != before["speed"]["ms_per_driver_frame"]
    assert after["speed"]["evaluate_seconds"] == before["speed"]["evaluate_seconds"]


def test_an_output_folder_copied_elsewhere_keeps_its_own_videos(drive_run):
    """A finished drive's output folder copied to a new place and run into: nothing is made again, and its
    metrics.json names the videos in the new folder (it named the first folder's, which it kept)."""
    folder, path, _ = drive_run
    shutil.copytree(folder / "output", folder / "output_copy")
    assert cli(["run", str(path), "--scheduler", "sync", "--quiet", "--set", "output=output_copy"]) == 0
    after = json.loads((folder / "output_copy" / "metrics.json").read_text())
    assert "videos" not in {r["stage"] for r in after["stages"]}
    assert after["videos"] and all(Path(v).parent == folder / "output_copy" for v in after["videos"].values())


def test_new_figures_evaluate_a_finished_drive_again(drive_run, monkeypatch):
    """A run whose evaluation's figures changed since (dag/evaluate.py's VERSION raised: a figure added,
    as the gains' intervals were) evaluates again, though nothing it is made from changed; it kept the
    old metrics.json before, without the new figure."""
    from persona.dag import evaluate

    folder, path, _ = drive_run
    metrics = folder / "output" / "metrics.json"
    first = metrics.read_text()
    monkeypatch.setattr(evaluate, "VERSION", evaluate.VERSION + 1)
    try:
        assert cli(["run", str(path), "--scheduler", "sync", "--quiet"]) == 0
        after = json.loads(metrics.read_text())
    finally:
        metrics.write_text(first)  # as the other tests of the module know it
    assert after["outputs_key"] != json.loads(first)["outputs_key"]
    assert "evaluate" in {r["stage"] for r in after["stages"]}
    # the drive was not made again: its speed is the last run's, not lost
    assert after["speed"]["ms_per_driver_frame"] == json.loads(first)["speed"]["ms_per_driver_frame"]


def test_the_videos_are_made_while_the_workers_evaluate_and_none_is_left_half_made_when_the_run_stops(
        drive_run, monkeypatch):
    """The videos are encoded in the run's own process while the evaluation runs: both steps have begun before
    either ends. Ctrl-C during the evaluation stops the videos too, and no video, whole or in part, is left in
    the output folder; the next run makes them."""
    from persona.dag import drive as drive_module
    from persona.dag.runner import Runner

    folder, path, _ = drive_run
    out = folder / "output_stopped"
    slow = drive_module.alone

    def alone(*args):  # 50 ms a frame: the videos are still being made when the evaluation stops
        time.sleep(0.05)
        return slow(*args)

    began = threading.Event()

    def evaluate(self, *args, **kwargs):
        began.set()
        raise KeyboardInterrupt

    monkeypatch.setattr(drive_module, "alone", alone)
    monkeypatch.setattr(Runner, "evaluate", evaluate)
    assert cli(["run", str(path), "--scheduler", "sync", "--quiet", "--set", f"output={out.name}"]) == 130
    assert began.is_set()
    assert not [p.name for p in out.iterdir() if ".mp4" in p.name]  # nor a temporary one
    monkeypatch.undo()

    assert cli(["run", str(path), "--scheduler", "sync", "--quiet", "--set", f"output={out.name}"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert all(Path(metrics["videos"][k]).is_file() for k in ("puppet", "side_by_side", "composite"))
    steps = {r["stage"]: r["wall_seconds"] for r in metrics["stages"] if r["collection"] == "drive"}
    assert metrics["speed"]["outputs_seconds"] >= max(steps["videos"], steps["evaluate"]) - 0.01
    assert metrics["speed"]["outputs_seconds"] < steps["videos"] + steps["evaluate"]  # side by side

"""Workflow format 2: people built once, every drive of them in one run (docs/batch.md)."""

import contextlib
import io
import json
import shutil

import numpy as np
import pytest
import yaml
import zarr

from persona.dag.cli import main as cli
from persona.dag.runner import run_workflow
from persona.dag.workflow import WorkflowError, load_workflow, parse_workflow
from persona.stores import media
from persona.stores.layout import Cast, Collection, open_store, summarize

from pipeline import assert_same_store

#: conftest.py's batch's settings, so that a run here of its people and drives makes its store
SETTINGS = {"photos_per_shard": 4, "stages": {"pose": {"params": {"focal_factor": 2.0}}},
            "evaluate": {"identity_frames": 2, "collection_sample": 4}}


def _people_workflow(folder, drives) -> dict:
    return {"version": 2, "name": "two puppets", "store": "people.zarr", "output": "people",
            "people": {"bea": {"photos": "data/bea/*.png"}, "cy": {"photos": "data/cy/*.png"},
                       "al": {"photos": "data/al/*.png"}},
            "drives": drives, **SETTINGS}


def _run(folder, data: dict, name: str):
    path = folder / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with contextlib.redirect_stderr(io.StringIO()):
        return run_workflow(load_workflow(path), scheduler="sync", progress=False)


@pytest.fixture(scope="module")
def people_run(batch, tmp_path_factory):
    """Two puppets (bea, cy) driven by al's video (8 frames) in one version-2 run in this process (the
    photos and video of conftest.py's batch, copied: tests here add to them), and bea driven by the same
    video in a version-1 run of its own, from the same photos."""
    folder = tmp_path_factory.mktemp("people")
    shutil.copytree(batch[0] / "data", folder / "data")
    drives = [{"puppet": ["bea", "cy"], "driver": "al", "video": "data/al.mp4"}]
    report = _run(folder, _people_workflow(folder, drives), "people.yaml")
    one = {"version": 1, "name": "bea alone", "puppet": {"photos": "data/bea/*.png"},
           "driver": {"photos": "data/al/*.png", "video": "data/al.mp4"}}
    alone = _run(folder, {**one, **SETTINGS, "store": "alone.zarr", "output": "alone"}, "alone.yaml")
    return folder, drives, report, alone


def test_each_puppet_gets_its_own_drive_and_folder(people_run):
    folder, _, report, _ = people_run
    assert set(report["drives"]) == {"bea_al_al", "cy_al_al"}
    for name in report["drives"]:
        out = folder / "people" / name
        for file in ("composite.mp4", "puppet.mp4", "frames.png", "metrics.json", "report.html"):
            assert (out / file).is_file(), out / file
        with media.VideoReader(out / "composite.mp4") as video:
            assert video.n_frames == 8
    page = (folder / "people" / "index.html").read_text()  # the batch page: every drive, linking its report
    assert 'href="bea_al_al/report.html"' in page and 'href="cy_al_al/report.html"' in page
    assert page.count("<img") >= 2 + 3  # a poster per drive, the people's pictures


def test_each_person_and_the_video_are_built_once(people_run):
    """Three people and one video, whatever uses them: one shape per person, one ingest of the video."""
    _, _, report, _ = people_run
    shapes = sorted(r["collection"] for r in report["stages"] if r["stage"] == "shape")
    assert shapes == ["people/al", "people/bea", "people/cy"]
    textures = sorted(r["collection"] for r in report["stages"] if r["stage"] == "texture")
    assert textures == ["people/bea", "people/cy"]  # puppets only: al only drives
    ingests = [r for r in report["stages"] if r["stage"] == "ingest" and r["collection"] == "videos/al"]
    assert len(ingests) == 1 and ingests[0]["n_done"] == 8


def test_inspect_shows_what_built_each_person_and_which_drives_use_it(people_run, tmp_path, capsys):
    """`persona inspect`: each person and video names the drives that use it, and every collection
    the stages that built it, in the order they ran; an array a run left unfinished is named."""
    folder, _, _, _ = people_run
    found = summarize(str(folder / "people.zarr"))["collections"]
    assert {"drives/bea_al_al", "drives/cy_al_al"} <= set(found["people/al"]["used_by"])
    assert {"drives/bea_al_al", "drives/cy_al_al"} <= set(found["videos/al"]["used_by"])
    assert found["people/bea"]["used_by"][0] == "drives/bea_al_al" and found["drives/bea_al_al"]["used_by"] == []
    bea, al = list(found["people/bea"]["built"]), list(found["people/al"]["built"])
    assert bea[:5] == ["ingest", "landmarks", "pose", "frontalize", "screen"] and {"shape", "texture"} <= set(bea)
    assert "texture" not in al  # al only drives
    drive = list(found["drives/bea_al_al"]["built"])
    assert drive[0] == "retarget" and drive[-1] == "composite" and "render3d" in drive
    assert all(not c["unfinished"] for c in found.values())
    capsys.readouterr()
    assert cli(["inspect", str(folder / "people.zarr")]) == 0
    shown = capsys.readouterr().out
    assert "used by: drives/bea_al_al" in shown and "built: ingest, landmarks (" in shown
    assert "aligned/rgb" not in shown  # the arrays only with --arrays
    assert cli(["inspect", "--arrays", str(folder / "people.zarr")]) == 0 and "aligned/rgb" in capsys.readouterr().out

    copy = tmp_path / "people.zarr"  # a run killed while it wrote the frame textures
    shutil.copytree(folder / "people.zarr", copy)
    zarr.open_array(copy / "drives/bea_al_al/texture/rgb", mode="r+").attrs.pop("provenance")
    assert summarize(str(copy))["collections"]["drives/bea_al_al"]["unfinished"] == ["texture/rgb"]


def test_a_drive_of_format_2_is_the_drive_of_format_1(people_run):
    """bea driven by al in the batch renders the same frames as bea driven by al alone."""
    folder, _, _, _ = people_run
    batch = Collection(open_store(str(folder / "people.zarr"), mode="r"), "drives/bea_al_al")
    alone = Collection(open_store(str(folder / "alone.zarr"), mode="r"), "drive")
    assert Cast.of(batch.root, batch.path) == Cast("people/bea", "people/al", "videos/al", "drives/bea_al_al")
    for name in ("mesh", "render/rgb", "composite/rgb"):
        assert np.array_equal(batch.array(name)[:], alone.array(name)[:], equal_nan=name == "mesh"), name


def test_people_are_built_two_at_a_time_on_a_cluster_and_the_store_is_the_same(batch, people_run):
    """``cluster.builds`` 2 (the default) on a local Dask cluster (conftest.py's batch's uninterrupted run,
    the same people and drive as people_run's): a second person's stages start while the first's are under
    way, and the store is the same, array for array, as the one-at-a-time run in this process (people_run,
    scheduler "sync")."""
    folder, workflow, timeline, _ = batch
    wf = load_workflow(workflow)
    assert wf.cluster.builds == 2 and wf.cluster.scheduler == "local"
    started = {event.split()[0]: t for event, t in timeline.items()
               if event.startswith("people/") and event.endswith(" ingest: started")}
    first_done = min(t for event, t in timeline.items() if event.startswith("people/") and event.endswith(": done"))
    assert sorted(started) == ["people/al", "people/bea", "people/cy"]
    assert sum(t < first_done for t in started.values()) >= 2, timeline  # two begun before either ended a step
    report = json.loads((folder / "reference" / "metrics.json").read_text())
    assert set(report["drives"]) == {"bea_al_al", "cy_al_al"}
    assert list(report["collections"]) == [plan.path for plan in wf.collections()]  # the workflow's order
    assert_same_store(folder / "reference.zarr", people_run[0] / "people.zarr")


def test_a_new_drive_builds_only_what_is_new(people_run):
    """Adding a drive (a range of the same video) to the workflow: no person, no finished drive is
    built, encoded or evaluated again; only the new range's frames and its drive are."""
    folder, drives, _, _ = people_run
    more = [*drives, {"puppet": "cy", "driver": "al", "video": {"video": "data/al.mp4", "stop": 6}}]
    report = _run(folder, _people_workflow(folder, more), "more.yaml")
    assert set(report["drives"]) == {"bea_al_al", "cy_al_al", "cy_al_al_0-6"}
    done = {(r["collection"], r["stage"]): r.get("n_done") for r in report["stages"]}
    for person in ("people/al", "people/bea", "people/cy"):
        assert done[(person, "landmarks")] == 0, person
    assert done[("drives/bea_al_al", "render3d")] == 0
    assert ("drives/bea_al_al", "videos") not in done  # its videos and evaluation are kept, not made again
    assert done[("videos/al_0-6", "ingest")] == 6 and done[("drives/cy_al_al_0-6", "render3d")] == 6


def test_version_2_names_people_and_says_what_is_wrong(tmp_path):
    data = {"version": 2, "name": "x", "store": "s.zarr", "output": "o",
            "people": {"bush": {"photos": "a"}, "obama": {"photos": "b"}},
            "puppet": {"photos": "c"},
            "drives": [{"puppet": ["bush", "powel"], "driver": "obmaa", "video": "v.mp4"}]}
    with pytest.raises(WorkflowError) as info:
        parse_workflow(data, base_dir=tmp_path)
    errors = dict(info.value.errors)
    assert "version 1" in errors["puppet"]
    assert 'no person "powel"' in errors["drives.0.puppet"]
    assert 'did you mean "obama"' in errors["drives.0.driver"].lower()
    with pytest.raises(WorkflowError) as info:
        parse_workflow({"version": 1, "name": "x", "store": "s", "output": "o", "people": {"a": {"photos": "p"}}},
                       base_dir=tmp_path)
    assert {"puppet", "people"} <= set(dict(info.value.errors))


def test_a_drive_that_fails_fails_alone(people_run):
    """A driver with too few photos for a 3D shape, and a video that is not one: their drives fail
    and say why, the run ends with an error naming them, and the other drives are done, their
    outputs written. (Runs last: it adds to the module's store.)"""
    from persona.dag.errors import RunError

    folder, drives, _, _ = people_run
    (folder / "data" / "broken.mp4").write_bytes(b"not a video at all")
    data = _people_workflow(folder, [*drives, {"puppet": "bea", "driver": "few", "video": "data/al.mp4"},
                                     {"puppet": "cy", "driver": "al", "video": "data/broken.mp4"}])
    data["people"]["few"] = {"photos": "data/al/photo000[0-3].png"}
    with pytest.raises(RunError, match=r"2 of 4 drives failed: bea_few_al: .*no 3D shape.*; "
                                       r"cy_al_broken: videos/broken: .*broken\.mp4"):
        _run(folder, data, "few.yaml")
    assert (folder / "people" / "cy_al_al" / "composite.mp4").is_file()
    page = (folder / "people" / "index.html").read_text()
    assert page.count("failed: ") == 2 and 'href="cy_al_al/report.html"' in page


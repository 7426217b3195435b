"""The Python API (docs/api.md): persona.run and persona.open, and the command line going through them."""

import pytest
import yaml

import persona
from persona.dag.cli import main as cli
from persona.dag.workflow import WorkflowError
from persona.stores.errors import InputError, PersonaError
from persona.stores.layout import StoreError


def test_persona_is_the_api_and_loads_nothing_heavy_until_used():
    """``import persona`` is the API's package (dag/_persona, mapped in pyproject.toml); its layers
    import as before."""
    import persona.stores.layout

    assert {"run", "open", "workflow"} <= set(dir(persona))
    assert persona.run.__module__ == "persona.dag.api"
    with pytest.raises(AttributeError, match="Persona's API"):
        persona.nothing_here


def test_a_workflow_dict_with_errors_raises_what_the_command_prints(tmp_path, capsys):
    bad = {"version": 1, "name": "x", "store": "s.zarr", "output": "out", "puppet": {"photos": "p"},
           "stages": {"landmarks": {"backend": "dlibb"}}}
    with pytest.raises(WorkflowError) as raised:
        persona.run(bad)
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(bad))
    assert cli(["run", str(tmp_path / "bad.yaml")]) == 2
    printed = capsys.readouterr().err
    assert "dlibb" in str(raised.value) and str(raised.value).split("\n", 1)[1] in printed


def test_a_missing_photo_folder_stops_the_api_before_anything_is_made(tmp_path):
    with pytest.raises(InputError, match="nowhere"):
        persona.run({"version": 1, "name": "x", "store": str(tmp_path / "s.zarr"), "output": str(tmp_path / "out"),
                     "puppet": {"photos": str(tmp_path / "nowhere")}})
    assert not (tmp_path / "s.zarr").exists() and not (tmp_path / "out").exists()


def test_the_command_runs_through_the_api(tmp_path, monkeypatch):
    """`persona run` calls persona.run with the validated workflow, --set applied (the run itself is the
    runner's, tested everywhere else)."""
    from persona.dag import api, runner

    seen = []

    def fake(wf, **kwargs):
        seen.append((wf, kwargs))
        return {"collections": {}, "report": "report.html"}

    monkeypatch.setattr(runner, "run_workflow", fake)
    (tmp_path / "p").mkdir()
    (tmp_path / "w.yaml").write_text(yaml.safe_dump({"version": 1, "name": "x", "store": "s.zarr", "output": "out",
                                                     "puppet": {"photos": "p"}}))
    called = []
    monkeypatch.setattr(api, "run", lambda *a, **k: called.append(a) or fake(*a, **k))
    assert cli(["run", str(tmp_path / "w.yaml"), "--set", "name=y", "--scheduler", "sync", "--quiet"]) == 0
    assert called and seen[0][0].name == "y" and seen[0][1]["scheduler"] == "sync"
    monkeypatch.undo()
    monkeypatch.setattr(runner, "run_workflow", fake)
    monkeypatch.chdir(tmp_path)  # a dict's relative paths resolve against the current folder
    persona.run({"version": 1, "name": "z", "store": "s.zarr", "output": "out", "puppet": {"photos": "p"}},
                overrides=["name=w"], progress=False)
    assert seen[-1][0].name == "w" and seen[-1][0].store == str(tmp_path / "s.zarr")


def test_open_gives_every_person_video_and_drive_of_a_batch(batch):
    """The batch's store and output opened from its store (and output) and from its workflow: the
    people, the video and the drives by name, with their counts, rejections, datasets, meshes and
    figures as metrics.json has them."""
    folder, workflow, _, _ = batch
    run = persona.open(folder / "reference.zarr", output=folder / "reference")
    assert sorted(run.people) == ["al", "bea", "cy"] and len(run.videos) == 1 and len(run.drives) == 2
    bea = run.people["bea"]
    assert bea.n == 8 and 0 < bea.accepted <= 8 and sum(map(len, bea.rejections.values())) == 8 - bea.accepted
    aligned = bea.dataset("aligned")
    assert aligned["rgb"].dims == ("photo", "y", "x", "channel") and aligned.sizes["fiducial"] == 49
    mesh = bea.mesh()
    assert mesh.vertices.shape[1] == 3 and mesh.texture.dtype.name == "uint8"
    assert 0.05 < float(mesh.vertices[:, 0].max() - mesh.vertices[:, 0].min()) < 0.3  # a face's width, metres
    assert set(bea.files) >= {"mesh_obj", "mean_face"}
    video = next(iter(run.videos.values()))
    assert video.n == 8 and video.fps == pytest.approx(25)
    drive = run.drives["bea_al_al"]
    assert (drive.puppet, drive.driver, drive.video) == ("bea", "al", video.name)
    assert drive.dataset()["mesh"].shape[0] == 8 and set(drive.videos) == {"composite", "puppet", "side_by_side"}
    assert drive.figures["amplitude"]["mouth_open"]["gain"] > 0 and drive.files["report"].endswith("report.html")
    with pytest.raises(StoreError, match="no group"):
        drive.dataset("nothing")
    as_run = {**yaml.safe_load(workflow.read_text()), "store": str(folder / "reference.zarr"),
              "output": str(folder / "reference")}  # the workflow as the reference run ran it
    by_workflow = persona.open(as_run)
    assert by_workflow.drives["cy_al_al"].output == str(folder / "reference" / "cy_al_al")
    assert by_workflow.drives["cy_al_al"].figures == run.drives["cy_al_al"].figures
    alone = persona.open(folder / "reference.zarr")
    with pytest.raises(PersonaError, match="output folder"):
        alone.drives["bea_al_al"].figures


def test_open_names_a_missing_store(tmp_path):
    with pytest.raises(StoreError, match="persona run"):
        persona.open(tmp_path / "none.zarr")

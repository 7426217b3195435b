"""Persona owns the output folders it writes: a folder of someone else's files stops a run before any
work, unless --force; a new, empty or Persona's own folder is written."""

import json

import pytest

from persona.stores import output

from pipeline import write_workflow


def test_a_folder_of_someone_elses_files_is_not_written(tmp_path):
    folder = tmp_path / "out"
    folder.mkdir()
    (folder / "report.html").write_text("<p>my own report</p>")
    (folder / "metrics.json").write_text(json.dumps({"mine": True}))
    with pytest.raises(output.OutputTaken, match=r"holds files Persona did not write \(metrics.json, report.html\)"):
        output.claim(str(folder), "run.zarr")
    assert not (folder / output.MARK).exists()
    output.claim(str(folder), "run.zarr", force=True)  # --force: the user says so
    assert (folder / output.MARK).exists()
    assert (folder / "report.html").read_text() == "<p>my own report</p>"  # claiming writes nothing else


def test_a_new_empty_or_persona_folder_is_claimed(tmp_path):
    output.claim(str(tmp_path / "new"), "run.zarr")
    assert (tmp_path / "new" / output.MARK).exists()
    output.claim(str(tmp_path / "new"), "run.zarr")  # its own again
    (tmp_path / "empty").mkdir()
    output.claim(str(tmp_path / "empty"), "run.zarr")
    earlier = tmp_path / "earlier"  # a run of an earlier version wrote it: its metrics name this store
    earlier.mkdir()
    (earlier / "metrics.json").write_text(json.dumps({"workflow": "w", "store": "run.zarr"}))
    output.claim(str(earlier), "run.zarr")
    with pytest.raises(output.OutputTaken):  # another store's
        other = tmp_path / "other"
        other.mkdir()
        (other / "metrics.json").write_text(json.dumps({"workflow": "w", "store": "elsewhere.zarr"}))
        output.claim(str(other), "run.zarr")


def test_persona_run_into_someone_elses_folder_stops_before_any_work(tmp_path, capsys):
    from persona.dag.cli import main

    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "a.png").write_bytes(b"")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "report.html").write_text("<p>my own report</p>")
    assert main(["run", str(write_workflow(tmp_path, "photos")), "--scheduler", "sync", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--force" in err and "resume with" not in err
    assert not (tmp_path / "run.zarr" / "zarr.json").exists()  # no work started
    assert (tmp_path / "out" / "report.html").read_text() == "<p>my own report</p>"

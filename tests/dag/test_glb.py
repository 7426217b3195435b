"""The .glb exports of a run (docs/api.md): each drive's puppet.glb beside its other outputs and `persona glb`,
checked by the Khronos validator and read back by trimesh, on the shared batch's store."""

import numpy as np
import pytest

from gltf_check import accessor, read_glb, trimesh_scene, validate
from persona.dag.cli import main as cli
from persona.dag.export import drive_frames, person_mesh
from persona.stores.layout import Cast, Collection, open_store


def test_every_drive_writes_a_valid_animated_glb_beside_its_videos(batch):
    """puppet.glb: no error from the validator; one morph target and one key per frame of the video at its
    rate; trimesh reads B's rest mesh with the vertices of the drive's grid and bounds in metres (a face)."""
    folder, _, _, _ = batch
    root = open_store(str(folder / "reference.zarr"), mode="r")
    files = {name: folder / "reference" / name / "puppet.glb" for name in ("bea_al_al", "cy_al_al")}
    reports = validate(*files.values())
    for name, path in files.items():
        report = reports[str(path)]
        assert report["numErrors"] == 0 and report["numWarnings"] == 0, (name, report["messages"])
        rest, frames, _, _, fps = drive_frames(root, Cast.of(root, f"drives/{name}"))
        doc, blob = read_glb(path)
        times = accessor(doc, blob, doc["animations"][0]["samplers"][0]["input"])[:, 0]
        assert len(times) == len(doc["meshes"][0]["primitives"][0]["targets"]) == len(frames) == 8
        assert times[1] == pytest.approx(1 / fps) and fps == pytest.approx(25)
        scene = trimesh_scene(path)
        (mesh,) = scene.geometry.values()
        assert len(mesh.vertices) == len(rest.vertices) == report["info"]["totalVertexCount"]
        np.testing.assert_allclose(scene.bounds, [rest.vertices.min(axis=0), rest.vertices.max(axis=0)], atol=1e-5)
        width, height = np.ptp(scene.bounds, axis=0)[:2]
        assert 0.08 < width < 0.25 and 0.08 < height < 0.3, scene.bounds  # metres: a face


def test_persona_glb_writes_each_person_and_drive(batch, tmp_path, capsys):
    folder, _, _, _ = batch
    store = str(folder / "reference.zarr")
    assert cli(["glb", store, "--out", str(tmp_path), "--only", "bea", "--only", "cy_al_al"]) == 0
    printed = capsys.readouterr().out
    assert "8 frames at 25 fps" in printed
    person, drive = tmp_path / "people_bea_mesh.glb", tmp_path / "cy_al_al.glb"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([person.name, drive.name])
    reports = validate(person, drive)
    assert all(r["numErrors"] == 0 and r["numWarnings"] == 0 for r in reports.values()), reports
    face = person_mesh(Collection(open_store(store, mode="r"), "people/bea"))
    scene = trimesh_scene(person)
    (mesh,) = scene.geometry.values()
    assert len(mesh.vertices) == len(face.vertices)
    np.testing.assert_allclose(scene.bounds, [face.vertices.min(axis=0), face.vertices.max(axis=0)], atol=1e-6)
    assert cli(["glb", store, "--only", "nobody"]) == 2
    assert "nobody: not a person or drive" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli(["glb", store, "--step", "0"])
    assert "--step: expected a whole number of 1 or more" in capsys.readouterr().err

"""stores/gltf.py: .glb files the Khronos validator passes, read back by trimesh and by hand."""

import numpy as np
import pytest

from gltf_check import accessor, read_glb, trimesh_scene, validate
from persona.stores.gltf import write_animated_glb, write_mesh_glb


def _grid(n=12):
    """A small textured sheet: vertices (n*n, 3) metres, CCW triangles seen from +z, uvs, a texture."""
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32)
    vertices = np.stack([xx / n * 0.1 - 0.05, 0.05 - yy / n * 0.1, 0.01 * np.sin(xx)], axis=-1).reshape(-1, 3)
    a = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    triangles = np.concatenate([np.stack([a, a + n, a + 1], 1), np.stack([a + 1, a + n, a + n + 1], 1)])
    uvs = np.stack([(xx + 0.5) / n, (yy + 0.5) / n], axis=-1).reshape(-1, 2)
    texture = (np.random.default_rng(0).random((16, 16, 3)) * 255).astype(np.uint8)
    return vertices, triangles, uvs, texture


def test_a_textured_mesh_passes_the_validator_and_reads_back(tmp_path):
    vertices, triangles, uvs, texture = _grid()
    path = tmp_path / "face.glb"
    write_mesh_glb(path, vertices=vertices, triangles=triangles, uvs=uvs, texture=texture,
                   normals=np.tile([0, 0, 1.0], (len(vertices), 1)), extras={"units": "metres"})
    report = validate(path)[str(path)]
    assert report["numErrors"] == 0 and report["numWarnings"] == 0, report["messages"]
    scene = trimesh_scene(path)
    (mesh,) = scene.geometry.values()
    assert len(mesh.vertices) == len(vertices) and len(mesh.faces) == len(triangles)
    np.testing.assert_allclose(scene.bounds, [vertices.min(axis=0), vertices.max(axis=0)], atol=1e-6)


def test_an_animated_mesh_passes_the_validator_and_every_frame_reads_back(tmp_path):
    """30 frames at 25 fps: the validator sees one animation and no error; trimesh reads the rest shape in
    metres; each frame's vertices, decoded from its morph target, are the ones written to within a quantum."""
    vertices, triangles, uvs, texture = _grid()
    count = 30
    t = np.arange(count)[:, None, None]
    frames = vertices[None] + np.float32(0.004) * np.sin(t / 5 + vertices[None, :, :1] * 40) * [0, 1, 1]
    angles = np.linspace(0, 0.5, count)
    rotations = np.stack([np.zeros(count), np.sin(angles / 2), np.zeros(count), np.cos(angles / 2)], axis=1)
    moves = np.stack([np.linspace(-0.01, 0.01, count), np.zeros(count), np.zeros(count)], axis=1)
    path = tmp_path / "drive.glb"
    written = write_animated_glb(path, rest=vertices, frames=frames, triangles=triangles, uvs=uvs, texture=texture,
                                 fps=25.0, rotations=rotations, translations=moves)
    assert written["bytes"] == path.stat().st_size
    report = validate(path)[str(path)]
    assert report["numErrors"] == 0 and report["numWarnings"] == 0, report["messages"]
    assert report["info"]["animationCount"] == 1 and report["info"]["totalVertexCount"] == len(vertices)

    scene = trimesh_scene(path)  # the rest shape, its 16-bit positions scaled to metres by its node
    (mesh,) = scene.geometry.values()
    assert len(mesh.vertices) == len(vertices)
    np.testing.assert_allclose(scene.bounds, [vertices.min(axis=0), vertices.max(axis=0)], atol=2 * written["quantum_m"])

    doc, blob = read_glb(path)
    animation = doc["animations"][0]
    times = accessor(doc, blob, animation["samplers"][0]["input"])[:, 0]
    np.testing.assert_allclose(times, np.arange(count) / 25.0)
    primitive = doc["meshes"][0]["primitives"][0]
    assert len(primitive["targets"]) == count
    quantum = doc["nodes"][1]["scale"][0]
    rest = accessor(doc, blob, primitive["attributes"]["POSITION"]).astype(float)
    weights = accessor(doc, blob, animation["samplers"][2]["output"]).reshape(count, count)
    np.testing.assert_array_equal(weights, np.eye(count))  # at frame t's time, frame t's target alone
    for k in (0, 13, count - 1):
        decoded = (rest + accessor(doc, blob, primitive["targets"][k]["POSITION"])) * quantum
        np.testing.assert_allclose(decoded, frames[k], atol=1.5 * quantum)
    np.testing.assert_allclose(accessor(doc, blob, animation["samplers"][0]["output"]), rotations, atol=1e-7)


def test_bad_input_is_named(tmp_path):
    vertices, triangles, uvs, texture = _grid()
    with pytest.raises(ValueError, match="frames must be"):
        write_animated_glb(tmp_path / "x.glb", rest=vertices, frames=vertices, triangles=triangles, uvs=uvs,
                           texture=texture, fps=25, rotations=np.zeros((1, 4)), translations=np.zeros((1, 3)))
    with pytest.raises(ValueError, match="texture"):
        write_mesh_glb(tmp_path / "x.glb", vertices=vertices, triangles=triangles, uvs=uvs, texture=texture[..., 0])
    assert not (tmp_path / "x.glb").exists()

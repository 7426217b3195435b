"""A person's average face and a drive as glTF 2.0 binary files (.glb), from the store.

The maths (the mesh in metres, the head's pose as a quaternion) is :mod:`persona.plugins.animation`'s, the
format :mod:`persona.stores.gltf`'s; this module reads the arrays and joins the two.

- a person: the average face of ``shape/depth`` over ``shape/mask``, with ``shape/texture`` (the OBJ's
  texture), every grid point a vertex, with normals: ``persona glb`` or ``Person.glb``;
- a drive: B's mesh of every frame (the drive's ``mesh``) as one morph target each, at the video's rate,
  on a grid of every ``step``-th point of B's face (2 by default: a quarter of the vertices, which keeps
  a 300-frame drive near 17 MB; docs/api.md gives the sizes), textured with B's neutral texture
  (``texture/neutral``: glTF has no texture that changes per frame), the head's pose per frame as its
  node's rotation and translation. Written beside each drive's other outputs as ``puppet.glb``.
"""

from __future__ import annotations

import numpy as np

from persona.plugins.animation import FaceMesh, face_mesh, head_motion, to_file_frame
from persona.plugins.face.meshing import METRIC_UNITS
from persona.stores.layout import Cast, Collection, StoreError

__all__ = ["drive_frames", "person_mesh", "write_drive_glb", "write_person_glb"]

#: the files' note on their units and axes (the asset's extras)
EXTRAS = {"units": METRIC_UNITS}


def person_mesh(coll: Collection, *, step: int = 1, texture: str = "shape/texture") -> FaceMesh:
    """The average face of the person ``coll`` in metres (:func:`persona.plugins.animation.face_mesh`)."""
    if not coll.has("shape/depth"):
        raise StoreError(f"{coll.path} has no 3D shape in the store (too few photos, or the run has not made it "
                         f"yet): `persona inspect` says why; run the workflow first")
    image = coll.array(texture)[...] if coll.has(texture) else coll.array("shape/texture")[...]
    return face_mesh(coll.array("shape/depth")[...], coll.array("shape/mask")[...],
                     coll.array("aligned/mean_fiducials")[...], image, step=step)


def write_person_glb(coll: Collection, path) -> str:
    """The average face of the person ``coll`` with its texture and normals as a .glb at ``path``."""
    from persona.stores.gltf import write_mesh_glb

    mesh = person_mesh(coll)
    write_mesh_glb(path, vertices=mesh.vertices, triangles=mesh.triangles, uvs=mesh.uvs, texture=mesh.texture,
                   normals=mesh.normals, name=coll.path.replace("/", "_"), extras=EXTRAS)
    return path


def drive_frames(root, cast: Cast, *, step: int = 2) -> tuple[FaceMesh, np.ndarray, np.ndarray, np.ndarray, float]:
    """What a drive's .glb and the report's 3D view show: B's rest mesh (with B's neutral texture), the
    vertices of every frame (T, n, 3) metres, the head's quaternions (T, 4) and translations (T, 3), and
    the frames' rate. A vertex a frame does not place (off that frame's mesh) stays where the rest mesh has it."""
    puppet, drive = Collection(root, cast.puppet), Collection(root, cast.drive)
    if not drive.has("mesh"):
        raise StoreError(f"{cast.drive} has no per-frame meshes in the store: it is a 2D drive (render backend "
                         "tps2d) or not made yet; run the workflow with the render backend mesh3d")
    rest = person_mesh(puppet, step=step, texture="texture/neutral")
    meshes = drive.array("mesh")
    frames = np.empty((drive.n, len(rest.vertices), 3), np.float32)
    for start, stop in drive.shard_ranges():  # a shard at a time: memory bounded by a shard
        points = meshes[start:stop][:, rest.rows, rest.cols]  # (frames, n, 3) canonical px
        placed = to_file_frame(points, rest.origin, rest.scale)
        frames[start:stop] = np.where(np.isfinite(placed).all(axis=-1, keepdims=True), placed, rest.vertices)
    rotations, translations = head_motion(drive.array("pose")[:], rest.origin, rest.scale)
    return rest, frames, rotations, translations, float(drive.attrs.get("fps", 25.0))


def write_drive_glb(root, cast: Cast, path, *, step: int = 2) -> dict:
    """The drive of ``cast`` as an animated .glb at ``path`` (module docstring); returns its frames, vertices,
    quantum (metres) and size (bytes)."""
    from persona.stores.gltf import write_animated_glb

    rest, frames, rotations, translations, fps = drive_frames(root, cast, step=step)
    written = write_animated_glb(path, rest=rest.vertices, frames=frames, triangles=rest.triangles, uvs=rest.uvs,
                                 texture=rest.texture, fps=fps, rotations=rotations, translations=translations,
                                 name=cast.puppet.replace("/", "_"), extras=EXTRAS)
    return {"path": str(path), "frames": len(frames), "vertices": len(rest.vertices), "fps": fps, **written}

"""A face and its drive as 3D data for files people open (glTF, and the report's 3D view): pure NumPy.

Persona's faces live on the canonical grid (ALGORITHMS §0): canonical px, x right, y down, Z away from
the camera, OpenCV's frame. Files are in metres with x right, y up, z towards the viewer and the origin
between the eyes, 63 mm between the eye centres (:func:`persona.plugins.face.meshing.metric_frame`, as
the OBJ export): a point ``X`` goes to ``F (X - origin) * scale`` with ``F = diag(1, -1, -1)``, a half
turn about x (a proper rotation, so triangles keep their winding).

A drive's head pose maps canonical points to the driver's camera, ``X -> R X + t`` (R from the Rodrigues
vector ``pose[:3]``, t = ``pose[3:6]``, canonical px). In the file's frame the face's vertices are
``v = F (X - origin) s``, so the camera sees ``F (R X + t) s = (F R F) v + s F (R origin + t)``: the head
node's rotation is ``F R F`` and its translation ``s F (R origin + t)``, less its mean over the drive so
that the head moves about the scene's origin rather than a camera's distance away.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .face.meshing import grid_mesh, metric_frame

__all__ = ["FLIP", "FaceMesh", "face_mesh", "head_motion", "to_file_frame", "vertex_normals"]

#: canonical (y down, Z away) to the files' frame (y up, z towards the viewer): a half turn about x
FLIP = np.diag([1.0, -1.0, -1.0])


@dataclass
class FaceMesh:
    """A face as a triangle mesh in the files' frame (module docstring).

    vertices : (n, 3) float32, metres
    triangles : (m, 3) int64, indices into ``vertices``; counter-clockwise seen from the front
    uvs : (n, 2) float32, texture coordinates in glTF's convention: (0, 0) the texture's top-left corner
    texture : (H, W, 3) uint8 RGB on the canonical grid, or None
    normals : (n, 3) float32 unit vertex normals (facing the viewer, +z, for a frontal face)
    rows, cols : (n,) int, each vertex's pixel on the canonical grid (to read per-frame positions there)
    origin, scale : the metric frame: vertex = FLIP @ (X - origin) * scale
    """

    vertices: np.ndarray
    triangles: np.ndarray
    uvs: np.ndarray
    texture: np.ndarray | None
    normals: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    origin: np.ndarray
    scale: float


def to_file_frame(points: np.ndarray, origin: np.ndarray, scale: float) -> np.ndarray:
    """Canonical points (..., 3) in the files' frame: ``FLIP (X - origin) * scale``, float32 metres."""
    return (((np.asarray(points, np.float64) - origin) * scale) @ FLIP).astype(np.float32)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit vertex normals (n, 3): the area-weighted sum of the normals of the triangles at each vertex
    (counter-clockwise triangles: the normal points at the side they are seen counter-clockwise from)."""
    v = np.asarray(vertices, np.float64)
    a, b, c = (v[triangles[:, k]] for k in range(3))
    face = np.cross(b - a, c - a)  # length: twice the triangle's area
    out = np.zeros_like(v)
    for k in range(3):
        np.add.at(out, triangles[:, k], face)
    length = np.linalg.norm(out, axis=1, keepdims=True)
    return (out / np.where(length > 0, length, 1.0)).astype(np.float32)


def face_mesh(depth: np.ndarray, mask: np.ndarray, fiducials: np.ndarray, texture: np.ndarray | None = None,
              *, step: int = 1) -> FaceMesh:
    """The average face of a depth map (H, W) over ``mask`` as a :class:`FaceMesh` in metres, its metric
    frame from the mean ``fiducials`` (49, 2); ``step`` keeps every step-th grid point across and down
    (2: a quarter of the vertices, for a drive's per-frame positions)."""
    if step < 1:
        raise ValueError(f"step must be 1 or more, got {step}")
    z = np.asarray(depth, np.float64)
    m = np.asarray(mask, bool) & np.isfinite(z)
    h, w = z.shape
    origin, scale = metric_frame(fiducials, z, m)
    # the grid points kept; a quad of them is a quad of the mesh. grid_triangles winds the triangles to face
    # the camera (normal -Z) in canonical px; FLIP turns that to +z, seen from the viewer at +z:
    # counter-clockwise, glTF's front faces
    triangles, r, c = grid_mesh(m[::step, ::step])
    rows, cols = r * step, c * step
    canonical = np.stack([cols, rows, z[rows, cols]], axis=1).astype(np.float64)
    vertices = to_file_frame(canonical, origin, scale)
    uvs = np.stack([(cols + 0.5) / w, (rows + 0.5) / h], axis=1).astype(np.float32)
    return FaceMesh(vertices, triangles, uvs, None if texture is None else np.asarray(texture, np.uint8),
                    vertex_normals(vertices, triangles), rows, cols, origin, scale)


def head_motion(poses: np.ndarray, origin: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """The head node's rotation and translation per frame (module docstring) from a drive's poses (T, >=6):
    quaternions (T, 4) as glTF orders them (x, y, z, w), each on the same side as the one before so that
    interpolating between frames takes the short way, and translations (T, 3) in metres about their mean.
    A frame without a pose (NaN) takes the nearest frame's; a drive without any, the face at rest."""
    p = np.asarray(poses, np.float64)[:, :6]
    t_count = len(p)
    ok = np.isfinite(p).all(axis=1)
    if not ok.any():
        return np.tile([0.0, 0.0, 0.0, 1.0], (t_count, 1)).astype(np.float32), np.zeros((t_count, 3), np.float32)
    good = np.flatnonzero(ok)
    nearest = good[np.abs(np.arange(t_count)[:, None] - good[None, :]).argmin(axis=1)]
    p = p[nearest]
    rotation = Rotation.from_rotvec(p[:, :3]).as_matrix()  # (T, 3, 3), the Rodrigues vector as OpenCV reads it
    turned = FLIP @ rotation @ FLIP
    quaternions = Rotation.from_matrix(turned).as_quat()  # (x, y, z, w)
    for k in range(1, t_count):
        if np.dot(quaternions[k], quaternions[k - 1]) < 0:
            quaternions[k] = -quaternions[k]
    moved = scale * ((rotation @ np.asarray(origin, np.float64)) + p[:, 3:6]) @ FLIP
    return quaternions.astype(np.float32), (moved - moved.mean(axis=0)).astype(np.float32)

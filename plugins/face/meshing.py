"""Depth maps as triangle meshes, and shaded previews of them (open3d; no files).

Mesh conventions (ALGORITHMS §0): a depth map ``Z (H, W)`` on the canonical grid becomes the
vertices ``(x, y, Z)`` in canonical px, x right, y down, Z away from the camera (a right-handed
frame, OpenCV's). Two triangles per grid quad whose four corners are in the mask
(:func:`persona.plugins.face.mesh.grid_triangles`), wound so that their normals point at the
camera (n_z < 0), like the depth map's normals ``(Z_x, Z_y, -1)/|.|``.

Texture coordinates map a texture image of the grid's size exactly, pixel centre on pixel
centre: the vertex of pixel (row y, col x) gets ``u = (x + 0.5)/W``, ``v = 1 - (y + 0.5)/H``.
This is the OBJ / OpenGL convention, (0, 0) at the *bottom*-left corner of the image, which
open3d's ``triangle_uvs`` keep as they are when reading and writing OBJ files (checked: open3d
0.20 round-trips ``vt`` values unchanged).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from .mesh import grid_triangles, raycasting_scene

__all__ = ["MEAN_IOD_M", "METRIC_UNITS", "depth_to_mesh", "grid_mesh", "metric_frame", "pixel_uvs",
           "shaded_previews"]

#: the mean adult distance between the eye centres, metres (about 63 mm): the scale of the meshes
#: Persona writes, which otherwise have none (a face seen by one camera has no size)
MEAN_IOD_M = 0.063
#: how the files say so (OBJ header), with the axes of ``write_mesh(..., y_up=True)``
METRIC_UNITS = "metres, eye centres 63 mm apart; x right, y up, z towards the viewer; origin between the eyes"


def metric_frame(fiducials: np.ndarray, depth: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, float]:
    """Where the meshes of a face written to files have their origin, and their scale: the origin
    (x, y, Z) canonical px is the midpoint of the eye centres of the 49 ``fiducials`` (eyes 19-30), at
    the median depth of the face ``mask``; the scale (metres per canonical px) puts those eye centres
    :data:`MEAN_IOD_M` apart. Every frame of one face shares them, so a sequence does not jump."""
    f = np.asarray(fiducials, np.float64)
    left, right = np.nanmean(f[19:25], axis=0), np.nanmean(f[25:31], axis=0)
    middle = (left + right) / 2
    origin = np.array([middle[0], middle[1], float(np.nanmedian(np.asarray(depth)[np.asarray(mask, bool)]))])
    return origin, MEAN_IOD_M / float(np.linalg.norm(right - left))


def pixel_uvs(rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(k, 2) texture coordinates (u, v) of pixel centres (row, col) on an (H, W) image, OBJ convention
    (origin at the bottom-left corner): ``u = (col + 0.5)/W``, ``v = 1 - (row + 0.5)/H``."""
    h, w = shape
    return np.stack([(np.asarray(cols) + 0.5) / w, 1.0 - (np.asarray(rows) + 0.5) / h], axis=-1)


def grid_mesh(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mesh of a grid's ``mask`` (H, W) bool: its triangles (:func:`grid_triangles`, two per quad of
    four mask pixels) as (m, 3) int64 indices into the pixels they use, and those pixels' rows and
    columns (k,), in row-major order."""
    tris = grid_triangles(mask).astype(np.int64)
    used = np.unique(tris)
    remap = np.full(mask.size, -1, np.int64)
    remap[used] = np.arange(used.size)
    rows, cols = np.divmod(used, mask.shape[1])
    return remap[tris], rows, cols


def depth_to_mesh(depth: np.ndarray, mask: np.ndarray, texture: np.ndarray | None = None) -> o3d.geometry.TriangleMesh:
    """A triangle mesh of a depth map.

    depth : ndarray, shape (H, W) — Z in canonical px (NaN allowed off the mask)
    mask : ndarray, shape (H, W), bool — pixels to mesh; pixels with non-finite depth are dropped
    texture : ndarray, shape (H, W, 3), uint8, or None — RGB image on the same grid

    Returns a ``TriangleMesh`` whose vertices are the mask pixels used by at least one triangle,
    in row-major order, at ``(x, y, Z)``; vertex normals computed (n_z < 0 facing the camera);
    with a texture: vertex colours (the texture at each vertex's pixel, in [0, 1]) and
    per-corner ``triangle_uvs`` (module docstring).
    """
    z = np.asarray(depth, dtype=np.float64)
    m = np.asarray(mask)
    if z.ndim != 2:
        raise ValueError(f"depth must have shape (H, W), got {z.shape}")
    if m.shape != z.shape:
        raise ValueError(f"mask must have shape {z.shape} like the depth, got {m.shape}")
    if m.dtype != bool:
        raise TypeError(f"mask must be bool, got {m.dtype}")
    if texture is not None:
        texture = np.asarray(texture)
        if texture.dtype != np.uint8 or texture.shape != z.shape + (3,):
            raise ValueError(f"texture must be uint8 of shape {z.shape + (3,)}, got {texture.dtype} {texture.shape}")
    triangles, rows, cols = grid_mesh(m & np.isfinite(z))
    verts = np.stack([cols.astype(np.float64), rows.astype(np.float64), z[rows, cols]], axis=1)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts),
                                     o3d.utility.Vector3iVector(triangles.astype(np.int32)))
    mesh.compute_vertex_normals()
    if texture is not None:
        mesh.vertex_colors = o3d.utility.Vector3dVector(texture[rows, cols].astype(np.float64) / 255.0)
        corners = triangles.ravel()
        mesh.triangle_uvs = o3d.utility.Vector2dVector(pixel_uvs(rows[corners], cols[corners], z.shape))
        mesh.triangle_material_ids = o3d.utility.IntVector(np.zeros(len(triangles), np.int32))
    return mesh


def _yaw(deg: float) -> np.ndarray:
    a = np.radians(deg)
    # about the vertical (y) axis; a positive yaw shows more of the face's left (image right) side
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])


def shaded_previews(mesh_or_depth, mask: np.ndarray | None = None, *, angles=(-40.0, 0.0, 40.0),
                    size: tuple[int, int] = (320, 320), light=(-0.35, -0.45, -1.0), ambient: float = 0.15,
                    fill: float = 0.9) -> list[np.ndarray]:
    """Lambertian grey renders of a face mesh from several yaw angles, for people to judge the shape.

    mesh_or_depth : ``open3d.geometry.TriangleMesh`` in the frame of :func:`depth_to_mesh`, or a
        depth map (H, W) with ``mask``
    angles : yaw angles in degrees (rotation about the vertical axis through the mesh centre)
    size : (height, width) of each preview
    light : direction towards the light in the view frame (x right, y down, z away from the viewer);
        the default is up-left on the viewer's side
    ambient : shade of a surface facing away from the light (0..1)
    fill : fraction of the image the face spans (the same scale for every angle)

    Orthographic ray casting (``open3d.t.geometry.RaycastingScene``) along +z, smooth shading with
    barycentrically interpolated vertex normals, white background. Returns one (h, w, 3) uint8 per angle.
    """
    if isinstance(mesh_or_depth, o3d.geometry.TriangleMesh):
        mesh = mesh_or_depth
    else:
        if mask is None:
            raise ValueError("shaded_previews of a depth map needs its mask")
        mesh = depth_to_mesh(mesh_or_depth, mask)
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    tris = np.asarray(mesh.triangles, dtype=np.int64)
    h, w = int(size[0]), int(size[1])
    if len(tris) == 0:
        return [np.full((h, w, 3), 255, np.uint8) for _ in angles]
    used = np.unique(tris)
    centre = 0.5 * (verts[used].min(axis=0) + verts[used].max(axis=0))
    if not mesh.has_vertex_normals():
        mesh = o3d.geometry.TriangleMesh(mesh)
        mesh.compute_vertex_normals()
    vnormals = np.asarray(mesh.vertex_normals, dtype=np.float64)
    views = [(verts - centre) @ _yaw(a).T for a in angles]
    extent = max(max(np.ptp(v[used, 0]) / w, np.ptp(v[used, 1]) / h) for v in views)  # mesh units per px
    scale = fill / max(extent, 1e-12)  # image px per mesh unit
    ldir = np.asarray(light, dtype=np.float64)
    ldir = ldir / np.linalg.norm(ldir)
    jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    out = []
    for a, v in zip(angles, views):
        scene = raycasting_scene(v, tris.astype(np.uint32))
        zmin = v[used, 2].min() - 10.0
        origins = np.stack([(jj.ravel() - (w - 1) / 2) / scale, (ii.ravel() - (h - 1) / 2) / scale,
                            np.full(h * w, zmin)], axis=1)
        dirs = np.tile([0.0, 0.0, 1.0], (h * w, 1))
        rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
        hits = scene.cast_rays(o3d.core.Tensor(rays))
        t = hits["t_hit"].numpy()
        hit = np.isfinite(t)
        img = np.full(h * w, 1.0)
        if hit.any():
            prim = hits["primitive_ids"].numpy()[hit].astype(np.int64)
            uv = hits["primitive_uvs"].numpy()[hit].astype(np.float64)
            corner = tris[prim]
            nrm = (vnormals[corner[:, 0]] * (1 - uv[:, :1] - uv[:, 1:]) + vnormals[corner[:, 1]] * uv[:, :1]
                   + vnormals[corner[:, 2]] * uv[:, 1:]) @ _yaw(a).T
            nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
            nrm[nrm[:, 2] > 0] *= -1  # two-sided: always the side facing the viewer
            img[hit] = 0.9 * (ambient + (1 - ambient) * np.clip(nrm @ ldir, 0.0, 1.0))  # never as white as the background
        out.append(np.repeat(np.round(img.reshape(h, w) * 255).astype(np.uint8)[..., None], 3, axis=2))
    return out

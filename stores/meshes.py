"""Mesh files people open (MeshLab, Blender, open3d): PLY and textured OBJ, plus a pymeshlab cleanup.

:func:`write_mesh` writes ``name.ply`` (binary, vertex normals and colours) and ``name.obj`` with
``name.mtl`` and the texture ``name.png``. Every file is written atomically (a temporary file in
the same folder, then :func:`os.replace`), the texture and material before the OBJ that points
to them. The meshes are open3d ``TriangleMesh`` objects in whatever frame the caller built them
(Persona's face meshes: x right, y down, z away from the camera, canonical px); ``y_up=True``
turns them 180° about x on the way out (x right, y up, z towards the viewer: the frame most
viewers start in, so the face shows upright and facing the viewer).

Texture coordinates are open3d's ``triangle_uvs``, written as they are: OBJ's convention, origin
at the bottom-left corner of the texture image (open3d reads them back unchanged).

This module imports neither ``persona.plugins`` nor ``persona.dag``.
"""

from __future__ import annotations

import io
import multiprocessing
import os
import threading
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import open3d as o3d

from . import storage
from .media import atomic_path, write_bytes, write_png

__all__ = ["clean_mesh", "write_mesh"]


def _check_name(name: str) -> str:
    if not isinstance(name, str) or not name or os.sep in name or "/" in name or name.startswith("."):
        raise ValueError(f"mesh name must be a plain file stem (no folder, not hidden), got {name!r}")
    return name


def _oriented(mesh: o3d.geometry.TriangleMesh, y_up: bool, origin, scale: float) -> o3d.geometry.TriangleMesh:
    out = o3d.geometry.TriangleMesh(mesh)  # a copy: the caller's mesh is left alone
    if not out.has_vertex_normals():
        out.compute_vertex_normals()
    out.vertices = o3d.utility.Vector3dVector((np.asarray(out.vertices) - np.asarray(origin, np.float64)) * scale)
    if y_up:
        flip = np.diag([1.0, -1.0, -1.0])  # a proper rotation (det +1): winding and normals stay consistent
        out.vertices = o3d.utility.Vector3dVector(np.asarray(out.vertices) @ flip)
        out.vertex_normals = o3d.utility.Vector3dVector(np.asarray(out.vertex_normals) @ flip)
    return out


def _rows(fmt: str, prefix: str, a: np.ndarray) -> str:
    if len(a) == 0:
        return ""
    buf = io.StringIO()
    np.savetxt(buf, a, fmt=fmt)
    return "".join(prefix + line for line in buf.getvalue().splitlines(keepends=True))


def _obj_text(mesh: o3d.geometry.TriangleMesh, name: str, textured: bool) -> str:
    v = np.asarray(mesh.vertices)
    tris = np.asarray(mesh.triangles, dtype=np.int64) + 1
    parts = ["# Persona mesh\n"]
    if textured:
        parts.append(f"mtllib {name}.mtl\n")
    if mesh.has_vertex_colors():
        parts.append(_rows("%.6f %.6f %.6f %.5f %.5f %.5f", "v ", np.hstack([v, np.asarray(mesh.vertex_colors)])))
    else:
        parts.append(_rows("%.6f %.6f %.6f", "v ", v))
    parts.append(_rows("%.6f %.6f %.6f", "vn ", np.asarray(mesh.vertex_normals)))
    if textured:
        parts.append(_rows("%.7f %.7f", "vt ", np.asarray(mesh.triangle_uvs)))
        parts.append(f"usemtl {name}\n")
        t = np.arange(1, 3 * len(tris) + 1).reshape(-1, 3)
        faces = np.stack([tris, t, tris], axis=2).reshape(-1, 9)
        parts.append(_rows("%d/%d/%d %d/%d/%d %d/%d/%d", "f ", faces))
    else:
        faces = np.stack([tris, tris], axis=2).reshape(-1, 6)
        parts.append(_rows("%d//%d %d//%d %d//%d", "f ", faces))
    return "".join(parts)


def _write_ply(path, mesh: o3d.geometry.TriangleMesh) -> None:
    with atomic_path(path, ".ply") as tmp:
        plain = o3d.geometry.TriangleMesh(mesh.vertices, mesh.triangles)
        plain.vertex_normals = mesh.vertex_normals
        if mesh.has_vertex_colors():
            plain.vertex_colors = mesh.vertex_colors
        ok = o3d.io.write_triangle_mesh(tmp, plain, write_ascii=False, compressed=False,
                                        write_vertex_normals=True, write_vertex_colors=mesh.has_vertex_colors(),
                                        write_triangle_uvs=False, print_progress=False)
        if not ok:
            raise OSError(f"open3d could not write {path}")


def write_mesh(folder, name: str, mesh: o3d.geometry.TriangleMesh, texture: np.ndarray | None = None, *,
               y_up: bool = False, origin=(0.0, 0.0, 0.0), scale: float = 1.0, units: str = "") -> dict[str, Path | str]:
    """Write ``name.ply`` and ``name.obj`` (+ ``name.mtl`` and ``name.png`` with a texture) in ``folder``.

    mesh : ``open3d.geometry.TriangleMesh``; vertex normals are computed when missing; vertex colours,
        when present, go into both files (OBJ as ``v x y z r g b``, which MeshLab, Blender and open3d read)
    texture : (h, w, 3) uint8 RGB image or None; needs the mesh's ``triangle_uvs`` (one per triangle corner)
    y_up : turn the mesh 180° about x first (module docstring)
    origin, scale, units : the vertices written are ``(v - origin) * scale``, in ``units`` (named in
        the OBJ's header), before the turn

    Returns the paths written (Paths, or URLs in a ``folder`` given as a URL), keyed ``"ply"``,
    ``"obj"`` and, with a texture, ``"mtl"``, ``"png"``.
    """
    name = _check_name(name)
    if not storage.is_url(folder):
        Path(folder).mkdir(parents=True, exist_ok=True)
    if not isinstance(mesh, o3d.geometry.TriangleMesh):
        raise TypeError(f"mesh must be an open3d.geometry.TriangleMesh, got {type(mesh).__name__}")
    textured = texture is not None
    if textured:
        tex = np.asarray(texture)
        if tex.dtype != np.uint8 or tex.ndim != 3 or tex.shape[2] != 3:
            raise ValueError(f"texture must be an (h, w, 3) uint8 RGB image, got {tex.dtype} {tex.shape}")
        if len(mesh.triangle_uvs) != 3 * len(mesh.triangles):
            raise ValueError(f"a texture needs triangle_uvs (3 per triangle = {3 * len(mesh.triangles)}), "
                             f"the mesh has {len(mesh.triangle_uvs)}")
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be positive and finite, got {scale}")
    m = _oriented(mesh, y_up, origin, scale)
    paths = {}
    if textured:
        paths["png"] = storage.join(folder, f"{name}.png")
        write_png(paths["png"], tex)
        paths["mtl"] = storage.join(folder, f"{name}.mtl")
        mtl = (f"# Persona mesh material\nnewmtl {name}\nKa 1.000 1.000 1.000\nKd 1.000 1.000 1.000\n"
               f"Ks 0.000 0.000 0.000\nd 1.0\nillum 1\nmap_Kd {name}.png\n")
        write_bytes(paths["mtl"], mtl.encode("utf-8"))
    paths["obj"] = storage.join(folder, f"{name}.obj")
    header = f"# units: {units}\n" if units else ""
    write_bytes(paths["obj"], (header + _obj_text(m, name, textured)).encode("utf-8"))
    paths["ply"] = storage.join(folder, f"{name}.ply")
    _write_ply(paths["ply"], m)
    return paths


def clean_mesh(mesh: o3d.geometry.TriangleMesh, *, min_component_faces: int | None = None) -> o3d.geometry.TriangleMesh:
    """A cleaned copy of ``mesh`` through pymeshlab: duplicated vertices merged, duplicated and
    null faces removed, connected components with fewer than ``min_component_faces`` faces
    removed (default: 1 % of the faces, at least 10), unreferenced vertices removed.

    Vertex colours and per-corner ``triangle_uvs`` are carried through; vertex normals are
    recomputed.

    pymeshlab runs in the process's main thread only: from any other thread it corrupts the heap
    (glibc then aborts, "malloc_consolidate(): unaligned fastbin chunk detected", at the latest when
    the process exits). Called from another thread (a Dask worker's task, a version-2 run's build
    of a person), the cleaning runs in a new process of its own, which costs a second or two.
    """
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.triangles, dtype=np.int32)
    colours = np.asarray(mesh.vertex_colors, dtype=np.float64) if mesh.has_vertex_colors() else None
    uvs = np.asarray(mesh.triangle_uvs, dtype=np.float64) if len(mesh.triangle_uvs) == 3 * len(faces) > 0 else None
    if min_component_faces is None:
        min_component_faces = max(10, len(faces) // 100)
    args = (verts, faces, colours, uvs, int(min_component_faces))
    if threading.current_thread() is threading.main_thread():
        verts, faces, colours, uvs = _cleaned(*args)
    else:
        with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as process:
            verts, faces, colours, uvs = process.submit(_cleaned, *args).result()
    out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(faces))
    if colours is not None:
        out.vertex_colors = o3d.utility.Vector3dVector(colours)
    if uvs is not None:
        out.triangle_uvs = o3d.utility.Vector2dVector(uvs)
        out.triangle_material_ids = o3d.utility.IntVector(np.zeros(len(out.triangles), np.int32))
    out.compute_vertex_normals()
    return out


def _cleaned(verts, faces, colours, uvs, min_component_faces: int) -> tuple:
    """:func:`clean_mesh`'s pymeshlab filters on arrays: (vertices, faces, colours or None, uvs or None)."""
    import pymeshlab

    kw = {}
    if colours is not None:
        kw["v_color_matrix"] = np.hstack([colours, np.ones((len(verts), 1))])
    if uvs is not None:
        kw["w_tex_coords_matrix"] = uvs
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=verts, face_matrix=faces, **kw))
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_null_faces()
    ms.meshing_remove_connected_component_by_face_number(mincomponentsize=min_component_faces, removeunref=True)
    ms.meshing_remove_unreferenced_vertices()
    cur = ms.current_mesh()
    return (cur.vertex_matrix(), cur.face_matrix().astype(np.int32),
            cur.vertex_color_matrix()[:, :3] if colours is not None else None,
            cur.wedge_tex_coord_matrix() if uvs is not None and cur.has_wedge_tex_coord() else None)

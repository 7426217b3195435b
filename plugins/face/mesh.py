"""Meshes parametrised on the canonical grid, and ray casting against them (open3d)."""

from __future__ import annotations

import cv2
import numpy as np


def rim_points(mask: np.ndarray, spacing: int) -> np.ndarray:
    """(k, 2) float64 canonical (x, y) points every ``spacing`` px along ``mask``'s outer contour:
    where a spline that moves the face's inside holds still."""
    contours = cv2.findContours(np.asarray(mask, np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0]
    return max(contours, key=len)[::spacing, 0].astype(np.float64)


def grid_triangles(mask: np.ndarray) -> np.ndarray:
    """Triangles (m, 3) of vertex indices (row * W + col): two per grid quad whose four corners are in ``mask``."""
    h, w = mask.shape
    quad = mask[:-1, :-1] & mask[:-1, 1:] & mask[1:, :-1] & mask[1:, 1:]
    r, c = np.nonzero(quad)
    a = r * w + c
    b, d, e = a + 1, a + w, a + w + 1
    return np.concatenate([np.stack([a, d, b], 1), np.stack([b, d, e], 1)]).astype(np.uint32)


def raycasting_scene(vertices: np.ndarray, triangles: np.ndarray):
    """An open3d RaycastingScene of one triangle mesh; vertices (n, 3)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)))
    return scene


def cast(scene, origins: np.ndarray, directions: np.ndarray) -> dict:
    """Cast rays (n, 3) + (n, 3); returns t_hit (inf on a miss), primitive_ids and primitive_uvs as NumPy."""
    import open3d as o3d

    rays = np.concatenate([origins, directions], axis=1).astype(np.float32)
    hits = scene.cast_rays(o3d.core.Tensor(rays))
    return {k: hits[k].numpy() for k in ("t_hit", "primitive_ids", "primitive_uvs")}

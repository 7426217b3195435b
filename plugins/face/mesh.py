"""Meshes parametrised on the canonical grid, and ray casting against them (open3d)."""

from __future__ import annotations

import cv2
import numpy as np

from .mouth import outer_corners
from .template import IDX49
from .warp import FACING


def rim_points(mask: np.ndarray, spacing: int) -> np.ndarray:
    """(k, 2) float64 canonical (x, y) points every ``spacing`` px along ``mask``'s outer contour:
    where a spline that moves the face's inside holds still."""
    contours = cv2.findContours(np.asarray(mask, np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0]
    return max(contours, key=len)[::spacing, 0].astype(np.float64)


def above_jaw(jaw: np.ndarray, shape: tuple[int, int], margin: float) -> np.ndarray:
    """(H, W) float32 in [0, 1]: how much of each canonical texel of a face whose jaw line (iBUG 0-16, (17, 2)
    canonical x, y) is ``jaw`` lies above that line moved ``margin`` px outwards (each point along its normal,
    away from the jaw's middle) and between its two ends' columns, antialiased: the face, without the neck,
    the ears and the background a canonical frame holds below and beside a jaw narrower than its oval."""
    jaw = np.asarray(jaw, np.float64)
    tangent = np.gradient(jaw, axis=0)
    normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)
    normal *= np.sign(np.sum((jaw - jaw.mean(axis=0)) * normal, axis=1, keepdims=True))  # outwards
    line = jaw + margin * normal
    outline = np.vstack([[line[0, 0], -1.0], line, [line[-1, 0], -1.0]])
    fine = np.zeros((shape[0] * 4, shape[1] * 4), np.uint8)  # drawn 4 times finer, averaged down
    cv2.fillPoly(fine, [np.round(((outline + 0.5) * 4 - 0.5) * 16).astype(np.int32)], 255, cv2.LINE_8, shift=4)
    return cv2.resize(fine, shape[::-1], interpolation=cv2.INTER_AREA).astype(np.float32) / 255


#: iBUG indices of the middle of the outer lower lip
LOWER_LIP = (56, 57, 58)


def jaw_motion(fiducials49: np.ndarray, offsets49: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(k, 2): how far the ``points`` (k, 2; x, y on the grid of the 49 ``fiducials49``) move with the
    jaw when the fiducials move by ``offsets49`` (49, 2). A rim held still while the lips part squeezes
    the chin between the lower lip and the rim; a jaw is rigid, and the chin drops with it.

    Each point takes a share of the mean offset of the lower lip's middle (iBUG 56-58): 0 at and above
    the mouth's corners, rising smoothly to 1 at the lower lip's middle and below, times a Gaussian
    across the face whose σ is the mouth's width: the chin moves with the lip, the cheeks beside the
    mouth less (docs/expression.md, "A jaw that drops with the lips")."""
    f, points = np.asarray(fiducials49, np.float64), np.asarray(points, np.float64)
    lower = [IDX49.index(i) for i in LOWER_LIP]
    corners = outer_corners(f)
    lip = f[lower].mean(axis=0)
    top, width = corners[:, 1].mean(), abs(corners[1, 0] - corners[0, 0])
    t = np.clip((points[:, 1] - top) / max(lip[1] - top, 1e-6), 0, 1)
    share = t * t * (3 - 2 * t) * np.exp(-0.5 * ((points[:, 0] - lip[0]) / max(width, 1e-6)) ** 2)
    return share[:, None] * np.asarray(offsets49, np.float64)[lower].mean(axis=0)


def lip_split(fiducials49: np.ndarray, offsets49: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(k, 2): how far the ``points`` (k, 2; x, y on the grid of the 49 ``fiducials49``) move with the
    lower lip as it parts from the upper one, when the fiducials move by ``offsets49`` (49, 2): the part
    of a mouth's opening a smooth spline cannot draw.

    The lips' two inner curves lie a texel or two apart on a closed mouth, and part by tens of texels when
    it opens: a spline through both, moved so far apart so close together, overshoots, and the rows just
    below the lower lip run down past the lip and fold back under it (the lip stretched into a pale band
    with a jagged edge below). Here the lower lip's opening, how much further down each inner lower point
    moves than the upper one facing it (the vertical part; none where the lips close), is taken out of the
    spline's work: every point below the line where the lips meet moves down by it, at its full value
    just below the line, fading (a Gaussian of σ half the mouth's width) further down, the chin's motion
    being left to the spline; a texel the line crosses moves by the share of it below the line, so a
    line that slopes across the grid parts the lips along it, not in steps of a texel. Along the mouth it is interpolated between the three pairs and falls to
    0 at the outer corners, where the lips stay joined; points above the line, and beside the mouth,
    do not move."""
    f, d = np.asarray(fiducials49, np.float64), np.asarray(offsets49, np.float64)
    points = np.asarray(points, np.float64)
    corners = outer_corners(f)
    xs = np.concatenate([[corners[0, 0]], [(f[u, 0] + f[l, 0]) / 2 for u, l in FACING[4:]], [corners[1, 0]]])
    meet = np.concatenate([[corners[0, 1]], [(f[u, 1] + f[l, 1]) / 2 for u, l in FACING[4:]], [corners[1, 1]]])
    opening = np.concatenate([[0.0], [max(d[l, 1] - d[u, 1], 0.0) for u, l in FACING[4:]], [0.0]])
    out = np.zeros((len(points), 2))
    if not (np.all(np.isfinite(xs)) and np.all(np.isfinite(opening)) and np.all(np.diff(xs) > 0)):
        return out
    x, y = points[:, 0], points[:, 1]
    line = np.interp(x, xs, meet)
    below = np.clip(y - line + 0.5, 0.0, 1.0) * ((x > xs[0]) & (x < xs[-1]))  # a texel's share below the line
    sigma = max((xs[-1] - xs[0]) / 2, 1e-6)
    out[:, 1] = below * np.interp(x, xs, opening) * np.exp(-0.5 * (np.maximum(y - line, 0.0) / sigma) ** 2)
    return out


def enclosed(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: ``mask`` with every hole it encloses filled, what no path of unmasked pixels (4-connected)
    joins to the grid's border: the face's own holes (under the nose, which hides it from a camera above),
    not its edge."""
    outside = np.pad(~np.asarray(mask, bool), 1, constant_values=True).astype(np.uint8)
    cv2.floodFill(outside, None, (0, 0), 2)
    return outside[1:-1, 1:-1] != 2


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

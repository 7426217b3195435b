"""Frontalization: sample the photo at the projection of every canonical template point.

After Hassner et al. (CVPR 2015) and ALGORITHMS.md §4: the map ``fmap`` takes each
canonical pixel (x, y) to the photo pixel where the posed template point
(x, y, Z(x, y)) projects; the photo is sampled once through it. A z-buffer of the
posed template (ray casting) marks self-occluded canonical pixels, which stay out of the mask
(used later as weights, never filled with mirrored texture).
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
from pydantic import Field
from scipy.ndimage import map_coordinates

from ..base import Params, Rejected
from ..face.mesh import cast, grid_triangles, raycasting_scene
from ..face.template import IDX49, generic_template
from ..hookspecs import hookimpl
from ..kinds import Frontal, FrontalizeBackend, Pose


def project(points: np.ndarray, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Project (..., 3) template points: image (x, y) of shape (..., 2) and camera depth (...)."""
    rotation = cv2.Rodrigues(pose.rvec)[0]
    cam = points @ rotation.T + pose.tvec
    z = cam[..., 2]
    k = pose.camera
    xy = np.stack([k[0, 0] * cam[..., 0] / z + k[0, 2], k[1, 1] * cam[..., 1] / z + k[1, 2]], axis=-1)
    return xy, z


def template_points(depth: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """3D template points (..., 3) at canonical positions xy (..., 2), depth sampled bilinearly."""
    z = map_coordinates(depth, [xy[..., 1].ravel(), xy[..., 0].ravel()], order=1, mode="nearest")
    return np.concatenate([xy, z.reshape(xy.shape[:-1])[..., None]], axis=-1)


def frontalizing_map(depth: np.ndarray, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """fmap (H, W, 2) float32 canonical pixel -> photo (x, y), and camera depth (H, W)."""
    h, w = depth.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    xy, z = project(np.stack([xs, ys, depth], axis=-1), pose)
    return xy.astype(np.float32), z


@lru_cache(maxsize=1)
def template_scene():
    """The generic template as a ray-casting scene in canonical coordinates (built once per process)."""
    template = generic_template()
    h, w = template.depth.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    vertices = np.stack([xs, ys, template.depth], axis=-1).reshape(-1, 3)
    return raycasting_scene(vertices, grid_triangles(template.mask))


def visible(fmap: np.ndarray, mask: np.ndarray, pose: Pose, image_size, tolerance: float,
            step: int = 1) -> np.ndarray:
    """Canonical pixels whose template point is the first surface hit on its ray from the camera.

    An exact z-buffer: rays from the camera centre (expressed in the canonical frame)
    through each template point; the point is visible when nothing of the template lies
    in front of it, and its projection falls inside the photo. With ``step`` > 1 the rays
    are cast on every step-th row and column and the answer spread to the pixels between.
    """
    template = generic_template()
    h, w = image_size
    inside = (mask & (fmap[..., 0] >= 0) & (fmap[..., 0] <= w - 1)
              & (fmap[..., 1] >= 0) & (fmap[..., 1] <= h - 1))
    rotation = cv2.Rodrigues(pose.rvec)[0]
    centre = -rotation.T @ pose.tvec
    coarse = np.zeros_like(mask)
    coarse[::step, ::step] = True
    rows, cols = np.nonzero(coarse & template.mask)
    points = np.stack([cols, rows, template.depth[rows, cols]], axis=1).astype(np.float64)
    offsets = points - centre
    distance = np.linalg.norm(offsets, axis=1)
    hits = cast(template_scene(), np.broadcast_to(centre, points.shape), offsets / distance[:, None])
    seen = np.zeros(mask.shape, np.uint8)
    seen[rows, cols] = hits["t_hit"] >= distance - tolerance
    if step > 1:  # each cast ray stands for the step x step block it starts
        seen = np.repeat(np.repeat(seen[::step, ::step], step, 0), step, 1)[:mask.shape[0], :mask.shape[1]]
    return inside & seen.astype(bool)


def canonical_landmarks(points: np.ndarray, depth: np.ndarray, pose: Pose, start: np.ndarray,
                        iterations: int = 20, max_step: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """Invert the frontalizing map at photo points (n, 2) by Gauss-Newton (ALGORITHMS §4.4).

    Returns (n, 2) canonical positions whose posed template point projects onto each photo
    point (the pose-corrected landmarks F^i), and the (n,) photo-px distance by which each
    still misses. A step moves a point at most ``max_step`` canonical px: a landmark on the
    silhouette of a turned face (the far side of the nose, say) has no preimage on the
    template, and unbounded steps there diverge to hundreds of px; bounded, such a point
    stays near the face and its miss says that it did not converge.
    """
    x = start.astype(np.float64).copy()
    delta = 0.5
    for _ in range(iterations):
        f = project(template_points(depth, x), pose)[0]
        jac = np.empty((len(x), 2, 2))
        for j in range(2):
            d = np.zeros(2)
            d[j] = delta
            jac[:, :, j] = (project(template_points(depth, x + d), pose)[0]
                            - project(template_points(depth, x - d), pose)[0]) / (2 * delta)
        # damped Gauss-Newton: a (near-)singular Jacobian far off the face must not fail
        jt = np.swapaxes(jac, 1, 2)
        normal = jt @ jac + 1e-6 * np.eye(2)
        step = np.linalg.solve(normal, jt @ (f - points)[..., None])[..., 0]
        length = np.linalg.norm(step, axis=1, keepdims=True)
        x -= step * np.minimum(1.0, max_step / np.maximum(length, 1e-12))
        if length.max() < 1e-4:
            break
    miss = np.linalg.norm(project(template_points(depth, x), pose)[0] - points, axis=1)
    return x, miss


def seen_at(points: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(n,) bool: whether each canonical point (n, 2) lies on a pixel of ``mask`` (False outside it)."""
    h, w = mask.shape
    cols, rows = np.round(np.nan_to_num(points, nan=-1.0)).astype(int).T
    inside = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
    seen = np.zeros(len(points), bool)
    seen[inside] = mask[rows[inside], cols[inside]]
    return seen


class TemplateFrontalize(FrontalizeBackend):
    name = "template"
    description = "back-project the posed generic 3D template (Hassner et al. 2015) with a z-buffer visibility mask"
    default = True
    version = "2"

    class Params(Params):
        occlusion_tolerance: float = Field(
            1.0, ge=0, description="canonical px a template point may lie behind the first "
            "surface hit on its camera ray and still count as visible")
        visibility_step: int = Field(2, ge=1, le=8, description="cast visibility rays on every "
                                     "n-th canonical row and column (1 = every pixel, exact)")
        min_visible: float = Field(0.3, ge=0, le=1, description="reject faces with less than "
                                   "this fraction of the template's face visible")
        landmark_miss: float = Field(0.02, gt=0, description="a pose-corrected landmark whose posed "
                                     "template point misses its photo landmark by more than this many "
                                     "inter-ocular distances has no preimage on the face (the silhouette "
                                     "of a turned face) and is marked not visible (NaN); converged points "
                                     "miss by < 0.001, silhouette points by 0.05-0.08 (docs/fiducials.md)")
        min_fiducials: float = Field(0.6, ge=0, le=1, description="reject faces with fewer than this "
                                     "fraction of the 49 fiducials visible after pose correction")

    def canonical_map(self, pose):
        return frontalizing_map(generic_template().depth, pose)[0]

    def frontalize(self, image, landmarks, pose):
        template = generic_template()
        fmap = self.canonical_map(pose)
        mask = visible(fmap, template.mask, pose, image.shape[:2], self.params.occlusion_tolerance,
                       self.params.visibility_step)
        fraction = mask.sum() / template.mask.sum()
        if fraction < self.params.min_visible:
            raise Rejected(f"frontalize: only {fraction:.0%} of the face is visible in the photo")
        canonical, miss = canonical_landmarks(landmarks, template.depth, pose, template.landmarks3d[:, :2])
        photo_iod = np.linalg.norm(landmarks[36:42].mean(axis=0) - landmarks[42:48].mean(axis=0))
        converged = miss <= self.params.landmark_miss * photo_iod
        fiducials = list(IDX49)
        h, w = mask.shape
        outside = converged & ~((canonical >= 0) & (canonical <= [w - 1, h - 1])).all(axis=1)
        if outside[fiducials].any():
            raise Rejected(f"frontalize: {outside[fiducials].sum()} fiducials land outside the canonical "
                           "frame: the pose does not fit the landmarks")
        trusted = converged & seen_at(canonical, mask)
        if trusted[fiducials].mean() < self.params.min_fiducials:
            raise Rejected(f"frontalize: only {trusted[fiducials].sum()} of the 49 fiducials are visible "
                           f"after pose correction (at least {self.params.min_fiducials:.0%} needed)")
        canonical[~trusted] = np.nan
        rgb = cv2.remap(image, fmap[..., 0], fmap[..., 1], cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        rgb[~mask] = 0
        return Frontal(rgb=rgb, mask=mask, landmarks=canonical)


@hookimpl
def persona_register_backends(register):
    register(TemplateFrontalize)

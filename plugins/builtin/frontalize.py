"""Frontalization: sample the photo at the projection of every canonical template point.

After Hassner et al. (CVPR 2015) and ALGORITHMS.md §4: the map ``fmap`` takes each
canonical pixel (x, y) to the photo pixel where the posed template point
(x, y, Z(x, y)) projects; the photo is sampled once through it. A z-buffer of the
posed template marks self-occluded canonical pixels, which stay out of the mask
(used later as weights, never filled with mirrored texture).
"""

from __future__ import annotations

import cv2
import numpy as np
from pydantic import Field
from scipy.ndimage import map_coordinates

from ..base import Params, Rejected
from ..face.template import generic_template
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


def visible(fmap: np.ndarray, z: np.ndarray, mask: np.ndarray, image_size, tolerance: float) -> np.ndarray:
    """Canonical pixels whose template point is the nearest one along its photo pixel's ray."""
    h, w = image_size
    cols = np.round(fmap[..., 0]).astype(np.int64)
    rows = np.round(fmap[..., 1]).astype(np.int64)
    inside = mask & (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h) & (z > 0)
    flat = rows[inside] * w + cols[inside]
    zbuffer = np.full(h * w, np.inf)
    np.minimum.at(zbuffer, flat, z[inside])
    # a 3x3 minimum makes the test robust to the rounding of neighbouring samples
    zbuffer = cv2.erode(zbuffer.reshape(h, w).astype(np.float32), np.ones((3, 3), np.uint8))
    out = np.zeros_like(mask)
    out[inside] = z[inside] <= zbuffer.ravel()[flat] + tolerance
    return out


def canonical_landmarks(points: np.ndarray, depth: np.ndarray, pose: Pose, start: np.ndarray,
                        iterations: int = 8) -> np.ndarray:
    """Invert the frontalizing map at photo points (n, 2) by Gauss-Newton (ALGORITHMS §4.4).

    Returns (n, 2) canonical positions whose posed template point projects onto each
    photo point: the pose-corrected landmarks F^i.
    """
    x = start.astype(np.float64).copy()
    step = 0.5
    for _ in range(iterations):
        f = project(template_points(depth, x), pose)[0]
        jac = np.empty((len(x), 2, 2))
        for j in range(2):
            d = np.zeros(2)
            d[j] = step
            jac[:, :, j] = (project(template_points(depth, x + d), pose)[0]
                            - project(template_points(depth, x - d), pose)[0]) / (2 * step)
        x -= np.linalg.solve(jac, (f - points)[..., None])[..., 0]
    return x


class TemplateFrontalize(FrontalizeBackend):
    name = "template"
    description = "back-project the posed generic 3D template (Hassner et al. 2015) with a z-buffer visibility mask"
    default = True

    class Params(Params):
        occlusion_tolerance: float = Field(
            3.0, ge=0, description="canonical depth units a point may lie behind the z-buffer "
            "and still count as visible")
        min_visible: float = Field(0.3, ge=0, le=1, description="reject faces with less than "
                                   "this fraction of the template's face visible")

    def frontalize(self, image, landmarks, pose):
        template = generic_template()
        fmap, z = frontalizing_map(template.depth, pose)
        mask = visible(fmap, z, template.mask, image.shape[:2], self.params.occlusion_tolerance)
        fraction = mask.sum() / template.mask.sum()
        if fraction < self.params.min_visible:
            raise Rejected(f"frontalize: only {fraction:.0%} of the face is visible in the photo")
        rgb = cv2.remap(image, fmap[..., 0], fmap[..., 1], cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        rgb[~mask] = 0
        canonical = canonical_landmarks(landmarks, template.depth, pose, template.landmarks3d[:, :2])
        return Frontal(rgb=rgb, mask=mask, landmarks=canonical)


@hookimpl
def persona_register_backends(register):
    register(TemplateFrontalize)

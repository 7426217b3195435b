"""The paper's 2D baseline renderer (§6, Fig. 5): one static average face, TPS-warped to
the target expression, placed in the driver's frame at the driver's head pose."""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np
from pydantic import Field

from ..base import Params
from ..face.composite import GREY
from ..face.mesh import cast
from ..face.warp import tps_map
from ..hookspecs import hookimpl
from ..kinds import Pose, RenderBackend, Rendered
from ..face.template import generic_template
from .frontalize import project, template_scene


def canonical_coordinates(pose: Pose, frame_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel of a frame, the canonical (x, y) of the posed template seen there.

    Casts a ray from the camera through each pixel (K⁻¹[j, i, 1], OpenCV pixel centres)
    onto the template. Returns the map (h, w, 2) float32 and a hit mask (h, w) bool.
    """
    h, w = frame_size
    where = np.zeros((h, w, 2), np.float32)
    hit = np.zeros((h, w), bool)
    box = _face_box(pose, frame_size)
    if box is None:
        return where, hit
    x0, y0, x1, y1 = box  # rays only where the face can be
    rotation = cv2.Rodrigues(pose.rvec)[0]
    centre = -rotation.T @ pose.tvec
    ys, xs = np.mgrid[y0:y1, x0:x1]
    pixels = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)], axis=1)
    directions = (np.linalg.solve(pose.camera, pixels.T).T) @ rotation  # R^T d for each row d
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    t_hit = cast(template_scene(), np.broadcast_to(centre, directions.shape), directions)["t_hit"]
    found = np.isfinite(t_hit)
    points = centre + directions * np.where(found, t_hit, 0)[:, None]
    where[y0:y1, x0:x1] = points[:, :2].reshape(y1 - y0, x1 - x0, 2)
    hit[y0:y1, x0:x1] = found.reshape(y1 - y0, x1 - x0)
    return where, hit


def _face_box(pose: Pose, frame_size) -> tuple[int, int, int, int] | None:
    """The frame box (x0, y0, x1, y1) holding the posed template's face, or None if off-frame."""
    template = generic_template()
    rows, cols = np.nonzero(template.mask[::4, ::4])
    points = np.stack([cols * 4, rows * 4, template.depth[rows * 4, cols * 4]], axis=1).astype(np.float64)
    xy = project(points, pose)[0]
    h, w = frame_size
    x0, y0 = np.floor(xy.min(axis=0)).astype(int) - 4
    x1, y1 = np.ceil(xy.max(axis=0)).astype(int) + 5
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None


class Tps2dRender(RenderBackend):
    name = "tps2d"
    description = "the paper's 2D baseline: the puppet's average face TPS-warped to the target fiducials, at the driver's pose"
    default = False
    version = "5"  # 2: rgb is the face's own colour across its soft edge (Rendered); no background param; 3: the
    # render step stores render/own (none of this backend's pixels); 4: its light plane from a deeper ring (LIGHT_BAND);
    # 5: the light plane judges skin in the face's own light (composite.skin_light)

    class Params(Params):
        tps_lambda: float = Field(10.0, ge=0, description="λ of the smoothing TPS (Eq. 1; paper: 10)")
        tps_scaling: Literal["objective", "diagonal", "wahba"] = Field(
            "objective", description="how λ enters the TPS system: 8πλ (the written objective), "
            "λ on the diagonal, or Wahba's 8πnλ (ALGORITHMS §5.2)")
        tps_step: int = Field(4, ge=1, le=16, description="evaluate the TPS on every n-th canonical "
                              "pixel and interpolate (1 = exact)")
        min_coverage: float = Field(0.3, ge=0, le=1, description="canonical pixels seen in fewer "
                                    "than this fraction of the puppet's photos are left out")
        feather: float = Field(3.0, ge=0, description="Gaussian σ (frame px) of the soft face edge")

    def render(self, puppet, target, pose, frame):
        h, w = frame.shape[:2]
        warp = tps_map(target, puppet.fiducials, puppet.coverage.shape,
                       lam=self.params.tps_lambda, scaling=self.params.tps_scaling, step=self.params.tps_step)
        face = cv2.remap(puppet.appearance, warp[..., 0], warp[..., 1], cv2.INTER_LINEAR)
        seen = cv2.remap((puppet.coverage >= self.params.min_coverage).astype(np.float32),
                         warp[..., 0], warp[..., 1], cv2.INTER_LINEAR)
        where, hit = canonical_coordinates(pose, (h, w))
        rgb = cv2.remap(face, where[..., 0], where[..., 1], cv2.INTER_LINEAR)
        mask = cv2.remap(seen, where[..., 0], where[..., 1], cv2.INTER_LINEAR) * hit
        if self.params.feather > 0:
            mask = cv2.GaussianBlur(mask, (0, 0), self.params.feather) * (mask > 0.5)
        out = np.where((mask > 0)[..., None], np.clip(rgb, 0, 255).round(), GREY).astype(np.uint8)
        return Rendered(rgb=out, mask=mask.astype(np.float32))


@hookimpl
def persona_register_backends(register):
    register(Tps2dRender)

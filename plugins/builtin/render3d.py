"""The paper's final rendering (§6, ALGORITHMS §13): the puppet's per-frame 3D mesh M_P^t, textured
with the frame's synthesized face, drawn at the driver's head pose with the driver's camera.

Each frame pixel shows the first surface point on the ray from the camera through its centre
(``K⁻¹[j, i, 1]``, OpenCV pixel centres, no half-pixel offset; ALGORITHMS §0), as an open3d
``RaycastingScene`` would find it. The visible surface is computed by a z-buffer rasteriser
compiled with numba rather than by open3d: on one core at 512×512 with the face 250 px wide
(57 800 triangles, 80 000 rays in the face box) open3d's ray casting alone takes about 55 ms a
frame; the z-buffer pass takes about 2.5 ms and the whole render about 17 ms
(``benchmarks/render_speed.py``). Both give the same pixels: every pixel centre inside a
projected triangle is tested, depths are compared along the pixel's ray, and the barycentric
weights are perspective-correct, i.e. those of the 3D hit.

The mesh is parametrised on the canonical texture grid: vertex (row v, col u) of ``puppet.mesh``
carries texture coordinate (u, v) of ``puppet.appearance``. Triangles are two per grid quad whose
four corners are finite (``face.mesh.grid_triangles``, the split of the synthetic ground truth).
The (u, v) of each pixel's hit is interpolated barycentrically, then the texture and the coverage
mask are sampled bilinearly there (the texture bicubically with ``sampling: bicubic``, a sharper face at HD:
``texture_sample``).
"""

from __future__ import annotations

from typing import Literal

import cv2
import numba
import numpy as np
from pydantic import Field

from ..base import Params
from ..face import mouth
from ..face.blend import gaussian_pyramid
from ..face.composite import BROWS, EYES, GREY, edge_not_skin, features_of
from ..face.mesh import above_jaw, enclosed, grid_triangles
from ..face.template import IDX49
from ..face.warp import compose
from ..hookspecs import hookimpl
from ..kinds import Pose, Puppet, RenderBackend, Rendered

#: camera depth (canonical px) below which a vertex counts as behind the camera
_NEAR = 1e-3


@numba.njit(cache=True, nogil=True)
def _rasterise(xy, z, uv, triangles, depth, hit_uv, x0, y0):
    """Z-buffer the triangles into the box of ``depth`` whose top-left frame pixel is (x0, y0).

    xy: (n, 2) projected vertices (frame x, y); z: (n,) camera depths; uv: (n, 2) texture
    coordinates; triangles: (m, 3) vertex indices. depth (bh, bw) is filled with the camera depth
    of the nearest surface at each pixel centre (left at +inf elsewhere) and hit_uv (bh, bw, 2) with
    its perspective-correctly interpolated texture coordinate. Triangles with a vertex behind the
    camera are skipped; edge-on ones cover no pixel centre.
    """
    bh, bw = depth.shape
    eps = -1e-7  # a pixel centre on a shared edge goes to both triangles (no cracks)
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        za, zb, zc = z[a], z[b], z[c]
        if za <= _NEAR or zb <= _NEAR or zc <= _NEAR:
            continue
        xa, ya = xy[a, 0] - x0, xy[a, 1] - y0
        xb, yb = xy[b, 0] - x0, xy[b, 1] - y0
        xc, yc = xy[c, 0] - x0, xy[c, 1] - y0
        area = (xb - xa) * (yc - ya) - (xc - xa) * (yb - ya)
        if area == 0.0:
            continue
        c0 = max(int(np.ceil(min(xa, xb, xc))), 0)
        c1 = min(int(np.floor(max(xa, xb, xc))), bw - 1)
        r0 = max(int(np.ceil(min(ya, yb, yc))), 0)
        r1 = min(int(np.floor(max(ya, yb, yc))), bh - 1)
        for r in range(r0, r1 + 1):
            for col in range(c0, c1 + 1):
                wa = ((xb - col) * (yc - r) - (xc - col) * (yb - r)) / area
                wb = ((xc - col) * (ya - r) - (xa - col) * (yc - r)) / area
                wc = 1.0 - wa - wb
                if wa < eps or wb < eps or wc < eps:
                    continue
                pa, pb, pc = wa / za, wb / zb, wc / zc  # perspective-correct: weights / depth
                zz = 1.0 / (pa + pb + pc)
                if zz < depth[r, col]:
                    depth[r, col] = zz
                    hit_uv[r, col, 0] = (pa * uv[a, 0] + pb * uv[b, 0] + pc * uv[c, 0]) * zz
                    hit_uv[r, col, 1] = (pa * uv[a, 1] + pb * uv[b, 1] + pc * uv[c, 1]) * zz


def project(points: np.ndarray, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Frame positions (n, 2) and camera depths (n,) of canonical points (n, 3) at ``pose``
    (R X + t, then K); a point at depth <= ``_NEAR`` (behind the camera) gets an arbitrary position."""
    rotation = cv2.Rodrigues(np.asarray(pose.rvec, np.float64))[0]
    cam = np.asarray(points, np.float64) @ rotation.T + np.asarray(pose.tvec, np.float64).reshape(3)
    z = cam[:, 2]
    k = pose.camera
    safe_z = np.where(z > _NEAR, z, 1.0)
    xy = np.stack([k[0, 0] * cam[:, 0] / safe_z + k[0, 1] * cam[:, 1] / safe_z + k[0, 2],
                   k[1, 1] * cam[:, 1] / safe_z + k[1, 2]], axis=1)
    return xy, z


#: footprints under 2^_LOD_FROM texels (1 % more than one) are sampled bilinearly, as at magnification
_LOD_FROM = np.log2(1.01)


def texture_sample(texture: np.ndarray, u: np.ndarray, v: np.ndarray, holes: np.ndarray | None = None,
                   sampling: str = "bilinear") -> np.ndarray:
    """``texture`` (H, W, C) float32 at the float32 texel coordinates ``u``, ``v`` (h, w), 0 off the
    texture. ``bilinear``: the plain bilinear sample. ``bicubic``: OpenCV's bicubic kernel (4 x 4
    texels), which keeps the detail between texel centres that a bilinear sample averages away where a
    texel spans more than a pixel; where that kernel would reach a texel of ``holes`` (H, W, bool: texels
    with no colour, stored as 0), the bilinear sample, so that the face's edge is no darker than with
    bilinear samples."""
    linear = cv2.remap(texture, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    if sampling == "bilinear":
        return linear
    cubic = cv2.remap(texture, u, v, cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT)
    blank = np.zeros(texture.shape[:2], np.uint8) if holes is None else np.asarray(holes, np.uint8)
    near = cv2.dilate(blank, np.ones((3, 3), np.uint8))  # the bicubic reads one texel further than bilinear
    near = cv2.remap(near.astype(np.float32), u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=1.0) > 0
    return np.where(near[..., None] if linear.ndim == 3 else near, linear, cubic)


def footprint_sample(texture: np.ndarray, u: np.ndarray, v: np.ndarray, holes: np.ndarray | None = None,
                     sampling: str = "bilinear") -> np.ndarray:
    """``texture`` (H, W, C) float32 at the float32 texel coordinates ``u``, ``v`` (h, w; NaN off the
    surface), each pixel filtered to its footprint, as GPUs sample a mipmap: trilinearly between the
    levels of the texture's Gaussian pyramid about log2 of how many texels one pixel spans (the
    longer of its two sides). Bilinear samples alone alias where a face is rendered smaller than its
    texture: a line one texel thin comes out as a row of dots, fine detail as moiré. A pixel that
    spans a texel or less is the plain bilinear sample, to the bit; so is a pixel next to one off the
    surface (NaN; 0 there), whose footprint is not known."""
    span = np.maximum(np.hypot(np.gradient(u, axis=1), np.gradient(v, axis=1)),
                      np.hypot(np.gradient(u, axis=0), np.gradient(v, axis=0)))
    lod = np.nan_to_num(np.log2(np.maximum(span, 1.0)), nan=0.0)[..., None]
    lod[lod < _LOD_FROM] = 0
    u, v = np.nan_to_num(u, nan=-1.0), np.nan_to_num(v, nan=-1.0)  # off the texture: 0
    out = cv2.remap(texture, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    pyramid = gaussian_pyramid(texture, int(np.ceil(lod.max())) + 1)
    for m, level in enumerate(pyramid[1:], start=1):  # level m: 2^m texels a pixel
        s = np.float32(2.0 ** -m)
        coarser = cv2.remap(level, (u + 0.5) * s - 0.5, (v + 0.5) * s - 0.5, cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT)
        t = np.clip(lod - (m - 1), 0, 1).astype(np.float32)
        out = np.where(lod > m - 1, out * (1 - t) + coarser * t, out)
    if sampling != "bilinear":
        out = np.where(lod == 0, texture_sample(texture, u, v, holes, sampling), out)
    return out


def surface_map(mesh: np.ndarray, pose: Pose, frame_size: tuple[int, int], pad: int = 0):
    """Where each frame pixel sees the mesh: its texture coordinate (u, v) and camera depth.

    mesh: (H, W, 3) canonical (x, y, Z), NaN off the face; pose maps canonical X to R X + t, then K;
    frame_size: (h, w). Only the box of the projected mesh, grown by ``pad`` px and clipped to the
    frame, is rasterised. Returns ``(box, uv, depth)`` with box = (x0, y0, x1, y1) (None when the face
    is off-frame, with uv and depth None), uv (y1-y0, x1-x0, 2) float32 (-1 where no surface is
    hit) and depth (y1-y0, x1-x0) float64 (+inf where no surface is hit).
    """
    h, w = frame_size
    grid_h, grid_w = mesh.shape[:2]
    finite = np.isfinite(mesh).all(axis=2)
    triangles = grid_triangles(finite)
    if len(triangles) == 0:
        return None, None, None
    vs, us = np.mgrid[0:grid_h, 0:grid_w]
    uv = np.stack([us, vs], axis=-1).reshape(-1, 2).astype(np.float64)
    xy, z = project(np.where(finite[..., None], mesh, 0).reshape(-1, 3), pose)
    front = finite.ravel() & (z > _NEAR)
    if not front.any():
        return None, None, None
    lo = np.floor(xy[front].min(axis=0)).astype(int) - pad
    hi = np.ceil(xy[front].max(axis=0)).astype(int) + pad + 1
    x0, y0 = max(lo[0], 0), max(lo[1], 0)
    x1, y1 = min(hi[0], w), min(hi[1], h)
    if x1 <= x0 or y1 <= y0:
        return None, None, None
    depth = np.full((y1 - y0, x1 - x0), np.inf)
    hit_uv = np.full((y1 - y0, x1 - x0, 2), -1.0, np.float32)
    _rasterise(xy, z, uv, triangles.astype(np.int64), depth, hit_uv, float(x0), float(y0))
    return (x0, y0, x1, y1), hit_uv, depth


class RaycastRender(RenderBackend):
    """The puppet's 3D face at the driver's pose (paper §6 and Fig. 1; ALGORITHMS §13).

    The face alone: ``rgb`` holds its own colour where the mask is above 0 and grey elsewhere (see
    ``Rendered``). B's face has B's own shape, so its outline differs from the driver's; the paper
    shows the puppet alone, and ``composite.mp4`` blends it into the driver's frame
    (``persona.plugins.face.composite``).
    """

    name = "mesh3d"
    description = ("the paper's final render: the puppet's per-frame 3D mesh with its synthesized "
                   "texture, at the driver's head pose (z-buffered, equal to ray casting pixel centres)")
    default = True
    uses_mesh = True
    #: raised whenever the same inputs are drawn differently, so a stored render is drawn again (the history
    #: is in docs/CHANGELOG.md)
    version = "21"

    class Params(Params):
        min_coverage: float = Field(0.3, ge=0, le=1, description="canonical pixels seen in fewer "
                                    "than this fraction of the puppet's photos are left out where they reach the "
                                    "face's edge (the sides a turned head hides); enclosed by the face (under the "
                                    "nose, which hides the nostrils from a camera above them) they are drawn")
        feather: float = Field(3.0, ge=0, description="Gaussian σ (frame px) of the soft face edge "
                               "(inwards, as tps2d); 0 = hard edge")
        filter_texture: bool = Field(False, description="where the face is drawn smaller than its texture "
                                     "(a pixel spans more than a texel), filter the texture to each pixel's "
                                     "footprint (footprint_sample, as GPUs sample a mipmap) rather than take one "
                                     "bilinear sample, which aliases: a one-texel line comes out dotted. Not in the "
                                     "paper, and off: on Bush <- Obama (1.4 texels a pixel) the shut lids' lash line "
                                     "is whole, but the face is softer and the composite's eye gain falls 0.54 -> "
                                     "0.51 (docs/composite.md)")
        sampling: Literal["bilinear", "bicubic"] = Field(
            "bilinear", description="how the texture is read between its texels: bilinearly (the paper's, as a "
            "GPU samples) or bicubically (4 x 4 texels; bilinear at the texture's edge). At HD a frame pixel spans "
            "about half a texel of the canonical grid, and bilinear interpolation blurs what the texels hold: "
            "bicubic makes the face at HD as sharp as the driver's own (the phone man's self-reenactment, 720p: "
            "0.69 -> 1.00 of the real face's fine detail). But the texture's detail does not lie exactly where "
            "the frame's does, and drawn sharper it differs from the frame more: the four HD self-reenactments' "
            "composites lost 0.09-0.43 dB. Not in the paper (docs/composite.md)")
        jaw_margin: float | None = Field(2.0, ge=0, description="draw B's face only above B's jaw line (the "
                                         "median of B's aligned photos' iBUG 0-16) moved this many canonical px "
                                         "outwards: below and beside B's jaw the canonical frame holds B's neck, "
                                         "ears and background, which were drawn as face. Not in the paper; None: "
                                         "the whole face mask, as the paper draws it (docs/composite.md)")
        rim: Literal["skin", "texture"] = Field(
            "skin", description="what of B's texture is drawn at the face's edge. `skin` (the default; not in "
            "the paper): what looks like B's skin there, judged on B's neutral texture so that it is the same in "
            "every frame, leaving out what does not and reaches in from beyond the edge (composite.edge_not_skin, "
            "B's eyes and brows spared, the chin's sector kept): the hair that hung over B's cheeks and temples in "
            "B's photos, which their blend keeps as a dark band at the rim and which, drawn, showed as a dark "
            "stripe down the cheek of the head B's face is put on. `texture`: all of it, as the paper draws it "
            "(docs/composite.md)")
        mouth: bool = Field(True, description="draw the inside of B's mouth (from B's open-mouth "
                            "photos) between B's inner lips where the mesh parts them, instead of the "
                            "stretched skin of a surface that cannot open (not in the paper; "
                            "persona.plugins.face.mouth)")
        mouth_photos: int = Field(5, ge=1, le=100, description="how many of B's open photos make the "
                                  "mouth's interior (their per-pixel median)")
        mouth_min_gap: float = Field(0.08, ge=0, description="a photo counts as open when its inner lips "
                                     "are this many inter-ocular distances apart")
        mouth_choice: Literal["frame", "widest", "darkest", "driver"] = Field(
            "frame", description="what the mouth's interior is made of. `frame` (the default): the driver's "
            "own mouth interior in each frame (A's teeth, tongue and cavity, between A's inner lips; "
            "mouth.from_frame), drawn into B's gap, its rows nearest each lip at their own size; none where A's "
            "lips are closed (B's own lips close over the gap). Or B's own open photos: those whose lips are furthest apart "
            "(mostly laughs: teeth and tongue), those whose gap is darkest in its middle (the cavity of an open "
            "mouth, as an 'O' shows it), or both, each frame taking B's teeth or B's cavity as the driver's own "
            "mouth shows teeth or cavity there (`driver`, mouth.teeth_share). B's own is what the expression "
            "issue asked for; but celebrity photos at ~100 px between the ears show blurred teeth or none "
            "(Bush's widest are shouts, dark inside), and B's opening was a dark hole where the driver showed "
            "teeth: with A's own, Bush <- Obama's composite mouth-opening gain rose 0.81 -> 1.13 and its width "
            "0.68 -> 0.74 (docs/expression.md)")
        frame_min_gap: float = Field(0.04, ge=0, description="mouth_choice frame: the driver's own interior is "
                                     "drawn where A's inner lips are at least this many inter-ocular distances "
                                     "apart (and 2 px); closer, B's own lips close over the gap. dlib puts the inner "
                                     "lips of a closed mouth a little apart; 0.04 is 2 px at the 256² address's 50 px "
                                     "between the eyes, where the interior was tuned (mouth.from_frame)")
        frame_inset: float | None = Field(0.03, ge=0, description="mouth_choice frame: the driver's interior is "
                                          "taken 15 % of the gap inside A's inner-lip points (which sit on the lips' "
                                          "edge), but at most this many inter-ocular distances (null: no cap). Not in "
                                          "the paper: 15 % of a wide-open mouth at HD cut off both rows of teeth, "
                                          "which hang from the lips (docs/expression.md)")
        lip_shadow: float = Field(0.5, ge=0, le=1, description="mouth_choice frame: how dark the band drawn "
                                  "along B's lower lip inside the opening is at the lip (0: none; it fades over a "
                                  "tenth of the gap's height, mouth.lower_lip_shadow). The driver's interior is "
                                  "taken inside A's lips, which leaves out the dark where A's lower lip meets the "
                                  "tongue; without it a tongue meets B's lower lip pink on pink. Not in the paper: "
                                  "on the MEAD drives the face alone's mouth-opening gain rose 0.60 -> 0.70 "
                                  "(happy) and 0.69 -> 0.79 (surprised) (docs/expression.md)")
        mouth_sigma: float = Field(1.5, ge=0, description="mouth_choice driver: how much of B's teeth each frame "
                                   "shows, smoothed in time by a Gaussian of this many frames (0: each frame's own)")
        mouth_corners: Literal["driver", "mesh"] = Field(
            "driver", description="where the opening's two corners (B's inner-lip corners, iBUG 60 and 64) are "
            "drawn. `driver` (the default; not in the paper): B's own neutral place moved along the mouth as far "
            "as the driver's inner corners moved from theirs in this frame (mouth.frame_insets), so that a round "
            "'O' leaves lip at the corners; `mesh`: where the mesh moved them, which follows only the 49 "
            "fiducials: they stay near the outer corners and an 'O' opens as wide as the lips "
            "(docs/expression.md)")

    def render(self, puppet: Puppet, target: np.ndarray, pose: Pose, frame: np.ndarray) -> Rendered:
        """target is not used: the expression is already in ``puppet.mesh`` and ``puppet.appearance``."""
        if puppet.mesh is None:
            raise ValueError("the mesh3d renderer needs the puppet's 3D mesh; this puppet has none "
                             "(Puppet.mesh is None: run the 3D pipeline, or use the 2D renderer tps2d)")
        grid = puppet.appearance.shape[:2]
        if puppet.mesh.shape != (*grid, 3) or puppet.coverage.shape != grid:
            raise ValueError(f"puppet arrays disagree: mesh {puppet.mesh.shape}, appearance "
                             f"{puppet.appearance.shape}, coverage {puppet.coverage.shape}")
        h, w = frame.shape[:2]
        feather = self.params.feather
        out = np.full((h, w, 3), GREY, np.uint8)
        mask = np.zeros((h, w), np.float32)
        box, hit_uv, depth = surface_map(puppet.mesh, pose, (h, w), pad=int(np.ceil(3 * feather)) + 1)
        if box is None:
            return Rendered(rgb=out, mask=mask)
        x0, y0, x1, y1 = box
        texture = np.asarray(puppet.appearance, np.float32)
        finite = np.isfinite(texture).all(axis=2)
        seen = (enclosed(puppet.coverage >= self.params.min_coverage) & finite).astype(np.float32)
        if self.params.jaw_margin is not None and puppet.jaw is not None:
            seen *= above_jaw(puppet.jaw, seen.shape, self.params.jaw_margin)
        texture = np.where(finite[..., None], texture, 0).astype(np.float32)
        if self.params.rim == "skin":  # judged on B's neutral texture: the same rim in every frame
            judged = texture if puppet.neutral is None else np.asarray(puppet.neutral, np.float32)
            seen *= 1 - edge_not_skin(judged, seen, spared=_eyes_and_brows(puppet.fiducials, seen.shape))
        u, v = hit_uv[..., 0], hit_uv[..., 1]
        on = np.isfinite(depth)
        sampling = self.params.sampling
        if self.params.filter_texture:
            rgb = footprint_sample(texture, np.where(on, u, np.nan), np.where(on, v, np.nan), ~finite, sampling)
        else:
            rgb = texture_sample(texture, u, v, ~finite, sampling)
        part = cv2.remap(seen, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT) * on
        if feather > 0:
            part = cv2.GaussianBlur(part, (0, 0), feather) * (part > 0.5)
        mask[y0:y1, x0:x1] = part
        face = np.clip(rgb, 0, 255).round().astype(np.uint8)
        out[y0:y1, x0:x1] = np.where((part > 0)[..., None], face, out[y0:y1, x0:x1])
        if self.params.mouth and puppet.mouth is not None and puppet.lips is not None:
            corners = mouth.outer_corners(np.asarray(puppet.fiducials, np.float32))
            points = np.concatenate([mouth.apart(puppet.lips).astype(np.float32).reshape(-1, 2), corners])[None]
            xy, z = project(compose(np.asarray(puppet.mesh, np.float32), points)[0], pose)  # the mesh there
            curves, outer = xy[:-2].reshape(2, -1, 2), xy[-2:]
            if self.params.mouth_corners == "driver" and puppet.lip_insets is not None:
                curves = mouth.place_corners(curves, outer, puppet.lip_insets)
            if np.all(z > _NEAR):  # B's photos' gap to frame px at the lips (f / z); the driver's is in them
                to_frame = 1.0 if puppet.mouth_own else pose.camera[0, 0] / float(np.mean(z[:-2]))
                gap = puppet.mouth_gap * to_frame
                drawn = mouth.draw(out, mask, np.asarray(puppet.mouth, np.float32), curves, gap=gap,
                                   keep_rows=puppet.mouth_own, shadow=self.params.lip_shadow)
                if puppet.mouth_own:
                    return Rendered(rgb=out, mask=mask, own=drawn)
        return Rendered(rgb=out, mask=mask)


def _eyes_and_brows(fiducials: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: the eyes and brows of a face with 49 ``fiducials`` (49, 2) on a grid of ``shape``, each the
    hull of its points grown as composite.features_of grows A's."""
    points = np.full((68, 2), np.nan)
    points[list(IDX49)] = fiducials
    return features_of(points, shape, EYES) | features_of(points, shape, BROWS)


@hookimpl
def persona_register_backends(register):
    register(RaycastRender)

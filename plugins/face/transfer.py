"""Deformation transfer from driver to puppet with magnitude adjustment (paper Sec. 4, Fig. 3;
ALGORITHMS §10).

The driver's per-frame meshes ``M_D^t`` and their mean ``M̄_D`` are parametrised on the driver's
canonical grid, the puppet's base mesh ``M_P`` on the puppet's grid (all ``(H, W, 3)`` arrays of
(x, y, Z) in canonical px, ALGORITHMS §0). ``phi`` (puppet grid, ``(H, W, 2)``, channels (x, y))
sends the puppet pixel q to its driver pixel φ(q) (ALGORITHMS §7.3). Per frame, on the puppet
grid:

1. ``D̄(q) = M̄_D(φ(q))``, ``Δ(q) = M_D^t(φ(q)) - D̄(q)`` (bilinear samples);
2. the moved point ``D̄(q) + Δ(q)`` lands nearest to the driver vertex ``D̄(q')``; a KD-tree over
   the ``D̄(q)`` of all valid puppet pixels gives q' directly (no inverse of φ is needed) and is
   built once per driver sequence, not per frame;
3. ``Δ' = M_P(q') - M_P(q)`` is how far the puppet must move to reach the same feature, and
   ``f = Δ̂·Δ'`` the magnitude along the driver's direction ``Δ̂ = Δ/|Δ|``;
4. ``f* = denoise(f)`` (a ``denoise`` backend; the paper: Huber-ROF, TV weight 1, ε = 0.05; here
   TV weight 0.3 by default, see :class:`DeformationTransfer`);
5. ``M_P^t = M_P + Δ̂ f*``.

Methods (``TransferParams.method``):

* ``magnitude``: the paper's method above;
* ``normal``: ALGORITHMS §10.3's variant. The nearest-vertex construction only sees motion along
  the surface (a cheek bulging out lands on itself), so Δ is split at the driver's mean surface
  normal N into ``(Δ·N)N``, added directly, and the tangential rest, which is magnitude-adjusted.
  Not in the paper; it halves the error on synthetic faces (ALGORITHMS §10.3);
* ``ratio`` (default): the magnitude adjustment as a ratio, ``f = |Δ| r`` with ``r = (Δ̂·Δ') / (Δ̂·Δ'_D)``,
  where ``Δ'_D = D̄(q') - D̄(q)`` is the driver's own distance to the vertex the moved point lands
  on. The paper's f measures how far the puppet must move to reach the feature the driver's
  point reaches, but the nearest *vertex* of a curved surface lies short of a point moved off it,
  so f falls short even when puppet and driver are the same face (self-puppetry keeps 60-70 % of
  the lips' motion on real meshes, docs/expression.md). The ratio keeps the paper's comparison of
  the two faces' feature sizes and cancels that shortfall: r = 1 on the same face, the exact
  transfer. On synthetic faces it errs less than the paper's method in self-puppetry (0.02 px
  RMS with the default denoiser, 0.06 with the paper's TV weight 1, against 0.33) and on the
  moving eyelids of identity-dependent blinks (test_transfer).
  Not in the paper; r is clipped to [1/max_ratio, max_ratio], and r = 1 where the
  point lands on itself (Δ̂·Δ'_D under half a pixel, a grid step's rounding);
* ``naive``: ``M_P^t = M_P + Δ``, the unadjusted transfer, for comparison.

Small motions (ALGORITHMS §10.3, §16.10): where |Δ| is below half the spacing of the driver
vertices the nearest vertex is the point itself, f = 0 and Δ̂ is noise. With
``small_motion = δ > 0`` the displacement is ``w Δ̂ f* + (1 - w) Δ`` with ``w = min(1, |Δ|/δ)``,
so that motions well under a pixel are passed on as they are; δ = 0 is the paper's formula.

Validity: a puppet pixel takes part if it is in the puppet mask, its ``M_P`` is finite, and φ(q)
falls inside the driver's grid with every bilinear corner of non-zero weight in the driver mask
and finite in ``M̄_D``. Other pixels keep ``M_P`` (they do not move). A frame whose mesh is not
finite at a valid pixel's corners gives that pixel no data: it is filled by the denoiser and moved
along ``Δ̂ = 0``, i.e. not at all.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numba
import numpy as np
from pydantic import Field
from scipy.ndimage import map_coordinates
from scipy.spatial import cKDTree

from ..base import Params
from ..kinds import DenoiseBackend, FlowBackend
from .eyes import SHUT_AT, SHUT_FROM, opened
from .mesh import lip_split, rim_points
from .mouth import outer_corners
from .subspace import project
from .template import IDX49
from .warp import FACING, TpsWarp, compose, pin, tps_map, tps_weights

#: the TV weight of the default denoiser (the paper's is 1; see DeformationTransfer)
DEFAULT_TV_WEIGHT = 0.3

#: Δ̂·Δ'_D (canonical px) below which the driver's point counts as landing on itself (``ratio``)
_LANDS = 0.5

__all__ = ["DeformationTransfer", "FiducialFollow", "TransferFrame", "TransferParams", "below_mouth", "correspondence",
           "fold_depths", "grid_normals", "lower_lip", "transfer_sequence", "unfolded"]


class TransferParams(Params):
    """Options of :class:`DeformationTransfer`."""

    method: Literal["magnitude", "ratio", "normal", "naive"] = Field(
        "ratio", description="'magnitude': the paper's magnitude-adjusted transfer M_P + Δ̂ f*; "
        "'ratio': f = |Δ| (Δ̂·Δ')/(Δ̂·Δ'_D), the puppet's distance to the landing vertex over the "
        "driver's (not in the paper; exact in self-puppetry); "
        "'normal': the normal part (Δ·N)N added directly and only the tangential part adjusted "
        "(ALGORITHMS §10.3, not in the paper); 'naive': M_P + Δ")
    max_ratio: float = Field(3.0, gt=1, description="'ratio' only: r is clipped to [1/max_ratio, max_ratio]")
    fiducials: float = Field(
        1.0, ge=0, le=1, description="how far B's transferred meshes are then moved towards the "
        "retargeted fiducials (the driver's landmark offsets on B's face, the 2D renderer's targets): "
        "1 = their fiducials land on them, 0 = the paper's transfer alone (not in the paper; "
        ":class:`FiducialFollow`)")
    fiducial_lambda: float = Field(0.1, ge=0, description="λ of the smoothing TPS that spreads the "
                                   "fiducials' misses over the face (Eq. 1, canonical px)")
    fiducial_sigma: float = Field(0.5, ge=0, le=10, description="σ in frames of the Gaussian smoothing "
                                  "of the retargeted fiducials over time (dlib's landmarks jitter; σ = 1 "
                                  "halves speech's 5 Hz at 25 fps: on Bush driven by Obama the targets' mouth "
                                  "gain is 0.92 unsmoothed, 0.89 at σ 0.5, 0.79 at 1)")
    corner_reach: float = Field(
        30.0, ge=0, description="canonical px beyond each mouth corner over which the skin is carried "
        "sideways at least a share of the corner's way, fading to none at that distance; skin the transfer "
        "already moves further is left (0: off, the paper; :class:`FiducialFollow`). 30 raised Bush <- "
        "Obama's face-alone mouth-width gain 0.70 -> 0.77 and the self-reenactment's 0.70 -> 0.74, and left the "
        "woman's drives within 0.01, which the two-sided hold of an earlier run lowered (Powell 0.72 -> 0.62): "
        "docs/expression.md, an earlier run")
    brow_hold: float = Field(
        0.5, ge=0, lt=1, description="share of the way from each upper lid up to its brow (0: off, the follower "
        "alone) above which the skin goes no further down than the brow as the eye shuts: a lid that shuts does "
        "not drag the brow down onto it. 0.5 took the frontal man <- fringe woman's face-alone eye gain 0.25 -> 0.36 "
        "and left the self-reenactments within 0.01 dB (:class:`FiducialFollow`, docs/expression.md)")
    split_lips: bool = Field(
        True, description="the follower parts B's inner lips as a step at the line where they meet, each read on "
        "its own side of it, and spreads the rest of the misses with its spline (not in the paper; false: the "
        "spline alone, which cannot part points a texel apart: a puppet whose photos keep the mouth shut opened "
        "its inner lips 0.34 as far as their targets; :class:`FiducialFollow`, docs/expression.md)")
    unfold: bool = Field(
        True, description="below the mouth's middle, a column of B's mesh that folds (the lower lip dropped over "
        "the skin under it, which the renderer drew as a ragged edge) is made to run down again: the lip's body "
        "squeezed over its outer edge, which stays on its target, and the skin under the lip into a band under it "
        "(:func:`unfolded`; not in the paper; on the example drives folds reached 13 canonical px, none after: "
        "docs/expression.md)")
    unfold_step: float = Field(0.3, ge=0, le=1, description="with unfold: the squeezed skin's band, canonical px a "
                               "row (0: laid flat on a line of no area, which met the chin with a hard, stepped "
                               "edge)")
    small_motion: float = Field(
        0.3, ge=0, description="δ in canonical px: the displacement is w Δ̂ f* + (1 - w) Δ with "
        "w = min(1, |Δ|/δ), so that sub-pixel motions, whose nearest vertex is the point itself, pass "
        "unadjusted (ALGORITHMS §10.3 suggests 0.3; with 'normal', Δ is the tangential part); 0 gives "
        "the paper's formula exactly")


@dataclass(frozen=True)
class TransferFrame:
    """One transferred frame, on the puppet grid.

    mesh : (H, W, 3) float64 — M_P^t (equal to M_P off the valid pixels)
    displacement : (H, W, 3) float64 — M_P^t - M_P (0 off the valid pixels)
    f, f_star : (H, W) float64 — the raw and denoised magnitudes (NaN off the valid pixels;
        for ``naive``, |Δ| and the same)
    valid : (H, W) bool — pixels that took part (see the module docstring)
    """

    mesh: np.ndarray
    displacement: np.ndarray
    f: np.ndarray
    f_star: np.ndarray
    valid: np.ndarray


def _check_mesh(mesh, name: str, shape: tuple[int, int] | None = None) -> np.ndarray:
    m = np.asarray(mesh, dtype=np.float64)
    if m.ndim != 3 or m.shape[2] != 3:
        raise ValueError(f"transfer: {name} must have shape (H, W, 3), got {m.shape}")
    if shape is not None and m.shape[:2] != shape:
        raise ValueError(f"transfer: {name} must have shape {shape + (3,)}, got {m.shape}")
    if min(m.shape[:2]) < 2:
        raise ValueError(f"transfer: {name} must be at least 2 x 2, got {m.shape}")
    return m


def _check_mask(mask, name: str, shape: tuple[int, int]) -> np.ndarray:
    if mask is None:
        return np.ones(shape, bool)
    m = np.asarray(mask)
    if m.shape != shape:
        raise ValueError(f"transfer: {name} must have shape {shape}, got {m.shape}")
    if m.dtype != bool:
        raise TypeError(f"transfer: {name} must be bool, got {m.dtype}")
    return m


def grid_normals(mesh: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Unit normals (H, W, 3) of a grid-parametrised mesh, oriented towards the camera (n_z <= 0).

    ``normalize(∂M/∂v × ∂M/∂u)`` (= (Z_x, Z_y, -1)/|.| for M = (u, v, Z), ALGORITHMS §0), with
    central differences between mask neighbours and one-sided ones at the mask's edge; NaN where a
    pixel has no neighbour along an axis or is off the mask.
    """
    m = mask & np.all(np.isfinite(mesh), axis=2)
    derivs = []
    for axis in (1, 0):  # ∂/∂u (columns), then ∂/∂v (rows)
        fwd = np.full(mesh.shape, np.nan)
        bwd = np.full(mesh.shape, np.nan)
        both = [slice(None)] * 2
        a, b = list(both), list(both)
        a[axis], b[axis] = slice(None, -1), slice(1, None)
        a, b = tuple(a), tuple(b)
        ok = m[a] & m[b]
        diff = np.where(ok[..., None], mesh[b] - mesh[a], np.nan)
        fwd[a] = diff  # M(x+1) - M(x), stored at x
        bwd[b] = diff  # M(x) - M(x-1), stored at x
        d = np.where(np.isnan(fwd), bwd, np.where(np.isnan(bwd), fwd, 0.5 * (fwd + bwd)))
        derivs.append(d)
    n = np.cross(derivs[1], derivs[0])
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    n = np.where(n[..., 2:3] > 0, -n, n)
    n[~m] = np.nan
    return n


@numba.njit(cache=True, nogil=True)
def _bilinear3(flat, idx, wts):
    """Σ_c wts[k, c] flat[idx[k, c]] for every k: bilinear samples (N, 3) of ``flat`` (P, 3) from
    the four corners ``idx`` (N, 4) with weights ``wts`` (N, 4). Ten times faster than the numpy
    gathers, which copy each corner's rows."""
    n = idx.shape[0]
    out = np.empty((n, 3))
    for k in range(n):
        for c in range(3):
            out[k, c] = (flat[idx[k, 0], c] * wts[k, 0] + flat[idx[k, 1], c] * wts[k, 1]
                         + flat[idx[k, 2], c] * wts[k, 2] + flat[idx[k, 3], c] * wts[k, 3])
    return out


class DeformationTransfer:
    """Transfer of one driver sequence onto one puppet; everything that does not depend on the
    frame (the sampling weights of φ, ``D̄``, the KD-tree, the normals) is built once here.

    driver_mean : (Hd, Wd, 3) — M̄_D, the mean of the *same* per-frame meshes that will be passed
        to :meth:`apply` (ALGORITHMS §10.3: another reconstruction's mean leaks its offsets into Δ)
    phi : (H, W, 2) — φ, puppet pixel -> driver pixel (x, y) on the driver grid
    puppet_mean : (H, W, 3) — M_P, the puppet's base (average) mesh
    puppet_mask : (H, W) bool; driver_mask : (Hd, Wd) bool or None (all of the driver grid)
    params : TransferParams or dict; denoiser : a ``denoise`` backend, used by every method but
        ``naive``. The default is huber_rof with TV weight 0.3 (the paper's is 1, in units it does not
        state), the paper's ε = 0.05, and ``outside='exclude'``. TV shrinks a feature of radius R
        by about 2w/R px, which takes most of a thin eyelid's 1-3 px: on Bush driven by Obama, B's
        meshes keep eye openness 0.73 of the driver's with w = 0.3 against 0.65 with w = 1 (mouth
        0.64 / 0.60), and on synthetic faces w = 0.3 errs less than w = 1 (self-puppetry 0.02 against
        0.06 px RMS; the moving eyelids of test_transfer's blinks no worse). ``outside='exclude'``:
        f* is only read on the valid pixels, and leaving the pixels without
        data out of the problem makes it converge linearly (about 60 iterations to the 1e-3 px
        stopping rule) where inpainting them needs thousands. On synthetic self-puppetry the two
        converged solutions differ by 0.01-0.03 px RMS in f* on the valid pixels, and the
        transferred meshes' errors by under 0.002 px.
    """

    def __init__(self, driver_mean, phi, puppet_mean, puppet_mask, driver_mask=None, *,
                 params: TransferParams | dict | None = None, denoiser: DenoiseBackend | None = None):
        self.params = params if isinstance(params, TransferParams) else TransferParams.model_validate(params or {})
        if denoiser is None:
            from ..builtin.denoise import HuberROFDenoise

            denoiser = HuberROFDenoise({"weight": DEFAULT_TV_WEIGHT, "outside": "exclude"})
        self.denoiser = denoiser
        dmean = _check_mesh(driver_mean, "driver_mean")
        self.driver_shape = dmean.shape[:2]
        self.puppet_mean = _check_mesh(puppet_mean, "puppet_mean")
        self.shape = self.puppet_mean.shape[:2]
        phi = np.asarray(phi, dtype=np.float64)
        if phi.shape != self.shape + (2,):
            raise ValueError(f"transfer: phi must have shape {self.shape + (2,)} like puppet_mean, got {phi.shape}")
        pmask = _check_mask(puppet_mask, "puppet_mask", self.shape)
        dmask = _check_mask(driver_mask, "driver_mask", self.driver_shape)
        dmask = dmask & np.all(np.isfinite(dmean), axis=2)

        hd, wd = self.driver_shape
        x, y = phi[..., 0], phi[..., 1]
        valid = (pmask & np.all(np.isfinite(self.puppet_mean), axis=2) & np.isfinite(x) & np.isfinite(y)
                 & (x >= 0) & (x <= wd - 1) & (y >= 0) & (y <= hd - 1))
        q = np.flatnonzero(valid)
        xq, yq = x.ravel()[q], y.ravel()[q]
        x0 = np.minimum(np.floor(xq).astype(np.int64), wd - 2)
        y0 = np.minimum(np.floor(yq).astype(np.int64), hd - 2)
        fx, fy = xq - x0, yq - y0
        idx = np.stack([y0 * wd + x0, y0 * wd + x0 + 1, (y0 + 1) * wd + x0, (y0 + 1) * wd + x0 + 1], axis=1)
        wts = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1)
        used = wts > 0
        ok = np.all(dmask.ravel()[idx] | ~used, axis=1)
        # corners of zero weight point at the heaviest corner, so that NaN off the mask cannot leak in
        idx = np.where(used, idx, idx[np.arange(len(idx)), np.argmax(wts, axis=1)][:, None])
        q, idx, wts = q[ok], idx[ok], wts[ok]
        valid = np.zeros(self.shape, bool)
        valid.ravel()[q] = True
        self.valid = valid
        self._q, self._idx, self._wts = q, idx, wts

        self.driver_at_phi = self._sample(dmean)  # D̄(q), (N, 3)
        self._mp = self.puppet_mean.reshape(-1, 3)[q]  # M_P(q), (N, 3)
        # |Δ| below half the distance to the nearest other vertex cannot reach another vertex:
        # those points need no query (their q' is q itself)
        self._reach = np.full(len(q), np.inf)
        if self.params.method != "naive" and len(q) > 1:
            self.tree = cKDTree(self.driver_at_phi)
            self._reach = 0.5 * self.tree.query(self.driver_at_phi, k=2)[0][:, 1]
        if self.params.method == "normal":
            n = self._sample(np.nan_to_num(grid_normals(dmean, dmask)))
            self._normals = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    def _sample(self, grid: np.ndarray) -> np.ndarray:
        """Bilinear samples (N, 3) of a driver-grid array (Hd, Wd, 3) at φ(q) of the valid pixels."""
        flat = np.ascontiguousarray(grid.reshape(self.driver_shape[0] * self.driver_shape[1], 3))
        return _bilinear3(flat, self._idx, self._wts)

    def apply(self, driver_mesh) -> TransferFrame:
        """Transfer one driver frame ``M_D^t`` (Hd, Wd, 3) onto the puppet (see the module docstring)."""
        mesh = _check_mesh(driver_mesh, "driver_mesh", self.driver_shape)
        h, w = self.shape
        q = self._q
        delta = self._sample(mesh) - self.driver_at_phi  # Δ(q), (N, 3)
        good = np.all(np.isfinite(delta), axis=1)
        delta[~good] = 0.0
        method = self.params.method
        f_img = np.full((h, w), np.nan)
        fs_img = np.full((h, w), np.nan)
        if method == "naive":
            disp = delta
            f_img.ravel()[q] = np.linalg.norm(delta, axis=1)
            fs_img = f_img.copy()
        else:
            normal_part = 0.0
            if method == "normal":
                normal_part = np.sum(delta * self._normals, axis=1, keepdims=True) * self._normals
                delta = delta - normal_part
            size = np.linalg.norm(delta, axis=1)
            direction = delta / np.where(size > 0, size, 1.0)[:, None]  # Δ̂ (0 where Δ = 0)
            hit = np.arange(len(q))
            moving = np.flatnonzero(size >= self._reach)
            if len(moving):
                hit[moving] = self.tree.query(self.driver_at_phi[moving] + delta[moving], workers=1)[1]
            f = np.einsum("ij,ij->i", direction, self._mp[hit] - self._mp)  # f = Δ̂·Δ'
            if method == "ratio":  # f = |Δ| (Δ̂·Δ') / (Δ̂·Δ'_D)
                own = np.einsum("ij,ij->i", direction, self.driver_at_phi[hit] - self.driver_at_phi)
                lands = own > _LANDS
                r = np.where(lands, f / np.where(lands, own, 1.0), 1.0)
                f = size * np.clip(r, 1 / self.params.max_ratio, self.params.max_ratio)
            f_img.ravel()[q[good]] = f[good]
            data = np.zeros((h, w), bool)
            data.ravel()[q[good]] = True
            f_star = np.asarray(self.denoiser.denoise(np.nan_to_num(f_img), data), dtype=np.float64).ravel()[q]
            fs_img.ravel()[q] = f_star
            adjusted = direction * f_star[:, None]
            delta_s = self.params.small_motion
            if delta_s > 0:
                wgt = np.minimum(size / delta_s, 1.0)[:, None]
                adjusted = wgt * adjusted + (1 - wgt) * delta
            disp = adjusted + normal_part
        displacement = np.zeros((h, w, 3))
        displacement.reshape(-1, 3)[q] = disp
        return TransferFrame(mesh=self.puppet_mean + displacement, displacement=displacement, f=f_img,
                             f_star=fs_img, valid=self.valid.copy())

    def __call__(self, driver_mesh) -> np.ndarray:
        """M_P^t (H, W, 3) for the driver frame ``M_D^t``."""
        return self.apply(driver_mesh).mesh


#: the outer mouth corners among the 49 fiducials (iBUG 48 and 54)
_MOUTH_CORNERS = (31, 37)

#: per eye, its upper lid's points and its brow's among the 49 fiducials (iBUG 37, 38 under 17-21; 43, 44
#: under 22-26)
_LIDS_BROWS = (((20, 21), tuple(range(0, 5))), ((26, 27), tuple(range(5, 10))))


def _under_brows(fiducials: np.ndarray, share: float) -> tuple[np.ndarray, np.ndarray]:
    """Points ``share`` of the way from each upper lid's point up to its brow, straight above it (two an
    eye, the face's right eye's first), and the (k, 49) weights that give each the brow's motion there
    (linear along the brow, between the two of its points the lid's point lies between)."""
    points, weights = [], []
    for lids, brow in _LIDS_BROWS:
        xs = fiducials[list(brow), 0]
        order = np.argsort(xs)
        for lid in lids:
            x = fiducials[lid, 0]
            w = np.zeros(len(fiducials))
            at = np.interp(x, xs[order], np.arange(len(brow)))  # fractional index along the brow
            i = min(int(at), len(brow) - 2)
            w[brow[order[i]]], w[brow[order[i + 1]]] = 1 - (at - i), at - i
            points.append(fiducials[lid] + share * (w @ fiducials - fiducials[lid]) * [0, 1])
            weights.append(w)
    return np.array(points), np.array(weights)


def own_sides(fiducials: np.ndarray) -> np.ndarray:
    """(49, 2) the ``fiducials`` with each of the inner lips' facing points (iBUG 61/67, 62/66, 63/65) moved
    straight up or down, if it must, onto the nearest texel row wholly on its own side of the line where the lips
    meet (the pair's middle; :func:`persona.plugins.face.mesh.lip_split` moves a texel with the lower lip by the
    share of it below that line): the upper lip's onto the lowest row at least half a texel above it, the lower
    lip's onto the highest row at least half a texel below it. Lips further apart than that are as they are."""
    out = np.array(fiducials, np.float64, copy=True)
    for upper, lower in FACING[4:]:
        middle = (out[upper, 1] + out[lower, 1]) / 2
        out[upper, 1] = min(out[upper, 1], np.floor(middle - 0.5))
        out[lower, 1] = max(out[lower, 1], np.ceil(middle + 0.5))
    return out


class FiducialFollow:
    """B's transferred meshes moved so that their fiducials land on per-frame targets (not in the
    paper; ``TransferParams.fiducials``).

    The transfer carries the driver's motion through its meshes, and every step on the way (the
    driver's flow and shading, the correspondence, the denoiser) loses some: on the example drives
    B's meshes kept 0.57-0.79 of the driver's eye motion and 0.58-0.80 of its mouth's
    (docs/expression.md). The retargeted fiducials (:func:`persona.plugins.face.warp.retarget`: B's
    neutral plus the driver's landmark offsets, scaled by the two faces' proportions) say where B's
    lids, lips and brows should be. Per frame, the misses of B's fiducials (the mesh's (x, y) at
    B's mean fiducials' texels) are spread over the face by a smoothing TPS that holds the rim of
    B's mask still, and added to the mesh's (x, y); depth is left to the transfer.

    fiducials : (49, 2) B's mean fiducials on the canonical grid; mask : (H, W) bool, B's face;
    lam : the spline's λ; spacing : px between the rim's still points; step : the spline is
    evaluated on every ``step``-th pixel (1: the inner and outer lips are 3-5 px apart and move
    apart, which a coarser grid blurs); corner_reach : px beyond each mouth corner (0: none) over
    which the skin moves sideways with the corner. The transfer's sideways motion falls to about
    half the corner's 15 px beyond it, so a narrowing mouth left the end of B's lip line behind,
    where dlib reads the corner (docs/expression.md). Two points on the line from the mouth's centre
    through each corner, a third and two thirds of the reach out, are moved sideways by
    (1 - distance / reach) of what separates their motion from the corner's, but only where that
    carries them further the corner's way than the follower alone would (which they otherwise keep,
    sideways and down): where the transfer already pulls the cheeks in further than the corners, as in
    an "O", holding them back to the corner's share stretched B's lip line outwards.
    brow_hold : share of the way from each upper lid's point up to its brow (0: none). A lid that comes
    down by a whole eye's height drags the skin above it down with it, over the short distance the
    smooth spline has there: on a face whose brows sit close over the eyes, the brow's lower half came
    down onto the shut lid, which then read (to dlib and to a viewer) as the upper lid of an eye still
    open. A point that far up, above each of the lid's two points, moves as the follower alone would
    move it, less the share of what it would go further down than the brow above it that the eye shuts:
    none while the target's lids are at least eyes.SHUT_FROM of their neutral distance apart (the mesh is
    the follower's alone), all of it at eyes.SHUT_AT and below.
    split_lips : the lips' parting as a step (:func:`persona.plugins.face.mesh.lip_split`, as the driver's
    meshes have it) and the spline through the rest of the misses. B's inner lips lie as far apart as B's photos
    hold them: a texel or less for a puppet whose photos keep the mouth shut, and a smooth spline cannot move
    two points so close tens of texels apart (on the woman with a fringe, B's meshes opened the inner lips 0.34
    as far as their targets, with a notch in the lower lip). Each inner lip is read, and held by the spline, on
    the first texel row wholly on its own side of the line where the lips meet (:func:`own_sides`), where the
    step moves a texel with the lower lip in full or not at all.
    """

    def __init__(self, fiducials: np.ndarray, mask: np.ndarray, *, lam: float = 0.1, spacing: int = 12,
                 step: int = 1, corner_reach: float = 0.0, brow_hold: float = 0.0, split_lips: bool = False):
        self.fiducials = np.asarray(fiducials, np.float64)
        self.split_lips = split_lips
        self._read = own_sides(self.fiducials) if split_lips else self.fiducials  # where each fiducial is read
        self._rim = rim = rim_points(mask, spacing)
        self._still = np.zeros((len(rim), 2))
        # with split_lips: the texels between the mouth's outer corners, the only ones the parting moves
        left, right = outer_corners(self.fiducials)[:, 0]
        ys, xs = np.mgrid[0:mask.shape[0], 0:mask.shape[1]]
        self._mouth = (xs > left) & (xs < right)
        self._mouth_points = np.stack([xs[self._mouth], ys[self._mouth]], axis=1)
        # with corner_reach: points beyond each mouth corner, each with its corner and how much of
        # the corner's sideways motion it takes
        self._beyond, self._corner, self._fade = np.zeros((0, 2)), np.zeros(0, int), np.zeros(0)
        if corner_reach > 0:
            centre = self.fiducials[list(_MOUTH_CORNERS)].mean(axis=0)
            steps = corner_reach * np.array([1, 2]) / 3
            out = [(self.fiducials[c] + d * (self.fiducials[c] - centre) / np.linalg.norm(self.fiducials[c] - centre),
                    c, 1 - d / corner_reach) for c in _MOUTH_CORNERS for d in steps]
            self._beyond, self._corner, self._fade = (np.array(v) for v in zip(*out))
            # the sideways move the follower gives those points without them (one-sided reach, below)
            self._free = tps_weights(np.concatenate([self._read, rim]), self._beyond, lam=lam)
        self._above, self._brows = (_under_brows(self.fiducials, brow_hold) if brow_hold > 0
                                    else (np.zeros((0, 2)), np.zeros((0, len(self.fiducials)))))
        # the move the follower gives those points without them
        self._free_above = tps_weights(np.concatenate([self._read, self._beyond, rim]), self._above, lam=lam) \
            if len(self._above) else None
        self.warp = TpsWarp(np.concatenate([self._read, self._beyond, self._above, rim]), np.asarray(mask).shape,
                            lam=lam, step=step)

    def _shutting(self, target: np.ndarray) -> np.ndarray:
        """(2,) how far each eye of the ``target`` fiducials shuts, 0 at SHUT_FROM of its neutral's opening and
        above, 1 at SHUT_AT and below (0 where the target has a NaN)."""
        shut = (SHUT_FROM - opened(target, self.fiducials)) / (SHUT_FROM - SHUT_AT)
        return np.nan_to_num(np.clip(shut, 0.0, 1.0))

    @staticmethod
    def moved(mesh: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(n, 2) where a mesh (H, W, 3) has moved the texels at ``points`` (x, y; bilinear)."""
        xy, rows_cols = np.nan_to_num(np.asarray(mesh, np.float64)[..., :2]), points[:, ::-1].T
        return np.stack([map_coordinates(xy[..., c], rows_cols, order=1, mode="nearest") for c in (0, 1)], axis=1)

    def landmarks(self, mesh: np.ndarray) -> np.ndarray:
        """(49, 2) where a mesh (H, W, 3) has moved B's fiducials (bilinear in the texels)."""
        return self.moved(mesh, self.fiducials)

    def __call__(self, mesh: np.ndarray, target: np.ndarray, weight: float = 1.0) -> np.ndarray:
        """The mesh (H, W, 3) moved ``weight`` of the way to fiducials at ``target`` (49, 2); a
        target with a NaN moves nothing."""
        now = self.moved(mesh, self._read)
        miss = weight * (np.asarray(target, np.float64) + (self._read - self.fiducials) - now)
        miss[~np.isfinite(miss).all(axis=1)] = 0.0
        still, parted = self._still, None
        if self.split_lips:  # the lips' parting as a step; the spline takes what it leaves, the rim held against it
            parted, at_read, at_rim = (lip_split(self.fiducials, miss, points)
                                       for points in (self._mouth_points, self._read, self._rim))
            miss, still = miss - at_read, -at_rim
        beyond = np.zeros((0, 2))  # without corner_reach there are no points beyond the corners
        if len(self._beyond):  # what the follower alone would move them by; sideways, at least a share of the corner's
            beyond = self._free @ np.concatenate([miss, still])
            corner = now[self._corner] + miss[self._corner] - self.fiducials[self._corner]
            shift = self.moved(mesh, self._beyond) - self._beyond
            held = self._fade * (corner[:, 0] - shift[:, 0])
            # where the skin already goes further the corner's way (the woman's "O" pulls the cheeks in), it is left
            beyond[:, 0] = np.where((held - beyond[:, 0]) * corner[:, 0] > 0, held, beyond[:, 0])
        above = np.zeros((0, 2))  # without brow_hold there are no points above the lids
        if len(self._above):  # as the follower alone would move them, but held up to the brow as the eye shuts
            above = self._free_above @ np.concatenate([miss, beyond, still])
            below = np.maximum(above[:, 1] - self._brows @ miss[:, 1], 0.0)  # how far further down than the brow
            above[:, 1] -= np.repeat(self._shutting(target), 2) * below
        out = np.array(mesh, np.float64, copy=True)
        out[..., :2] += self.warp.map(np.concatenate([miss, beyond, above, still]))
        if parted is not None:
            out[self._mouth, :2] += parted
        return out


def below_mouth(mask: np.ndarray, fiducials: np.ndarray) -> np.ndarray:
    """(H, W) bool: B's face ``mask`` from the middle of its mouth down (the mean row of the inner lips' middle
    points, iBUG 62 and 66, among B's 49 mean ``fiducials``)."""
    middle = np.asarray(fiducials, np.float64)[[IDX49.index(i) for i in (62, 66)], 1].mean()
    out = np.array(mask, bool, copy=True)
    out[: int(np.ceil(middle))] = False
    return out


def fold_depths(mesh: np.ndarray, below: np.ndarray, step: float = 0.0) -> np.ndarray:
    """(H, W): how far (canonical px) each texel of ``below`` (H, W) bool must move down its column of the
    mesh (H, W, 3) to lie at least ``step`` px per row below every texel over it (0: not above any of
    them, where the mesh folds); 0 where its rows already lie that far apart, and outside ``below``."""
    y = np.asarray(mesh, np.float64)[..., 1]
    inside = np.asarray(below, bool) & np.isfinite(y)
    rows = step * np.arange(y.shape[0], dtype=np.float64)[:, None]
    least = np.maximum.accumulate(np.where(inside, y - rows, -np.inf), axis=0) + rows
    return np.where(inside, least - np.where(inside, y, 0.0), 0.0)


def lower_lip(below: np.ndarray, fiducials: np.ndarray) -> np.ndarray:
    """(2, W): the row (canonical px, fractional) of B's inner and of its outer lower lip in each column of
    ``below`` (:func:`below_mouth`), the lines through its mean ``fiducials`` iBUG 48, 67-65, 54 and 48, 59-55, 54;
    NaN beside the mouth. The rows between them are the lower lip's body. The inner row is never above the
    column's first row of ``below``: a puppet whose lips meet within a texel has its inner lower lip on the row
    the upper lip's texels part from, which moves with neither lip in full (mesh.lip_split)."""
    below = np.asarray(below, bool)
    cols = np.arange(below.shape[1], dtype=np.float64)
    out = np.full((2, below.shape[1]), np.nan)
    for k, line in enumerate(((48, 67, 66, 65, 54), (48, 59, 58, 57, 56, 55, 54))):
        points = np.asarray(fiducials, np.float64)[[IDX49.index(i) for i in line]]
        points = points[np.argsort(points[:, 0], kind="stable")]  # np.interp needs them left to right
        out[k] = np.interp(cols, points[:, 0], points[:, 1], left=np.nan, right=np.nan)
    first = np.where(below.any(axis=0), below.argmax(axis=0), 0)
    out[0] = np.where(np.isfinite(out[0]), np.maximum(out[0], first), np.nan)
    return out


def _lip_rows(below: np.ndarray, lip: np.ndarray) -> np.ndarray:
    """(H, W) bool: the texels of ``below`` between the lower lip's inner and outer rows ``lip`` (:func:`lower_lip`)."""
    rows = np.arange(below.shape[0], dtype=np.float64)[:, None]
    with np.errstate(invalid="ignore"):
        return np.asarray(below, bool) & (rows >= lip[0]) & (rows <= lip[1])


def _row_at(column: np.ndarray, row: float) -> float:
    """A column's value at a fractional ``row``, linear between its two rows."""
    low = int(np.floor(row))
    return float(column[low] + (row - low) * (column[min(low + 1, len(column) - 1)] - column[low]))


def _evened(y: np.ndarray, below: np.ndarray, lip: np.ndarray, step: float) -> np.ndarray:
    """The rows' heights ``y`` (H, W) with, in each column, the rows of ``below`` between the lower lip's inner
    and outer rows ``lip`` (2, W) spread evenly between where those two lines lie (read between rows, so that
    neighbouring columns agree); as they were in a column whose lines lie closer than ``step`` px a row."""
    out = np.array(y, np.float64, copy=True)
    inside = _lip_rows(below, lip)
    for c in np.flatnonzero(inside.sum(axis=0) > 1):
        top, edge = lip[:, c]
        ends = _row_at(y[:, c], top), _row_at(y[:, c], edge)
        if ends[1] - ends[0] >= step * (edge - top):
            rows = np.flatnonzero(inside[:, c])
            out[rows, c] = ends[0] + (ends[1] - ends[0]) * (rows - top) / (edge - top)
    return out


def unfolded(mesh: np.ndarray, below: np.ndarray, step: float = 0.3, lip: np.ndarray | None = None) -> np.ndarray:
    """The mesh (H, W, 3) with no texel of ``below`` (H, W) bool, the face below the mouth's middle, drawn
    over by one above it in its column.

    The transfer carries the driver's lower lip down with its own magnitude and the skin below with
    smaller ones, and the fiducial follower pulls B's lower lip to its target with the rim held still:
    where the lip drops further than the skin under it, the mesh folds, the lip's texels over the
    chin's, and the renderer draws the overlap as a ragged edge under the lip and along the chin (on
    Powell <- woman up to 13 canonical px deep; docs/expression.md). A jaw does not fold.

    First, with ``lip`` (2, W), the rows of the lower lip's inner and outer edges (:func:`lower_lip`): the
    follower puts those edges on their targets, but its smooth correction added to the transfer's uneven drop
    inside the lip can carry the lip's middle rows below its outer edge. The lip's rows are spread evenly
    between its two edges, which stay where the follower put them, so the lip is drawn as the texture has
    it. Squeezed instead into a band ``step`` px a row over the edge, the lip was drawn as its top rows (the
    wet inside of the lip) stretched into pale streaks over most of its height and the rest pressed into a
    line (a self-reenactment's "O", docs/expression.md); pushed down with the chin, the edge left its
    target by up to 5 px on Bush <- man with glasses and the lip was drawn half as tall again. The band is
    kept for a column whose edges lie too close to spread the lip between them. Then, in a column that
    still folds, the lip keeps its drop and the skin that was under it is squeezed into a band ``step`` px
    a row below it (:func:`fold_depths`), down to where the column's own rows run lower again; laid on a
    line of no area (``step`` 0), it met the chin under it with a hard, stepped edge. A column folded by
    d px takes min(d, 1) of the band and the rest of that line, so the band fades out beside a fold; a
    column that does not fold, however squeezed, is not touched, nor are texels above the mouth or outside
    ``below`` (:func:`below_mouth`)."""
    out = np.array(mesh, np.float64, copy=True)
    if lip is not None:
        out[..., 1] = _evened(out[..., 1], below, lip, step)
        # where that cannot be, the same rule as below read from the bottom up: each lip texel at least step a
        # row over those below
        out[..., 1] -= fold_depths(-out[::-1], _lip_rows(below, lip)[::-1], step)[::-1]
    flat = fold_depths(out, below)
    share = np.clip(flat.max(axis=0), 0, 1)  # per column: how far it folds, up to a pixel
    if share.any():  # most frames do not fold: nothing to move
        out[..., 1] += flat + share * (fold_depths(out, below, step) - flat)  # both rise down the column: so does this
    return out


def transfer_sequence(driver_meshes, phi, puppet_mean, puppet_mask, driver_mask=None, *,
                      params: TransferParams | dict | None = None,
                      denoiser: DenoiseBackend | None = None) -> np.ndarray:
    """M_P^t (T, H, W, 3) for every driver mesh ``M_D^t`` of ``driver_meshes`` (T, Hd, Wd, 3),
    with ``M̄_D`` their mean (the paper's "average mesh over the entire frame sequence")."""
    meshes = np.asarray(driver_meshes, dtype=np.float64)
    if meshes.ndim != 4 or len(meshes) == 0:
        raise ValueError(f"transfer: driver_meshes must have shape (T, H, W, 3) with T >= 1, got {meshes.shape}")
    t = DeformationTransfer(meshes.mean(axis=0), phi, puppet_mean, puppet_mask, driver_mask, params=params,
                            denoiser=denoiser)
    return np.stack([t(m) for m in meshes])


def correspondence(puppet_average: np.ndarray, puppet_mask: np.ndarray, driver_basis: np.ndarray,
                   flow: FlowBackend, guide: np.ndarray | None = None) -> np.ndarray:
    """φ (H, W, 2): for each puppet pixel, the driver pixel (x, y) that corresponds (ALGORITHMS §7.3).

    The puppet's 2D average A_P (H, W, 3, 0-255) projected onto the driver's basis (k, H, W, 3)
    keeps A_P's lighting and takes the driver's geometry, so the flow A_P -> Π_D(A_P) is the
    geometric difference between the two faces. ``guide`` (H, W, 2), a map puppet px -> driver px
    (e.g. the TPS of the two faces' mean fiducials), is where the flow starts: the basis is
    warped by it first, and φ = guide ∘ (identity + flow)."""
    ys, xs = np.mgrid[0:puppet_mask.shape[0], 0:puppet_mask.shape[1]].astype(np.float32)
    grid = np.stack([xs, ys], axis=-1)
    start = grid if guide is None else np.asarray(guide, np.float32)
    if guide is not None:
        driver_basis = np.stack([compose(np.asarray(b, np.float32), start, cv2.BORDER_REPLICATE) for b in driver_basis])
    average = np.asarray(puppet_average, np.float32) / 255
    projected = np.clip(project(average, driver_basis, puppet_mask), 0, 1).astype(np.float32)
    w = flow.flow(average, projected, puppet_mask)
    return compose(start, grid + w, cv2.BORDER_REPLICATE)


def guided_correspondence(puppet_average: np.ndarray, puppet_mask: np.ndarray, driver_basis: np.ndarray,
                          flow: FlowBackend, puppet_fiducials: np.ndarray, driver_fiducials: np.ndarray, *,
                          landmark_guide: bool = True, guide_lambda: float = 1.0, pin_fiducials: bool = True,
                          pin_lambda: float = 1.0) -> np.ndarray:
    """φ as the motion step makes it (the workflow's ``motion.correspondence``): :func:`correspondence`
    started from the smoothing TPS (λ ``guide_lambda``) that takes the puppet's mean fiducials (49, 2)
    to the driver's (``landmark_guide``), then pinned to them (:func:`persona.plugins.face.warp.pin`,
    λ ``pin_lambda``; ``pin_fiducials``), so that the two faces' fiducials correspond exactly."""
    guide = tps_map(puppet_fiducials, driver_fiducials, puppet_mask.shape, lam=guide_lambda,
                    step=4) if landmark_guide else None
    phi = correspondence(puppet_average, puppet_mask, driver_basis, flow, guide)
    return pin(phi, puppet_fiducials, driver_fiducials, lam=pin_lambda) if pin_fiducials else phi

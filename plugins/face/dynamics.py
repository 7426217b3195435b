"""The driver's per-frame 3D flow: how the driver's average face moves in every video frame.

The paper takes its per-frame meshes ``M_D^t`` from [23] ("Total moving face reconstruction",
ECCV 2014): a dense 3D flow of the person's average shape, helped by shading. This module is the
stand-in of ALGORITHMS §9.2, built from the collection's outputs (average depth ``Z̄``, grey
albedo ``ρ̄``, rank-4 appearance basis ``B_D``):

1. the frame's pose, smoothed over time (:func:`smooth_poses`);
2. the frame frontalised with the person's *own* average depth, and a z-buffer visibility mask;
3. the illumination-matched reference ``Ĵ_t = B_D c_t`` (masked least squares): the frame's
   lighting on the average expression;
4. 2D flow ``w_t`` from ``Ĵ_t`` to the frontalised frame ``J_t``: the average's surface point at
   canonical ``(u, v)`` is seen at ``(u, v) + w_t``. Not in ALGORITHMS: by default the flow starts
   from the frame's landmarks (:func:`landmark_guide`): ``J_t`` is first warped by the smoothing
   TPS that takes the average's fiducials to the frame's pose-corrected landmarks, steps 3-4 run on
   the warped frame, and ``w_t`` is that flow composed with the TPS. On real video the flow alone
   missed most of the mouth and eye motion;
5. that point slid on the average surface, ``X_t = (u + w_x, v + w_y, Z̄((u, v) + w_t))``. The true
   point lies on the camera ray through it;
6. shading refinement along that ray: ``M = X_t + δ r`` with ``r`` the ray direction scaled to a
   unit canonical z step (the exact ray of the frame's camera, not ALGORITHMS' z-axis
   approximation). The frame light ``l_t`` comes from ``ρ̄`` and the current normals by least
   squares, then Gauss-Newton steps on
   ``Σ (ρ̄ (l0 + l·n(M)) - J̃_t)² + λ_s ||Δδ||² + λ_0 ||δ||²`` over the visible, well-exposed,
   lit pixels (``J̃_t`` = the frame's intensity at the tracked point);
7. temporal smoothing of ``w_t`` and ``δ`` (:func:`smooth_tracks`), then the meshes
   ``M_D^t = X_t + δ r`` (:func:`frame_mesh`) and their mean ``M̄_D`` (:func:`mean_mesh`).

Everything is on the canonical grid (H x W, 244 x 194 by default) in canonical px, with the rigid
head pose removed. The per-frame work is :func:`track_frame`; a DAG stage calls it per frame of a
chunk (with ``time_radius`` frames of halo on each side), then :func:`smooth_tracks` and
:func:`frame_mesh`. :func:`driver_meshes` does the whole sequence in memory (tests, benchmarks).

What is approximated (ALGORITHMS §9.3): [23]'s joint energy and temporal terms; out-of-plane motion
comes from shading only; δ is solved on a coarser grid (``solve_stride``) and interpolated
bilinearly, which keeps the sparse solve small (out-of-plane expression motion is smooth);
occlusions are masked, not modelled.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.sparse as sp
from pydantic import Field
from scipy.linalg import solveh_banded
from scipy.ndimage import distance_transform_edt

from ..base import Params, Rejected
from ..builtin.frontalize import canonical_landmarks, frontalizing_map
from ..kinds import FlowBackend, Pose
from .mesh import cast, grid_triangles, jaw_motion, lip_split, raycasting_scene, rim_points
from .subspace import project
from .template import IDX49
from .tracks import bridge
from .warp import TpsWarp, compose

__all__ = ["DynamicsParams", "DriverModel", "FrameTrack", "smooth_poses", "track_frame", "smooth_tracks",
           "frame_mesh", "mean_mesh", "driver_meshes", "mesh_error"]

_LUMA = np.array([0.299, 0.587, 0.114])


class DynamicsParams(Params):
    """Parameters of the driver's per-frame 3D flow (ALGORITHMS §9.2; defaults tuned on synthetic
    driver videos, see tests/plugins/test_dynamics.py and benchmarks/dynamics_speed.py)."""

    landmark_guide: bool = Field(True, description="start the flow from the frame's own landmarks: a "
                                 "smoothing TPS takes the average's fiducials to the frame's landmarks "
                                 "(pose-corrected with the average depth), and the flow only corrects it. "
                                 "Off = the flow alone (ALGORITHMS §9.2.4), which misses wide mouth "
                                 "motion on real video")
    guide_lambda: float = Field(0.1, ge=0, description="λ of the guide's smoothing TPS (Eq. 1; the paper "
                                "warps photos with 10): larger is smoother and passes on less of the motion "
                                "(measured in docs/expression.md)")
    guide_step: int = Field(1, ge=1, le=8, description="evaluate the guide's spline on every n-th canonical row "
                            "and column, bilinearly between: more than 1 rounds off the eyelids' few-px motion "
                            "(measured in docs/expression.md)")
    guide_rim_spacing: int = Field(12, ge=2, le=100, description="px between the points of the average's "
                                   "rim that the guide holds in place (12 on the 244 x 194 grid: ~50 points)")
    guide_jaw: float = Field(0.8, ge=0, le=2, description="how far the rim below the mouth moves with the "
                             "lower lip (mesh.jaw_motion; not in the paper): 0.8 = as far as dlib's chin point "
                             "moves with the lower lip on the example drivers; 0 = the whole rim held still, "
                             "which squeezed the chin between the lip and the rim (docs/expression.md, \"A jaw "
                             "that drops with the lips\")")
    guide_split: bool = Field(True, description="the guide parts the lips rather than bending between them "
                              "(mesh.lip_split; not in the paper): how much further the lower lip moves than the "
                              "upper one is a step at the line where the lips meet, and the spline draws the rest. "
                              "Off = one spline through both lips, which overshoots below an open mouth: the "
                              "rows under the lower lip ran 8 px past it and folded back (docs/expression.md)")
    shading_refinement: bool = Field(True, description="refine the depth along the camera ray by shading "
                                     "(step 6); off = points slide on the average surface only")
    smoothness: float = Field(0.003, ge=0, description="λ_s: weight of ||Δδ||², the squared 5-point "
                              "Laplacian of the depth change (intensity² per (px/px²)²). Tuned on synthetic "
                              "driver videos (GT pose and average): 0.001-0.01 equally good, 0.1 keeps half "
                              "the gain, ALGORITHMS' starting 1-10 almost none")
    damping: float = Field(1e-4, ge=0, description="λ_0: weight of ||δ||² (intensity² per px²); pins the "
                           "part of δ that shading leaves free. Tuned as λ_s: 1e-5 and 1e-4 alike, 1e-3 "
                           "(ALGORITHMS' start) loses most of the gain, 1e-6 lets δ drift (worse than none)")
    gauss_newton_steps: int = Field(2, ge=1, le=10, description="Gauss-Newton steps of the shading "
                                    "refinement (the light is re-fitted before each; 3 gave the same error)")
    solve_stride: int = Field(3, ge=1, le=8, description="δ is solved on every n-th row and column and "
                              "interpolated bilinearly between (1 = every pixel: 2 % lower error on "
                              "synthetic videos, 9x slower; out-of-plane expression motion is smooth)")
    robust_threshold: float = Field(0.01, gt=0, description="Huber threshold of the shading residual "
                                    "(intensity units): larger residuals, from flow errors on texture "
                                    "edges, weigh as |r| instead of r²")
    dark: float = Field(0.03, ge=0, lt=1, description="frame intensities below this are left out of the "
                        "shading fit (noise, cast shadows)")
    saturated: float = Field(0.98, gt=0, le=1, description="frame intensities above this are left out "
                             "of the shading fit (clipped)")
    min_shading: float = Field(0.05, ge=0, description="pixels whose predicted shading l0 + l·n falls "
                               "below this are left out (attached shadow: the model is not linear there)")
    rim: int = Field(2, ge=0, le=20, description="px of the visible face's rim left out of the reference fit "
                     "and the flow (filled from inside): the frontalised rim mixes in background at the "
                     "silhouette, and the flow latches onto that edge (0.2 px instead of 4.8 px flow error "
                     "there on synthetic frames)")
    shading_blur: float = Field(1.0, ge=0, le=10, description="σ in px of the Gaussian low-pass of the frame "
                                "intensity and the albedo before the shading fit (0 = none): the frame resolves "
                                "less albedo texture than the average, and flow errors misplace it")
    shading_rim: int = Field(4, ge=0, le=20, description="px of the tracked face's rim left out of the "
                             "shading fit (grazing view: the frame mixes in background there)")
    occlusion_tolerance: float = Field(1.0, ge=0, description="canonical px a surface point may lie "
                                       "behind the first hit on its camera ray and still count as visible")
    visibility_step: int = Field(2, ge=1, le=8, description="cast visibility rays on every n-th canonical "
                                 "row and column (1 = every pixel)")
    time_sigma: float = Field(0.75, ge=0, le=10, description="σ in frames of the Gaussian smoothing of the "
                              "flow and δ over time (0 = off): larger is steadier and passes on less of fast "
                              "motion (speech moves the lips at 3-6 Hz; measured in docs/expression.md)")
    time_radius: int = Field(2, ge=0, le=10, description="frames on each side in the temporal smoothing "
                             "(the halo a chunk of frames needs)")


# ----------------------------------------------------------------------------- the average model


@dataclass(frozen=True, eq=False)
class DriverModel:
    """The driver's average face on the canonical grid, as the collection stage stores it.

    depth : (H, W) float64 — Z̄, canonical px (``shape/depth``), filled beyond ``mask`` by the
        nearest face value so that sampling near the border stays finite
    albedo : (H, W) float64 — ρ̄, grey (``shape/albedo``), 0 off the mask
    mask : (H, W) bool — where the average is defined (``shape/mask``)
    basis : (k, H, W) float64 — B_D in grey (luma of ``subspace/basis``; grey images of the
        collection lie in its span because luma is linear)
    fiducials : (49, 2) float64 or None — where the average's 49 fiducials lie on the canonical grid
        (``aligned/mean_fiducials``: the collection is registered to them); None = no landmark guide
    """

    depth: np.ndarray
    albedo: np.ndarray
    mask: np.ndarray
    basis: np.ndarray
    fiducials: np.ndarray | None = None

    @classmethod
    def build(cls, depth: np.ndarray, albedo: np.ndarray, mask: np.ndarray, basis: np.ndarray,
              fiducials: np.ndarray | None = None) -> "DriverModel":
        """Check and convert the collection's arrays: depth (H, W) with NaN allowed off the mask, albedo
        (H, W) grey (NaN allowed off the mask), mask (H, W) bool, basis (k, H, W, 3) RGB or (k, H, W),
        fiducials (49, 2) or None."""
        depth = np.asarray(depth, dtype=np.float64)
        if depth.ndim != 2:
            raise ValueError(f"depth must have shape (H, W), got {depth.shape}")
        shape = depth.shape
        mask = np.asarray(mask)
        if mask.shape != shape or mask.dtype != bool:
            raise ValueError(f"mask must be bool of shape {shape}, got {mask.dtype} {mask.shape}")
        albedo = np.asarray(albedo, dtype=np.float64)
        if albedo.shape != shape:
            raise ValueError(f"albedo must be grey of shape {shape}, got {albedo.shape}")
        basis = np.asarray(basis, dtype=np.float64)
        if basis.ndim == 4 and basis.shape[3] == 3:
            basis = basis @ _LUMA
        if basis.ndim != 3 or basis.shape[1:] != shape:
            raise ValueError(f"basis must have shape (k, {shape[0]}, {shape[1]}[, 3]), got {basis.shape}")
        if fiducials is not None:
            fiducials = np.array(fiducials, dtype=np.float64)
            if fiducials.shape != (49, 2) or not np.isfinite(fiducials).all():
                raise ValueError(f"fiducials must be 49 finite (x, y) points, got {fiducials.shape}")
            fiducials.setflags(write=False)
        mask = mask & np.isfinite(depth) & np.isfinite(albedo) & np.isfinite(basis).all(axis=0)
        if mask.sum() < 100:
            raise ValueError(f"the average face has only {int(mask.sum())} valid pixels")
        nearest = distance_transform_edt(~mask, return_distances=False, return_indices=True)
        depth = depth[tuple(nearest)]
        albedo = np.where(mask, albedo, 0.0)
        basis = np.where(mask, np.nan_to_num(basis), 0.0)
        for a in (depth, albedo, mask, basis):
            a.setflags(write=False)
        return cls(depth, albedo, mask, basis, fiducials)

    @property
    def shape(self) -> tuple[int, int]:
        return self.depth.shape

    @functools.cached_property
    def grid(self) -> tuple[np.ndarray, np.ndarray]:
        """Canonical pixel coordinates (xs, ys), each (H, W) float32."""
        h, w = self.shape
        ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
        return xs, ys

    @functools.cached_property
    def rest_mesh(self) -> np.ndarray:
        """The average surface M(u, v) = (u, v, Z̄(u, v)), (H, W, 3) float32: the no-motion mesh."""
        xs, ys = self.grid
        return np.stack([xs, ys, self.depth.astype(np.float32)], axis=-1)

    @functools.cached_property
    def scene(self):
        """The average mesh as an open3d ray-casting scene (visibility), built once per model."""
        return raycasting_scene(self.rest_mesh.reshape(-1, 3).astype(np.float64), grid_triangles(self.mask))

    def visible(self, fmap: np.ndarray, pose: Pose, image_size: tuple[int, int], tolerance: float,
                step: int) -> np.ndarray:
        """(H, W) bool: mask pixels whose average-surface point is the first hit on its ray from the
        camera and projects inside the photo (an exact z-buffer; rays on every ``step``-th pixel)."""
        h, w = image_size
        inside = (self.mask & (fmap[..., 0] >= 0) & (fmap[..., 0] <= w - 1)
                  & (fmap[..., 1] >= 0) & (fmap[..., 1] <= h - 1))
        centre = camera_centre(pose)
        coarse = np.zeros(self.shape, bool)
        coarse[::step, ::step] = True
        rows, cols = np.nonzero(coarse & self.mask)
        points = self.rest_mesh[rows, cols].astype(np.float64)
        offsets = points - centre
        distance = np.linalg.norm(offsets, axis=1)
        hits = cast(self.scene, np.broadcast_to(centre, points.shape), offsets / distance[:, None])
        seen = np.zeros(self.shape, bool)
        seen[rows, cols] = hits["t_hit"] >= distance - tolerance
        if step > 1:  # each cast ray stands for the step x step block it starts
            seen = np.repeat(np.repeat(seen[::step, ::step], step, 0), step, 1)[:self.shape[0], :self.shape[1]]
        return inside & seen

    @functools.lru_cache(maxsize=4)
    def rim_points(self, spacing: int) -> np.ndarray:
        """(k, 2) float64 canonical (x, y) points every ``spacing`` px along the mask's outer contour."""
        return rim_points(self.mask, spacing)

    @functools.lru_cache(maxsize=4)
    def guide_warp(self, lam: float, spacing: int, step: int = 1) -> TpsWarp:
        """The landmark guide's spline (fitted once per model): from the fiducials and the rim points
        every ``spacing`` px, which stay in place, to where a frame shows them; evaluated on every
        ``step``-th pixel."""
        return TpsWarp(np.concatenate([self.fiducials, self.rim_points(spacing)]), self.shape, lam=lam, step=step)

    @functools.cached_property
    def _operators(self) -> dict[int, "_Operators"]:
        return {}

    def operators(self, stride: int) -> "_Operators":
        """The sparse operators of the shading refinement for a solve stride (built once per model)."""
        if stride not in self._operators:
            self._operators[stride] = _Operators.build(self.mask, stride)
        return self._operators[stride]


def camera_centre(pose: Pose) -> np.ndarray:
    """The camera centre in the canonical frame, ``-Rᵀ t`` (3,)."""
    rotation = cv2.Rodrigues(np.asarray(pose.rvec, dtype=np.float64))[0]
    return -rotation.T @ np.asarray(pose.tvec, dtype=np.float64)


# ----------------------------------------------------------------------------- sparse operators


@dataclass(frozen=True, eq=False)
class _Operators:
    """Finite differences on the mask pixels (in ``np.nonzero(mask)`` order) and the coarse grid.

    du, dv : (n, n) ∂/∂u, ∂/∂v — central differences, one-sided where a neighbour is off the mask
    laplacian : (m, n) 5-point Laplacian on the pixels whose 4 neighbours are all on the mask
    up : (n, c) bilinear interpolation of the coarse nodes (every ``stride``-th row and column)
    pattern : du @ up and dv @ up on their union sparsity pattern (see :meth:`jacobian`)
    laplacian_gram, up_gram : (laplacian @ up)ᵀ (laplacian @ up) and upᵀ up, the regularisers' normal
        matrices on the coarse nodes
    """

    rows: np.ndarray
    cols: np.ndarray
    du: sp.csr_matrix
    dv: sp.csr_matrix
    laplacian: sp.csr_matrix
    up: sp.csr_matrix
    pattern: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    laplacian_gram: sp.csr_matrix
    up_gram: sp.csr_matrix

    @classmethod
    def build(cls, mask: np.ndarray, stride: int) -> "_Operators":
        h, w = mask.shape
        rows, cols = np.nonzero(mask)
        n = len(rows)
        index = np.full((h + 2, w + 2), -1)  # padded: neighbours off the grid are off the mask
        index[rows + 1, cols + 1] = np.arange(n)
        me = np.arange(n)

        def difference(dr, dc):
            plus = index[rows + 1 + dr, cols + 1 + dc]
            minus = index[rows + 1 - dr, cols + 1 - dc]
            both = (plus >= 0) & (minus >= 0)
            only_plus = (plus >= 0) & (minus < 0)
            only_minus = (plus < 0) & (minus >= 0)
            r = np.concatenate([me[both], me[both], me[only_plus], me[only_plus], me[only_minus], me[only_minus]])
            c = np.concatenate([plus[both], minus[both], plus[only_plus], me[only_plus], me[only_minus],
                                minus[only_minus]])
            v = np.concatenate([np.full(both.sum(), 0.5), np.full(both.sum(), -0.5),
                                np.ones(only_plus.sum()), -np.ones(only_plus.sum()),
                                np.ones(only_minus.sum()), -np.ones(only_minus.sum())])
            return sp.csr_matrix((v, (r, c)), shape=(n, n))

        du, dv = difference(0, 1), difference(1, 0)
        neighbours = [index[rows + 1 + dr, cols + 1 + dc] for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0))]
        inner = np.all([nb >= 0 for nb in neighbours], axis=0)
        k = int(inner.sum())
        lr = np.repeat(np.arange(k), 5)
        lc = np.stack([me[inner]] + [nb[inner] for nb in neighbours], axis=1).ravel()
        lv = np.tile([-4.0, 1.0, 1.0, 1.0, 1.0], k)
        laplacian = sp.csr_matrix((lv, (lr, lc)), shape=(k, n))

        # bilinear interpolation from the coarse nodes (y, x) = (stride i, stride j)
        hc, wc = (h - 1) // stride + 2, (w - 1) // stride + 2
        fy, fx = rows / stride, cols / stride
        y0, x0 = np.floor(fy).astype(int), np.floor(fx).astype(int)
        ty, tx = fy - y0, fx - x0
        ur, uc, uv = [], [], []
        for oy, ox, weight in ((0, 0, (1 - ty) * (1 - tx)), (0, 1, (1 - ty) * tx), (1, 0, ty * (1 - tx)),
                               (1, 1, ty * tx)):
            ur.append(me)
            uc.append((y0 + oy) * wc + (x0 + ox))
            uv.append(weight)
        up = sp.csr_matrix((np.concatenate(uv), (np.concatenate(ur), np.concatenate(uc))), shape=(n, hc * wc))
        used = np.flatnonzero(np.asarray(abs(up).sum(axis=0)).ravel() > 0)
        up = up[:, used].tocsr()
        laplacian_up = (laplacian @ up).tocsr()
        # du @ up and dv @ up on their union pattern (real and imaginary parts of one matrix), so that
        # diag(a) du @ up + diag(b) dv @ up is a weighted sum of two data arrays, with no sparse algebra
        both = ((du @ up).astype(np.complex128) + 1j * (dv @ up)).tocsr()
        both.sum_duplicates()
        entry_rows = np.repeat(np.arange(n), np.diff(both.indptr))
        pattern = (both.indptr, both.indices, both.data.real.copy(), both.data.imag.copy(), entry_rows)
        return cls(rows, cols, du, dv, laplacian, up, pattern,
                   (laplacian_up.T @ laplacian_up).tocsr(), (up.T @ up).tocsr())

    @functools.lru_cache(maxsize=4)
    def regulariser(self, smoothness: float, damping: float) -> sp.csr_matrix:
        """λ_s (laplacian @ up)ᵀ (laplacian @ up) + λ_0 upᵀ up: the shading refinement's prior on the coarse
        nodes, the same in every frame (made once per pair of weights)."""
        return (smoothness * self.laplacian_gram + damping * self.up_gram).tocsr()

    def jacobian(self, a: np.ndarray, b: np.ndarray) -> sp.csr_matrix:
        """diag(a) du @ up + diag(b) dv @ up, (n, c): the derivative of per-pixel values that depend on
        the δ-derivatives through coefficients a (of ∂δ/∂u) and b (of ∂δ/∂v)."""
        indptr, indices, du_up, dv_up, entry_rows = self.pattern
        data = a[entry_rows] * du_up + b[entry_rows] * dv_up
        return sp.csr_matrix((data, indices, indptr), shape=(len(self.rows), self.up.shape[1]))


# ----------------------------------------------------------------------------- poses

#: σ (frames) of the driver's pose smoothing, the default of ``stages.motion.params.pose_sigma``: light
#: enough to keep a head that moves unevenly from frame to frame where it is, while it takes out most of
#: dlib's noise; wider ones took real head motion away (the face lagged where the head went;
#: docs/expression.md, "The head's pose, smoothed less", benchmarks/pose_smoothing.py)
POSE_SIGMA = 0.5


def smooth_poses(poses: Sequence[Pose | None], sigma: float = POSE_SIGMA) -> list[Pose]:
    """Poses smoothed over time: Gaussian of ``sigma`` frames on rvec and tvec (ALGORITHMS §9.2.1).

    Frames without a pose (None) are first bridged by linear interpolation between their neighbours
    (held constant at the ends), so they get a pose too. Rotation vectors are averaged component-wise,
    which is accurate for the small, slowly varying head rotations of a video (far from the 180°
    wrap-around of Rodrigues vectors). The camera and reprojection RMS of a frame are kept (a bridged
    frame takes those of the nearest frame with a pose, and rms NaN).
    """
    if sigma < 0:
        raise ValueError(f"sigma must be >= 0, got {sigma}")
    found = np.array([p is not None for p in poses])
    if not found.any():
        raise ValueError("no frame has a pose: nothing to smooth")
    vectors = np.full((len(poses), 6), np.nan)
    vectors[found] = [np.r_[p.rvec, p.tvec] for p in poses if p is not None]
    filled = smooth_in_time(bridge(vectors, found), sigma)
    known = np.flatnonzero(found)
    out = []
    for t, v in enumerate(filled):
        source = poses[known[np.argmin(np.abs(known - t))]]
        out.append(Pose(rvec=v[:3].copy(), tvec=v[3:].copy(), camera=np.asarray(source.camera, dtype=np.float64),
                        rms=float(source.rms) if found[t] else float("nan")))
    return out


def smooth_in_time(values: np.ndarray, sigma: float) -> np.ndarray:
    """``values`` (T, ...) with no missing frame, Gaussian-smoothed along time over ±3σ frames; σ = 0
    (or a single frame) returns them unchanged."""
    if sigma <= 0 or len(values) < 2:
        return np.asarray(values, dtype=np.float64)
    return gaussian_in_time(values, None, sigma, time_radius(sigma))


def time_radius(sigma: float) -> int:
    """How many frames on each side :func:`smooth_in_time` takes in at ``sigma`` (0 for none)."""
    return max(1, int(np.ceil(3 * sigma))) if sigma > 0 else 0


def gaussian_in_time(values: np.ndarray, valid: np.ndarray | None, sigma: float, radius: int) -> np.ndarray:
    """Normalised Gaussian average over ±radius frames along axis 0 of ``values`` (T, ...).

    Frames with ``valid`` False have weight 0; at the ends the window is cut and renormalised.
    A frame with no valid frame in its window comes back NaN."""
    values = np.asarray(values, dtype=np.float64)
    n = len(values)
    valid = np.ones(n, bool) if valid is None else np.asarray(valid, bool)
    offsets = np.arange(-radius, radius + 1)
    kernel = np.exp(-0.5 * (offsets / sigma) ** 2) if sigma > 0 else (offsets == 0).astype(float)
    out = np.full_like(values, np.nan)
    for t in range(n):
        idx = t + offsets
        keep = (idx >= 0) & (idx < n)
        idx, wts = idx[keep], kernel[keep] * valid[idx[keep]]
        if wts.sum() > 0:
            out[t] = np.tensordot(wts / wts.sum(), values[idx], axes=1)
    return out


# ----------------------------------------------------------------------------- one frame


@dataclass(frozen=True)
class FrameTrack:
    """The 3D flow of one frame before temporal smoothing.

    flow : (H, W, 2) float32 — w_t: the average's point at canonical (u, v) is seen at (u, v) + w_t
        in the frame frontalised with the average depth
    delta : (H, W) float32 — δ, the depth change along the camera ray in canonical z px (0 off the
        mask, and everywhere without shading refinement)
    light : (4,) float64 — (l0, lx, ly, lz) of the frame in the face frame, with ρ̄'s scale (NaN
        without refinement)
    tracked : (H, W) bool — mask pixels whose tracked point is visible in the frame
    used : (H, W) bool — the pixels the shading fit used (visible, well exposed, lit)
    """

    flow: np.ndarray
    delta: np.ndarray
    light: np.ndarray
    tracked: np.ndarray
    used: np.ndarray


def as_grey_image(image: np.ndarray) -> np.ndarray:
    """(h, w, 3) RGB or (h, w) grey, uint8 or float in [0, 1] -> (h, w) float32 grey in [0, 1]."""
    a = np.asarray(image)
    scale = 1 / 255 if a.dtype == np.uint8 else 1.0
    if a.ndim == 3 and a.shape[2] == 3:
        a = a.astype(np.float32) @ _LUMA.astype(np.float32)
    elif a.ndim != 2:
        raise ValueError(f"image must have shape (h, w, 3) or (h, w), got {a.shape}")
    return np.ascontiguousarray(a * np.float32(scale), dtype=np.float32)


def _sample(image: np.ndarray, x: np.ndarray, y: np.ndarray, border=cv2.BORDER_REPLICATE) -> np.ndarray:
    """Bilinear samples of a (h, w) float image at float32 maps x, y (cv2.remap, §0 conventions)."""
    return cv2.remap(np.ascontiguousarray(image, dtype=np.float32), x, y, cv2.INTER_LINEAR, borderMode=border)


def track_frame(model: DriverModel, image: np.ndarray, pose: Pose, flow: FlowBackend,
                params: DynamicsParams = DynamicsParams(), landmarks: np.ndarray | None = None) -> FrameTrack:
    """Steps 2-6 of ALGORITHMS §9.2 for one frame (its pose already smoothed).

    image : (h, w, 3) RGB or (h, w) grey, uint8 or float in [0, 1] — the raw video frame
    pose : the frame's head pose (canonical point X -> camera ``R X + t``)
    flow : the 2D flow backend for reference -> frame; it gets the pair already filled beyond the
        visible face (:func:`fill_outside`) and no mask
    landmarks : (68, 2) or (49, 2) the frame's landmarks in the photo, or None. With
        ``params.landmark_guide`` and ``model.fiducials``, the frontalised frame is first warped by
        the smoothing TPS that takes its pose-corrected landmarks to the average's fiducials; the
        reference is fitted and the flow computed on that warped frame, and the flow is composed
        with the TPS (:func:`landmark_guide`)

    Raises :class:`Rejected` when fewer than 100 face pixels are visible (the DAG records the frame
    as rejected and bridges it; :func:`smooth_tracks` accepts None for it).
    """
    grey = as_grey_image(image)
    fmap, _ = frontalizing_map(model.depth, pose)
    seen = model.visible(fmap, pose, grey.shape, params.occlusion_tolerance, params.visibility_step)
    if seen.sum() < 100:
        raise Rejected(f"dynamics: only {int(seen.sum())} pixels of the face are visible in the frame")
    xs, ys = model.grid
    guide = landmark_guide(model, landmarks, pose, params)
    if guide is None:
        guide = np.stack([xs, ys], axis=-1)
    to_photo = compose(fmap, guide, cv2.BORDER_REPLICATE)
    frontal = _sample(grey, to_photo[..., 0], to_photo[..., 1])
    warped_seen = _sample(seen.astype(np.float32), guide[..., 0], guide[..., 1], cv2.BORDER_CONSTANT) > 0.999
    inner = cv2.erode(warped_seen.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=params.rim).astype(bool)
    if inner.sum() < 100:
        raise Rejected(f"dynamics: only {int(inner.sum())} pixels of the face are visible after the landmark guide")
    reference = np.clip(project(frontal, model.basis, weights=inner), 0.0, 1.0)
    r = flow.flow(*fill_outside(np.stack([reference, frontal]), inner))
    # compose: u in the reference <-> u + r(u) in the warped frame <-> guide(u + r(u)) in the frontal frame
    w = compose(guide, np.stack([xs + r[..., 0], ys + r[..., 1]], axis=-1), cv2.BORDER_REPLICATE)
    w[..., 0] -= xs
    w[..., 1] -= ys
    tx, ty = xs + w[..., 0], ys + w[..., 1]
    tracked = model.mask & (_sample(seen.astype(np.float32), tx, ty, cv2.BORDER_CONSTANT) > 0.999)
    delta = np.zeros(model.shape, np.float32)
    light = np.full(4, np.nan)
    used = np.zeros(model.shape, bool)
    if params.shading_refinement:
        # the frame's intensity at the tracked point: compose the maps, sample the photo once (§0)
        photo_x = _sample(fmap[..., 0], tx, ty)
        photo_y = _sample(fmap[..., 1], tx, ty)
        intensity = _sample(grey, photo_x, photo_y)
        surface = _surface(model, w)
        ray = _rays(surface, pose)
        good = tracked & (intensity > params.dark) & (intensity < params.saturated)
        good = cv2.erode(good.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=params.shading_rim).astype(bool)
        delta, light, used = refine_depth(model, surface, ray, intensity, good, params)
    return FrameTrack(flow=w, delta=delta, light=light, tracked=tracked, used=used)


def landmark_guide(model: DriverModel, landmarks: np.ndarray | None, pose: Pose,
                   params: DynamicsParams) -> np.ndarray | None:
    """(H, W, 2) float32 map canonical px -> frontalised-frame px that takes the average's fiducials to
    the frame's pose-corrected landmarks (smoothing TPS, λ = ``guide_lambda``), or None when there is
    no guide (switched off, no model fiducials, no or non-finite landmarks).

    Points on the rim of the average's mask stay in place: the 49 fiducials have no jaw line, and
    without them the spline's affine part stretches the whole face when the mouth opens and the
    brows rise (on a synthetic frame at λ = 10: 4.9 px RMS from the truth instead of 2.1; no motion 3.1).
    Those below the mouth move with the lower lip (``guide_jaw`` of :func:`mesh.jaw_motion`): the chin
    drops with the jaw. With ``guide_split``, the lips' parting is a step at the line where they meet
    (:func:`mesh.lip_split`), not a spline's steepest stretch."""
    if not params.landmark_guide or model.fiducials is None or landmarks is None:
        return None
    points = np.asarray(landmarks, np.float64)
    points = points[list(IDX49)] if len(points) == 68 else points
    if points.shape != (49, 2) or not np.isfinite(points).all():
        return None
    canonical, _ = canonical_landmarks(points, model.depth, pose, model.fiducials)
    offsets = canonical - model.fiducials
    still = model.rim_points(params.guide_rim_spacing)
    rim = still + params.guide_jaw * jaw_motion(model.fiducials, offsets, still) if params.guide_jaw else still
    warp = model.guide_warp(params.guide_lambda, params.guide_rim_spacing, params.guide_step)
    if not params.guide_split:
        return warp.map(np.concatenate([canonical, rim]))
    # the lips' parting as a step, the spline through what is left of the motion (mesh.lip_split)
    nodes = np.concatenate([model.fiducials, still])
    xs, ys = model.grid
    step = lip_split(model.fiducials, offsets, np.stack([xs.ravel(), ys.ravel()], axis=1))
    return warp.map(np.concatenate([canonical, rim]) - lip_split(model.fiducials, offsets, nodes)) + \
        step.reshape(*xs.shape, 2).astype(np.float32)


def fill_outside(images: np.ndarray, mask: np.ndarray, sigma: float = 4.0) -> np.ndarray:
    """images (n, H, W) float32 with the pixels off ``mask`` replaced by the nearest mask pixel's value,
    blurred (σ px): a texture-free extension without an edge at the mask border, for the flow to
    ignore (as the flow backends' own mask filling, ALGORITHMS §6.5, which is 10x slower on a canvas
    the face nearly fills because it widens its blur until the corners are reached)."""
    nearest = distance_transform_edt(~mask, return_distances=False, return_indices=True)
    out = np.empty(images.shape, np.float32)
    for k, image in enumerate(images):
        extended = cv2.GaussianBlur(np.ascontiguousarray(image[tuple(nearest)], dtype=np.float32), (0, 0), sigma)
        out[k] = np.where(mask, image, extended)
    return out


def _surface(model: DriverModel, w: np.ndarray) -> np.ndarray:
    """X_t = (u + w_x, v + w_y, Z̄((u, v) + w)), (H, W, 3) float32: the points slid on the average."""
    xs, ys = model.grid
    tx, ty = xs + w[..., 0], ys + w[..., 1]
    return np.stack([tx, ty, _sample(model.depth, tx, ty)], axis=-1)


def _rays(surface: np.ndarray, pose: Pose) -> np.ndarray:
    """Camera ray directions through the points (H, W, 3), scaled to a unit step in canonical z."""
    offset = surface.astype(np.float64) - camera_centre(pose)
    return (offset / offset[..., 2:3]).astype(np.float32)


def refine_depth(model: DriverModel, surface: np.ndarray, ray: np.ndarray, intensity: np.ndarray,
                 good: np.ndarray, params: DynamicsParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shading refinement along the camera rays (ALGORITHMS §9.2.6).

    Gauss-Newton on δ (one value per coarse node, interpolated to the mask pixels) of
    ``Σ h(ρ̄ (l0 + l·n(X + δ r)) - J̃) + λ_s ||Δδ||² + λ_0 ||δ||²`` with h the Huber function; the
    light is re-fitted by least squares before each step. Normals ``n = normalize(X_v × X_u)``
    (towards the camera, §0) from the mesh's finite differences; their derivative in δ treats the
    ray as locally constant.

    Returns δ (H, W) float32 (0 off the mask), the light (4,) and the pixels used (H, W) bool.
    """
    ops = model.operators(params.solve_stride)
    rows, cols = ops.rows, ops.cols
    x0 = surface[rows, cols].astype(np.float64)
    r = ray[rows, cols].astype(np.float64)
    # low-pass both sides alike: shading is smooth, while the albedo's fine texture is blurred by the
    # frame's lower resolution and misplaced by flow errors (at the truth: 0.017 -> 0.009 RMS)
    rho = _blur_on(model.albedo, good, params.shading_blur)[rows, cols]
    target = _blur_on(intensity, good, params.shading_blur)[rows, cols]
    candidate = good[rows, cols] & (rho > 0)
    regulariser = ops.regulariser(params.smoothness, params.damping)
    coarse = np.zeros(ops.up.shape[1])
    delta = np.zeros(len(rows))
    light = np.full(4, np.nan)
    rows_used = np.zeros(len(rows), bool)
    for _ in range(params.gauss_newton_steps):
        x = x0 + delta[:, None] * r
        xu, xv = ops.du @ x, ops.dv @ x
        m = np.cross(xv, xu)
        norm = np.linalg.norm(m, axis=1)
        defined = norm > 1e-9  # nodes whose differences vanish (e.g. isolated by holes in the mask) have no normal
        norm = np.where(defined, norm, 1.0)
        n = m / norm[:, None]
        design = rho[:, None] * np.column_stack([np.ones(len(n)), n])
        use = candidate & defined
        if use.sum() < 50:
            break
        light = np.linalg.lstsq(design[use], target[use], rcond=None)[0]
        shading = light[0] + n @ light[1:]
        use &= shading > params.min_shading
        residual = rho * shading - target
        weight = np.where(use, np.minimum(1.0, params.robust_threshold / np.maximum(np.abs(residual), 1e-12)), 0.0)
        g = (light[1:] - n * (n @ light[1:])[:, None]) / norm[:, None]
        a = rho * np.sum(g * np.cross(xv, r), axis=1)
        b = rho * np.sum(g * np.cross(r, xu), axis=1)
        root = np.sqrt(weight)
        jac = ops.jacobian(a * root, b * root)
        normal = (jac.T @ jac) + regulariser
        gradient = jac.T @ (root * residual) + regulariser @ coarse
        coarse = coarse - _solve_spd(normal, gradient)
        delta = ops.up @ coarse
        rows_used = use
    out = np.zeros(model.shape, np.float32)
    out[rows, cols] = delta
    used = np.zeros(model.shape, bool)
    used[rows, cols] = rows_used
    return out, light, used


def _blur_on(image: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Normalised Gaussian blur of ``image`` over the pixels of ``mask`` (float64; σ = 0: unchanged)."""
    image = np.asarray(image, dtype=np.float64)
    if sigma <= 0:
        return image
    weight = cv2.GaussianBlur(mask.astype(np.float64), (0, 0), sigma)
    blurred = cv2.GaussianBlur(np.where(mask, image, 0.0), (0, 0), sigma)
    return blurred / np.maximum(weight, 1e-6)


def _solve_spd(matrix: sp.spmatrix, rhs: np.ndarray) -> np.ndarray:
    """Solve a sparse symmetric positive definite system by banded Cholesky (LAPACK pbtrf/pbtrs).

    The unknowns are coarse grid nodes in row-major order, so the matrix is banded (about two grid
    rows): 3-4x faster here than SuperLU, whose fill-in on a 2D grid costs more than the band. The band
    is read off the matrix's compressed rows as they are (no triangular copy)."""
    matrix = sp.csr_matrix(matrix)
    matrix.sum_duplicates()  # a no-op for a sum or product of sparse matrices, which has none
    rows = np.repeat(np.arange(matrix.shape[0]), np.diff(matrix.indptr))
    offset = rows - matrix.indices
    lower = offset >= 0
    bands = np.zeros((int(offset[lower].max()) + 1, matrix.shape[0]))
    bands[offset[lower], matrix.indices[lower]] = matrix.data[lower]
    # a node that no data or prior reaches (a hole in a reconstructed mask) has an empty row: pin it
    # with a unit diagonal (its right-hand side is 0 too), and keep the rest safely definite
    bands[0] += 1e-10 * bands[0].max() + (bands[0] <= 0)
    return solveh_banded(bands, rhs, lower=True, check_finite=False)


# ----------------------------------------------------------------------------- sequences


def smooth_tracks(tracks: Sequence[FrameTrack | None], params: DynamicsParams = DynamicsParams()
                  ) -> list[FrameTrack | None]:
    """Flow and δ averaged over ±``time_radius`` frames with Gaussian weights (σ = ``time_sigma``).

    Missing frames (None) carry no weight; they get the average of their neighbours when any lies
    within the radius, else stay None. For a chunk of frames, pass the chunk with ``time_radius``
    frames of halo on each side and keep the middle: the result equals the whole sequence's there.
    """
    present = np.array([t is not None for t in tracks])
    if params.time_sigma == 0 or params.time_radius == 0 or not present.any():
        return list(tracks)
    first = next(t for t in tracks if t is not None)
    out: list[FrameTrack | None] = []
    offsets = np.arange(-params.time_radius, params.time_radius + 1)
    kernel = np.exp(-0.5 * (offsets / params.time_sigma) ** 2)
    for t in range(len(tracks)):
        flow = np.zeros(first.flow.shape, np.float64)
        delta = np.zeros(first.delta.shape, np.float64)
        total = 0.0
        for o, k in zip(offsets, kernel):
            s = t + o
            if 0 <= s < len(tracks) and present[s]:
                flow += k * tracks[s].flow
                delta += k * tracks[s].delta
                total += k
        if total == 0:
            out.append(None)
            continue
        own = tracks[t] if present[t] else None
        out.append(FrameTrack(flow=(flow / total).astype(np.float32), delta=(delta / total).astype(np.float32),
                              light=own.light if own else np.full(4, np.nan),
                              tracked=own.tracked if own else np.zeros(first.tracked.shape, bool),
                              used=own.used if own else np.zeros(first.used.shape, bool)))
    return out


def frame_mesh(model: DriverModel, track: FrameTrack, pose: Pose) -> np.ndarray:
    """M_D^t = X_t + δ r (ALGORITHMS §9.2.7): (H, W, 3) float32 in canonical px, rigid pose removed.

    Finite everywhere (the flow and the filled depth extend beyond the mask, where δ = 0), meaningful
    on ``model.mask``."""
    surface = _surface(model, track.flow)
    return surface + track.delta[..., None] * _rays(surface, pose)


def mean_mesh(meshes: Iterable[np.ndarray]) -> np.ndarray:
    """M̄_D = mean over the frames of M_D^t (ALGORITHMS §9.2.9), (H, W, 3) float32; streams the meshes."""
    total, count = None, 0
    for mesh in meshes:
        total = mesh.astype(np.float64) if total is None else total + mesh
        count += 1
    if count == 0:
        raise ValueError("no meshes to average")
    return (total / count).astype(np.float32)


def driver_meshes(model: DriverModel, images: Sequence[np.ndarray], poses: Sequence[Pose | None],
                  flow: FlowBackend, params: DynamicsParams = DynamicsParams(), *, pose_sigma: float = POSE_SIGMA
                  ) -> tuple[np.ndarray, np.ndarray]:
    """A whole video in memory: poses smoothed, every frame tracked, tracks smoothed, meshes built.

    Frames with pose None (no face) are tracked with the bridged pose. Returns the per-frame meshes
    (T, H, W, 3) float32 and their mean M̄_D (H, W, 3) float32.
    """
    smoothed = smooth_poses(poses, pose_sigma)
    tracks = smooth_tracks([track_frame(model, im, p, flow, params) for im, p in zip(images, smoothed)], params)
    meshes = np.stack([frame_mesh(model, t, p) for t, p in zip(tracks, smoothed)])
    return meshes, mean_mesh(meshes)


def mesh_error(mesh: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    """RMS 3D distance (canonical px) between two meshes parametrised on the same grid, over mask."""
    d = np.asarray(mesh, np.float64)[mask] - np.asarray(truth, np.float64)[mask]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))

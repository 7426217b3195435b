"""Kind ``shape``: photometric stereo over an aligned photo collection (ALGORITHMS §8).

Model (Kemelmacher-Shlizerman & Seitz, ICCV 2011 [14]): the n aligned grey images on the p
mask pixels, stacked as the rows of ``M (n x p)``, satisfy ``M ≈ L S`` with

* ``L (n x 4)``: per-image first-order spherical-harmonic lights ``(l0, lx, ly, lz)``;
* ``S (4 x p)``: ``[ρ; ρ n_x; ρ n_y; ρ n_z]``, albedo ρ times ``[1, n]``.

A rank-4 factorisation ``M ≈ L~ S~`` is unique only up to an invertible 4x4 A
(``L = L~ A^-1``, ``S = A S~``). [14] fixes A with the generic template: the template's
``S_t = [ρ_t; ρ_t n_t]`` gives lights ``L_t = argmin ||M - L S_t||``, then
``A^-1 = argmin ||L~ A^-1 - L_t||`` (ALGORITHMS §8.2). The recovered face therefore inherits the
template's depth scale in its bas-relief components.

Missing pixels (``visibility`` False, or NaN) are filled by the rank-4 model itself: masked
alternating least squares of ``W ⊙ (M - L S)`` (W = 1 where seen), started from the template's
``S = [1; n_t]`` (a start near the answer: block-missing data, such as one side of the face
hidden in a third of the photos, stalls ALS started from mean-filled data).

The ``regularised`` variant (ALGORITHMS §8.2 and §16.9) is template-regularised alternating least
squares: start from ``S = S_t`` and iterate ``L = argmin ||W ⊙ (M - L S)||``,
``S = argmin ||W ⊙ (M - L S)||² + g ||S - S_prior||²`` with ``S_prior = [ρ; ρ n_t]`` (ρ the current
albedo) and ``g = weight · trace(LᵀL)/4``. Missing pixels simply get weight 0.

Scale: ``L S`` does not change when L is multiplied by c and S divided by c. The result is scaled
so that the mean over the images of ``l0 - lz`` (the shading of a normal facing the camera) is 1:
the albedo is then in image intensity units.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from ..base import Params, Rejected
from ..hookspecs import hookimpl
from ..kinds import Shape, ShapeBackend

__all__ = ["TemplatePhotometricStereo", "angular_error_deg", "as_grey"]

_LUMA = np.array([0.299, 0.587, 0.114])


def as_grey(images: np.ndarray) -> np.ndarray:
    """(n, H, W) grey or (n, H, W, 3) RGB -> (n, H, W) float64 grey (Rec. 601 luma; linear, so
    a Lambertian collection stays Lambertian). Float64 grey is returned as it is, not copied."""
    a = np.asarray(images)
    if a.ndim == 4 and a.shape[3] == 3:
        return a.astype(np.float64) @ _LUMA
    if a.ndim == 3:
        return np.asarray(a, dtype=np.float64)
    raise ValueError(f"images must have shape (n, H, W) or (n, H, W, 3), got {a.shape}")


def angular_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in degrees between unit normal fields a and b (..., 3)."""
    c = np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def _rank_k(M: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The k leading singular triplets of M (n x p) through the n x n Gram matrix when n << p
    (the same numbers as the SVD, n² p instead of n p min(n, p) work)."""
    n, p = M.shape
    if 4 * n > p:
        U, s, Vt = np.linalg.svd(M, full_matrices=False)
        return U[:, :k], s[:k], Vt[:k]
    evals, evecs = np.linalg.eigh(M @ M.T)
    order = np.argsort(evals)[::-1][:k]
    s = np.sqrt(np.maximum(evals[order], 0.0))
    U = evecs[:, order]
    Vt = (U.T @ M) / np.maximum(s, 1e-300)[:, None]
    return U, s, Vt


def _solve_rows(A: np.ndarray, B: np.ndarray, W: np.ndarray | None, reg: float | np.ndarray = 0.0,
                prior: np.ndarray | None = None) -> np.ndarray:
    """X (k, q) minimising ||W ⊙ (B - A X)||² + Σ_j reg_j ||X_j - prior_j||², column by column.

    A: (m, k); B, W: (m, q); reg a scalar or one weight per column (q,). W None means all
    ones (one shared solve when reg is a scalar)."""
    k = A.shape[1]
    if W is None and np.ndim(reg) == 0:
        G = A.T @ A + reg * np.eye(k)
        rhs = A.T @ B + (reg * prior if reg else 0.0)
        return np.linalg.solve(G, rhs)
    m, q = B.shape
    reg = np.broadcast_to(np.asarray(reg, dtype=np.float64), (q,))
    AA = (A[:, :, None] * A[:, None, :]).reshape(m, k * k)
    G = (np.broadcast_to(AA.sum(axis=0), (q, k * k)) if W is None else W.T @ AA).reshape(-1, k, k)
    G = G + reg[:, None, None] * np.eye(k)
    rhs = (B if W is None else W * B).T @ A
    if reg.any():
        rhs = rhs + reg[:, None] * prior.T
    # a column with too few observations stays solvable through the tiny ridge
    G += (1e-12 * np.trace(G, axis1=1, axis2=2) + 1e-300)[:, None, None] * np.eye(k)
    return np.linalg.solve(G, rhs[..., None])[..., 0].T


def lighting_variety(lights: np.ndarray) -> float:
    """How much the photos' lights (n, 4: first-order spherical harmonics) differ: the third singular value
    of the matrix over the first. A normal has two directions and the albedo a third to be told apart, so the
    lights must span three: 0 for one light in every photo, and for one that only swings one way (a head
    that turns under one lamp); 0.37 for Powell's photos from many places and years. Rows that are not finite
    (photos the fit did not take: ``max_images``) are left out."""
    lights = np.asarray(lights, np.float64)
    lights = lights[np.isfinite(lights).all(axis=1)]
    if len(lights) < 3:
        return 0.0
    s = np.linalg.svd(lights, compute_uv=False)
    return float(s[2] / s[0]) if len(s) > 2 and s[0] > 0 else 0.0


class TemplatePhotometricStereo(ShapeBackend):
    name = "ps_template"
    description = ("rank-4 photometric stereo of the aligned collection, the 4x4 ambiguity fixed with the "
                   "generic template (Kemelmacher-Shlizerman & Seitz 2011; ALGORITHMS §8)")
    default = True

    class Params(Params):
        rank: int = Field(4, ge=4, le=9, description="rank of the factorisation M ≈ L S; 4 = first-order "
                          "spherical harmonics (ambient + 3 directional). Only the first 4 components "
                          "are used for the shape; a higher rank only helps fill missing pixels")
        template_iterations: int = Field(50, ge=1, le=1000, description="most rounds of the template "
                                         "fit: lights L_t from S_t = [ρ_t; ρ_t n_t], ambiguity A, then "
                                         "ρ_t ← ρ/mean(ρ) (ALGORITHMS §8.2 step 4). The fixed point is "
                                         "exact when the template is the truth; it converges linearly "
                                         "(3 rounds: 0.87°, 10: 0.15°, 30: 0.01° on exact images)")
        template_tolerance: float = Field(1e-7, gt=0, description="stop the template rounds when ρ_t "
                                          "changes by less than this (RMS, relative to its mean 1)")
        fill_iterations: int = Field(100, ge=0, le=1000, description="masked alternating least-squares "
                                     "rounds of the rank-r fit that fills the missing pixels (visibility "
                                     "False or NaN) before the factorisation")
        fill_tolerance: float = Field(1e-6, gt=0, description="stop refilling when the RMS change of "
                                      "the filled entries falls below this (intensity units)")
        max_template_angle: float = Field(
            30.0, gt=0, le=180, description="normals further than this (degrees) from the template's "
            "are taken as outliers and replaced by the template's (real collections: shadowed sides, "
            "hair, glasses); 180 keeps every recovered normal. Not in [14]: a robustness choice")
        regularised: bool = Field(True, description="template-regularised alternating least squares "
                                  "instead of SVD + template lights (ALGORITHMS §8.2, §16.9): more robust "
                                  "to residual misalignment, pulls towards the template where the "
                                  "images say little (measured: docs/shape.md)")
        als_iterations: int = Field(30, ge=1, le=1000, description="regularised variant: ALS rounds")
        regularisation: float = Field(0.01, ge=0, description="regularised variant: g = regularisation · "
                                      "trace(LᵀL)/4, the weight of ||S - [ρ; ρ n_t]||²")
        prior: Literal["normal", "shape"] = Field(
            "normal", description="regularised variant, how the template pull is spread over the pixels. "
            "'shape' (ALGORITHMS §8.2): the same weight g on ||S_j - ρ_j [1; n_t]||² everywhere, so the "
            "pull on the normal's direction grows with ρ² while the noise does not: dark pixels (hair, "
            "brows) follow the noise. 'normal': g (mean ρ / ρ_j)², the same pull on the direction at "
            "every pixel, i.e. a fixed angular prior against fixed image noise (a MAP reading; ρ_j "
            "floored at 5 % of the mean; measured: docs/shape.md)")
        robust: float = Field(1.5, ge=0, description="regularised variant: iteratively reweighted least "
                              "squares against shadows, specularities and residual misalignment. Each "
                              "round weights every image pixel by 1/(1 + (r/(robust·σ))²) (Cauchy), with r "
                              "its residual from the rank-4 model and σ = 1.4826 · median |r| over the whole "
                              "collection; 0 = plain least squares ([14]; measured: docs/shape.md)")
        min_images: int = Field(8, ge=4, description="fewest images; fewer cannot pin down 4 lights "
                                "robustly and the collection is rejected")
        max_images: int = Field(600, ge=0, description="most images: a larger collection gives this many, "
                                "evenly spaced over it (the others get no lights); 0 = all. Not in [14]: the "
                                "fit holds every image's grey face in memory, about 1.6 MB each with its "
                                "working arrays (Bush's 530: 1.08 GiB resident), so 600 keeps a worker within "
                                "2 GiB. On Bush, every 2nd of 530 photos moves the normals by 0.66° (median; "
                                "docs/shape.md)")
        min_visible: float = Field(0.6, ge=0, le=1, description="a mask pixel seen by fewer than this "
                                   "fraction of the images is left out (NaN in the result). The outer ring of "
                                   "the oval, seen only in part of the photos, is where real collections show "
                                   "ears, hair and background; its normals tilt the integrated surface "
                                   "(measured: docs/shape.md)")
        dark_threshold: float = Field(0.0, ge=0, lt=1, description="pixels darker than this are treated "
                                      "as missing (attached shadows break the linear model); 0 = keep all")
        full_variety: float = Field(0.25, ge=0, description="the collection's lighting variety (lighting_variety: "
                                    "the third singular value of the photos' lights over the first) from which "
                                    "the recovered normals are kept as they are; below it they are drawn towards "
                                    "the template's in proportion (at half of it, half way). Under one light "
                                    "(one video under one lamp) photometric stereo cannot tell a dark albedo (brows, "
                                    "lips) from a normal turned from the light, and the face bulges. Not in [14] "
                                    "(0: the normals as recovered). Powell's LFW photos measure 0.37 and keep theirs; "
                                    "single videos 0.00-0.02 (docs/shape.md)")

    def images_for(self, n: int) -> np.ndarray:
        """All n, or ``max_images`` of them evenly spaced."""
        if self.params.max_images == 0 or n <= self.params.max_images:
            return np.arange(n)
        return np.unique(np.linspace(0, n - 1, self.params.max_images).round().astype(int))

    # ------------------------------------------------------------------ inputs
    def _inputs(self, images, mask, visibility, template_normals, template_depth):
        grey = as_grey(images)
        n, h, w = grey.shape
        mask = np.asarray(mask)
        if mask.shape != (h, w):
            raise ValueError(f"mask must have shape ({h}, {w}) like the images, got {mask.shape}")
        if mask.dtype != bool:
            raise TypeError(f"mask must be bool, got {mask.dtype}")
        tn = np.asarray(template_normals, dtype=np.float64)
        if tn.shape != (h, w, 3):
            raise ValueError(f"template_normals must have shape ({h}, {w}, 3), got {tn.shape}")
        td = np.asarray(template_depth, dtype=np.float64)
        if td.shape != (h, w):
            raise ValueError(f"template_depth must have shape ({h}, {w}), got {td.shape}")
        seen = np.isfinite(grey)
        if visibility is not None:
            vis = np.asarray(visibility)
            if vis.shape != (n, h, w):
                raise ValueError(f"visibility must have shape ({n}, {h}, {w}), got {vis.shape}")
            if vis.dtype != bool:
                raise TypeError(f"visibility must be bool, got {vis.dtype}")
            seen &= vis
        if self.params.dark_threshold > 0:
            seen &= ~(grey < self.params.dark_threshold)
        if n < self.params.min_images:
            raise Rejected(f"shape: {n} images, need at least {self.params.min_images} for photometric stereo: "
                           "add photos of the same person")
        tnorm = np.linalg.norm(tn, axis=2)
        use = mask & np.isfinite(tnorm) & (tnorm > 0)
        use &= seen.mean(axis=0) >= max(self.params.min_visible, 4.0 / n)
        if use.sum() < 16:
            raise Rejected(f"shape: only {int(use.sum())} mask pixels seen by enough images")
        M = grey[:, use]
        W = seen[:, use]
        return M, W, use, tn[use] / tnorm[use][:, None]

    # ------------------------------------------------------------------ fits
    def _fill(self, M: np.ndarray, W: np.ndarray, tn: np.ndarray) -> np.ndarray:
        """Missing entries filled by the rank-r model: masked alternating least squares of
        ``W ⊙ (M - L S)``, started from the template's ``S_t = [1; n_t]`` (plus, for r > 4, the
        next components of the pixel-mean-filled matrix)."""
        if W.all():
            return M
        Mz = np.where(W, M, 0.0)
        S = np.vstack([np.ones(len(tn)), tn.T])
        if self.params.rank > 4:
            col_mean = Mz.sum(axis=0) / np.maximum(W.sum(axis=0), 1)
            extra = _rank_k(np.where(W, M, col_mean[None, :]), self.params.rank)[2][4:]
            S = np.vstack([S, extra])
        Wf = W.astype(np.float64)
        miss = ~W
        previous = np.zeros(int(miss.sum()))
        for _ in range(self.params.fill_iterations):
            L = _solve_rows(S.T, Mz.T, Wf.T).T
            S = _solve_rows(L, Mz, Wf)
            filled = (L @ S)[miss]
            change = np.sqrt(np.mean((filled - previous) ** 2))
            previous = filled
            if change < self.params.fill_tolerance:
                break
        Mz[miss] = previous  # filled in place, the last use of Mz: no second (n, p) array
        return Mz

    def _template_fit(self, M, W, tn):
        F = self._fill(M, W, tn)
        U, s, Vt = _rank_k(F, 4)
        Lt_ = U * np.sqrt(s)  # L~
        St_ = np.sqrt(s)[:, None] * Vt  # S~
        rho_t = np.ones(M.shape[1])
        for _ in range(self.params.template_iterations):
            S_t = rho_t[None, :] * np.vstack([np.ones(M.shape[1]), tn.T])
            L_t = _solve_rows(S_t.T, F.T, None).T  # argmin ||F - L S_t||
            A_inv = np.linalg.lstsq(Lt_, L_t, rcond=None)[0]  # L~ A^-1 ≈ L_t
            S = np.linalg.solve(A_inv, St_)
            L = Lt_ @ A_inv
            rho = np.linalg.norm(S[1:4], axis=0)
            rho = rho / max(rho.mean(), 1e-12)
            change = np.sqrt(np.mean((rho - rho_t) ** 2))
            rho_t = rho
            if change < self.params.template_tolerance:
                break
        return L, S

    def _als(self, M, W, tn, L, S):
        """Template-regularised ALS (see the module docstring), optionally robust (``robust``):
        the weights of each round come from the residuals of the previous one."""
        seen = None if W.all() else W.astype(np.float64)
        Wf = seen
        Mz = np.where(W, M, 0.0)
        for _ in range(self.params.als_iterations):
            L = _solve_rows(S.T, Mz.T, None if Wf is None else Wf.T).T
            rho = np.linalg.norm(S[1:4], axis=0)
            prior = rho[None, :] * np.vstack([np.ones_like(rho), tn.T])
            g = self.params.regularisation * np.trace(L.T @ L) / 4
            if self.params.prior == "normal":  # a fixed pull on the direction: g (mean ρ / ρ_j)²
                g = g * (rho.mean() / np.maximum(rho, 0.05 * rho.mean())) ** 2
            S = _solve_rows(L, Mz, Wf, reg=g, prior=prior)
            if self.params.robust > 0:  # in place: each (n, p) array here is as large as the collection
                Wf = None  # this round's weights are used: let them go before the next are made
                r = L @ S
                np.subtract(Mz, r, out=r)
                np.abs(r, out=r)
                sigma = 1.4826 * (np.median(r) if W.all() else np.median(r[W], overwrite_input=True))
                np.divide(r, max(self.params.robust * sigma, 1e-12), out=r)
                np.square(r, out=r)
                r += 1.0
                Wf = np.reciprocal(r, out=r)
                if seen is not None:
                    Wf *= seen
        return L, S

    # ------------------------------------------------------------------ contract
    def reconstruct(self, images, mask, visibility, template_normals, template_depth):
        """Normals, albedo and lights of the aligned collection; ``depth`` is None.

        ``template_depth`` is only checked: integrate the normals with an ``integrate`` backend,
        passing ``reference=template_depth`` to put the face at the template's depth. Mask pixels
        seen by too few images (``min_visible``) are NaN in the result like those off the mask.
        """
        M, W, use, tn = self._inputs(images, mask, visibility, template_normals, template_depth)
        L, S = self._template_fit(M, W, tn)
        if self.params.regularised:
            L, S = self._als(M, W, tn, L, S)
        rho = np.linalg.norm(S[1:4], axis=0)
        normals = (S[1:4] / np.maximum(rho, 1e-300)).T
        if np.mean(normals[:, 2]) > 0:  # global sign only, never per pixel
            normals, S, L = -normals, S * np.array([[1], [-1], [-1], [-1]]), L * np.array([1, -1, -1, -1])
        # scale: mean over images of the shading of a camera-facing normal (l0 - lz) is 1
        c = float(np.mean(L[:, 0] - L[:, 3]))
        if not np.isfinite(c) or c == 0:
            raise Rejected("shape: degenerate lighting (the images carry no shading)")
        L, rho = L / abs(c), rho * abs(c)
        facing = tn if np.mean(tn[:, 2]) < 0 else -tn  # the template, turned to the camera
        trust = min(lighting_variety(L) / self.params.full_variety, 1.0) if self.params.full_variety > 0 else 1.0
        if trust < 1:  # lighting too uniform to tell albedo from shape: towards the template
            normals = facing + trust * (normals - facing)
            normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        if self.params.max_template_angle < 180:  # outliers (shadowed sides, hair, glasses)
            far = np.sum(normals * facing, axis=1) < np.cos(np.radians(self.params.max_template_angle))
            normals[far] = facing[far]
        h, w = use.shape
        out_n = np.full((h, w, 3), np.nan)
        out_n[use] = normals
        out_rho = np.full((h, w), np.nan)
        out_rho[use] = rho
        return Shape(normals=out_n, albedo=out_rho, lighting=np.ascontiguousarray(L, dtype=np.float64),
                     depth=None)


@hookimpl
def persona_register_backends(register):
    register(TemplatePhotometricStereo)

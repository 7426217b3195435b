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

Streamed: the fit never holds the collection, so every photo can be taken. The images arrive a chunk at
a time (``reconstruct_chunks``) and wait, grey on the mask's pixels, in a temporary folder
(:class:`_Faces`); every step is a pass over them that keeps only arrays the size of a face or of the
lights. A least-squares step for L is each chunk's own (one light per image); one for S sums each
chunk's share of the per-pixel normal equations. The rank-4 factorisation is a subspace iteration on
``FᵀF`` (:func:`_top_singular`, to convergence), and the template fit needs no pass at all (it depends
on the images only through the factorisation). The robust weights' median is exact (:func:`_median`).
The fill's stopping rule sees each round's change in the next pass and stops where a whole-batch fit
would. The result is the whole-batch fit's to rounding (docs/shape.md).
"""

from __future__ import annotations

import os
import tempfile
from typing import Literal

import numpy as np
from pydantic import Field

from ..base import Params, Rejected
from ..face.mesh import enclosed
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


def _solve_normal(G: np.ndarray, rhs: np.ndarray, reg: float | np.ndarray = 0.0,
                  prior: np.ndarray | None = None) -> np.ndarray:
    """X (k, q) from the normal equations of q least-squares problems, G (q, k(k+1)/2: the upper triangle of
    each k x k matrix, :func:`_outer_rows`) and rhs (q, k), with Σ_j reg_j ||X_j - prior_j||² added; reg a
    scalar or one weight per problem (q,), prior (k, q). G may be one row that every problem shares: with
    a scalar reg, that is one solve."""
    q, k = rhs.shape
    G = G[..., _symmetric(k)]  # (..., k, k)
    if G.ndim == 2 and np.ndim(reg) == 0:
        return np.linalg.solve(G + reg * np.eye(k), rhs.T + (reg * prior if reg else 0.0))
    reg = np.broadcast_to(np.asarray(reg, dtype=np.float64), (q,))
    G = np.broadcast_to(G, (q, k, k)) + reg[:, None, None] * np.eye(k)
    if reg.any():
        rhs = rhs + reg[:, None] * prior.T
    # a problem with too few observations stays solvable through the tiny ridge
    G += (1e-12 * np.trace(G, axis1=1, axis2=2) + 1e-300)[:, None, None] * np.eye(k)
    return np.linalg.solve(G, rhs[..., None])[..., 0].T


def _symmetric(k: int) -> np.ndarray:
    """(k, k): where each entry of a symmetric k x k matrix is in its upper triangle's row (:func:`_outer_rows`)."""
    index = np.zeros((k, k), int)
    rows, cols = np.triu_indices(k)
    index[rows, cols] = index[cols, rows] = np.arange(len(rows))
    return index


def _outer_rows(A: np.ndarray) -> np.ndarray:
    """(m, k(k+1)/2): each row of A (m, k) times itself, the upper triangle of a_i a_iᵀ (it is symmetric)."""
    rows, cols = np.triu_indices(A.shape[1])
    return A[:, rows] * A[:, cols]


def _chunk_step(M: np.ndarray, Wf: np.ndarray | None, S: np.ndarray, SS: np.ndarray):
    """One chunk's share of a round of alternating least squares of ``Wf ⊙ (M - L S)`` (Wf None: all ones):
    its images' lights L_c (m, k), each image's own least squares given S (k, p), and the normal equations
    of S that they give, pixel by pixel, to be summed over the chunks: G (p, k(k+1)/2) (one row when Wf is
    None) and rhs (p, k). SS: :func:`_outer_rows` of Sᵀ."""
    WM = M if Wf is None else Wf * M
    L = _solve_normal(SS.sum(axis=0) if Wf is None else Wf @ SS, WM @ S.T).T
    LL = _outer_rows(L)
    return L, (LL.sum(axis=0) if Wf is None else Wf.T @ LL), WM.T @ L


class _Faces:
    """The collection's grey faces on the fit's pixels, kept in a temporary folder ``size`` images to a file,
    and read back a file at a time by every pass of the fit (:meth:`chunks`): no more than a chunk of images
    is in memory, however many there are. They are written as they arrive (:meth:`add`), NaN where a photo
    does not see, with the number of images that see each pixel (``count``) and the sum of what they see
    (``total``); once the fit's pixels are known (:meth:`keep`), rewritten on those alone, as the values (0
    where unseen) and where they are seen. A collection of one chunk stays in memory."""

    def __init__(self, folder: str, size: int, pixels: int):
        self.folder, self.size = folder, size
        self.files: list[str] = []
        self.n = 0
        self.count = np.zeros(pixels, np.int64)
        self.total = np.zeros(pixels)
        self._pending: list[np.ndarray] = []
        self._held = None  # the one chunk of a small collection

    def add(self, grey: np.ndarray) -> None:
        """Rows (m, pixels) of grey values, NaN where unseen; written ``size`` at a time."""
        seen = np.isfinite(grey)
        self.count += seen.sum(axis=0)
        self.total += np.where(seen, grey, 0.0).sum(axis=0)
        self.n += len(grey)
        self._pending.append(grey)
        if sum(len(g) for g in self._pending) < self.size:
            return
        rows = np.concatenate(self._pending)
        start = 0
        while len(rows) - start >= self.size:
            self._write(rows[start:start + self.size])
            start += self.size
        self._pending = [rows[start:]]

    def _write(self, rows: np.ndarray) -> None:
        self.files.append(os.path.join(self.folder, f"{len(self.files):06d}.npy"))
        np.save(self.files[-1], rows)

    def keep(self, columns: np.ndarray) -> None:
        """The rows still pending written; then every file rewritten on these pixels alone (indices into those
        added), as the values, 0 where unseen, and where they are seen."""
        rest = np.concatenate(self._pending) if self._pending else np.empty((0, len(self.count)))
        self._pending = []
        self.count, self.total = self.count[columns], self.total[columns]
        if not self.files and len(rest):  # one chunk in all: held as it is, never written
            self._held = _valued(rest[:, columns])
            return
        if len(rest):
            self._write(rest)
        for path in self.files:
            M, W = _valued(np.load(path)[:, columns])
            if len(self.files) == 1:
                self._held = (M, W)
            else:
                np.save(path, M)
                np.save(path[:-4] + "_seen.npy", W)

    @property
    def all_seen(self) -> bool:
        return bool((self.count == self.n).all())

    def chunks(self):
        """(rows, M, W) for each file in turn: the images' rows in the collection (a slice), their grey values
        on the pixels kept, 0 where unseen, and where they are seen (bool)."""
        held = [self._held] if self._held is not None else (
            (np.load(path), np.load(path[:-4] + "_seen.npy")) for path in self.files)
        start = 0
        for M, W in held:
            yield slice(start, start + len(M)), M, W
            start += len(M)


def _valued(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Grey values (m, p), NaN where unseen, as :meth:`_Faces.chunks` gives them: 0 where unseen, and where seen."""
    W = np.isfinite(M)
    M[~W] = 0.0
    return M, W


def _top_singular(faces: _Faces, k: int, matrix, tolerance: float = 1e-10,
                  most: int = 60) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The k leading singular triplets U (n, k), s (k,), Vt (k, p) of the matrix F whose rows
    ``matrix(rows, M, W)`` makes of each chunk of ``faces``, one pass over them a round.

    Subspace iteration on FᵀF with a block of k + 10 vectors Z (p, k + 10): each pass gives P = F Z and
    Y = FᵀF Z = Σ over chunks of F_cᵀ P_c; the SVD of P gives U and s, ``Y`` gives Uᵀ F, and the next
    block is Y orthonormalised. Rounds go on until U's span moves by less than ``tolerance``, each direction
    weighted by its singular value over all of theirs (the SVD's to rounding, not a randomised
    approximation; 6-8 rounds on Bush's photos and on random lights), or for ``most`` rounds: so many only
    where the k-th singular value is hardly above the next ones (one light for every photo: 150 rounds),
    and then the SVD's k-th direction is the noise's choice too. As from the SVD, U's columns are
    orthonormal and Uᵀ F = diag(s) Vt exactly."""
    n, p = faces.n, len(faces.count)
    block = min(k + 10, n, p)
    Z = np.linalg.qr(np.random.default_rng(0).standard_normal((p, block)))[0]
    previous = None
    for _ in range(most):
        P, Y = np.empty((n, block)), np.zeros((p, block))
        for rows, M, W in faces.chunks():
            F = matrix(rows, M, W)
            P[rows] = F @ Z
            Y += F.T @ P[rows]
        Ub, sb, Wbt = np.linalg.svd(P, full_matrices=False)  # F Z = Ub sb Wbᵀ, so Ubᵀ F = sb⁻¹ Wbᵀ Yᵀ
        U, s = Ub[:, :k], sb[:k]
        UtF = (Y @ Wbt[:k].T / np.maximum(s, 1e-300)).T
        if previous is not None:  # how far U left the last span, each direction weighted by its singular value
            moved = np.linalg.norm((U - previous @ (previous.T @ U)) * s) / np.linalg.norm(s)
            if moved < tolerance:
                break
        previous = U
        Z = np.linalg.qr(Y)[0]
    return U, s, UtF / np.maximum(s, 1e-300)[:, None]


def _median(faces: _Faces, values, near: float | None = None, bits: int = 20, most: int = 1 << 20) -> float:
    """The exact median (as ``np.median``: the mean of the two middle ones of an even count) of the
    non-negative float64 numbers ``values(rows, M, W)`` gives, 1-D, for each chunk of ``faces``.

    Non-negative floats sort as their bit patterns do (as unsigned integers): each pass counts the
    patterns in 2^bits bins of the range that holds the middle ones and narrows the range to their bins,
    until at most ``most`` numbers lie in it; a last pass collects those and sorts them. ``near``, a guess
    (the last round's median), saves that pass when it is right: the first pass also collects the numbers
    within two bins of it."""
    lo, hi, shift = 0, 1 << 63, 63 - bits  # [lo, hi) of bit patterns; a non-negative float's is under 2^63
    below, total = 0, None  # how many numbers lie under lo; how many there are
    guess = None
    if near is not None and near > 0:
        b = int(np.float64(near).view(np.uint64)) >> shift
        guess, caught = (max(b - 2, 0) << shift, (b + 3) << shift), []
    while True:
        counts = np.zeros((hi - lo) >> shift, np.int64)
        for chunk in faces.chunks():
            x = values(*chunk).view(np.uint64)
            if lo > 0 or hi < 1 << 63:  # the first pass takes them all
                x = x[(x >= lo) & (x < hi)]
            counts += np.bincount(((x - np.uint64(lo)) >> np.uint64(shift)).astype(np.intp), minlength=len(counts))
            if guess is not None:
                caught.append(x[(x >= guess[0]) & (x < guess[1])])
        if total is None:
            total = int(counts.sum())
            middle = ((total - 1) // 2, total // 2)
        ends = below + np.cumsum(counts)
        first, last = np.searchsorted(ends, middle, side="right")  # the bins of the two middle ones
        below += int(counts[:first].sum())
        lo, hi = lo + (int(first) << shift), lo + ((int(last) + 1) << shift)
        if guess is not None and guess[0] <= lo and hi <= guess[1]:
            kept = np.concatenate(caught)
            kept = kept[(kept >= lo) & (kept < hi)]
            break
        guess = None
        if ends[last] - below <= most or shift == 0:
            kept = np.concatenate([x[(x >= lo) & (x < hi)] for x in
                                   (values(*chunk).view(np.uint64) for chunk in faces.chunks())])
            break
        shift = max(shift - bits, 0)
    kept.sort()
    a, b = kept[[middle[0] - below, middle[1] - below]].view(np.float64)
    return float((a + b) / 2)


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
    #: raised whenever the same inputs give another shape, so a stored one is made again (docs/CHANGELOG.md)
    version = "3"

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
        max_images: int = Field(0, ge=0, description="most images; 0 = all. A larger collection gives this many, "
                                "evenly spaced over it (the others get no lights). The fit streams over the "
                                "images (chunk_images), so its memory does not grow with them and every photo "
                                "can be taken; its time does, about linearly: a cap for a collection so large "
                                "that the shape's time matters. On Bush, every 2nd of 530 photos moves the "
                                "normals by 0.66° (median; docs/shape.md)")
        chunk_images: int = Field(64, ge=1, description="images the fit holds in memory at once. The collection "
                                  "waits, grey on the mask's pixels, in a temporary folder (TMPDIR; 9 bytes a "
                                  "pixel, about 0.25 MB a photo) and every round of the fit is a pass over it, a "
                                  "chunk at a time: memory grows with this and not with the photos. The result "
                                  "does not depend on it beyond rounding")
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

    # ------------------------------------------------------------------ contract
    def reconstruct(self, images, mask, visibility, template_normals, template_depth):
        """Normals, albedo and lights of the aligned collection; ``depth`` is None.

        ``template_depth`` is only checked: integrate the normals with an ``integrate`` backend,
        passing ``reference=template_depth`` to put the face at the template's depth. Mask pixels
        seen by too few images (``min_visible``) are NaN in the result like those off the mask.
        """
        return self.reconstruct_chunks([(images, visibility)], mask, template_normals, template_depth)

    def reconstruct_chunks(self, chunks, mask, template_normals, template_depth):
        """:meth:`reconstruct` of the images that ``chunks`` gives, (images, visibility) pairs of consecutive
        images, read once: the fit keeps them in a temporary folder (``chunk_images``) and holds one chunk
        of them at a time."""
        with tempfile.TemporaryDirectory(prefix="persona-shape-") as folder:
            faces, use, tn = self._inputs(chunks, folder, mask, template_normals, template_depth)
            L, S = _template_fit(faces, tn, self.params)
            if self.params.regularised:
                L, S = _als(faces, tn, L, S, self.params)
        rho = np.linalg.norm(S[1:4], axis=0)
        normals = (S[1:4] / np.maximum(rho, 1e-300)).T
        if np.mean(normals[:, 2]) > 0:  # global sign only, never per pixel
            normals, S, L = -normals, S * np.array([[1], [-1], [-1], [-1]]), L * np.array([1, -1, -1, -1])
        # scale: mean over images of the shading of a camera-facing normal (l0 - lz) is 1
        c = float(np.mean(L[:, 0] - L[:, 3]))
        if not np.isfinite(c) or c == 0:
            raise Rejected("shape: degenerate lighting (the images carry no shading)")
        L, rho = L / abs(c), rho * abs(c)
        turn = 1.0 if np.mean(tn[:, 2]) < 0 else -1.0  # the template's sign that turns it to the camera
        facing = turn * tn
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
        # a hole in the face that too few images see (under the nose, which hides it from a camera above) is
        # not its edge, which min_visible leaves out: it takes the template's normal, as an outlier does, and
        # the face's median albedo, so that the surface has no hole there
        template = np.asarray(template_normals, np.float64)
        length = np.linalg.norm(template, axis=2)
        holes = enclosed(use) & ~use & (length > 0)  # NaN lengths compare False: where the template has a normal
        out_n[holes] = turn * template[holes] / length[holes][:, None]
        out_rho[holes] = np.median(rho)
        return Shape(normals=out_n, albedo=out_rho, lighting=np.ascontiguousarray(L, dtype=np.float64),
                     depth=None)

    # ------------------------------------------------------------------ inputs
    def _inputs(self, chunks, folder, mask, template_normals, template_depth):
        """The images into ``folder`` (:class:`_Faces`), grey and NaN where unseen (visibility False, NaN, or
        under ``dark_threshold``), on the mask's pixels where the template has a normal; then only those
        pixels that enough of them see (``min_visible``). Returns the faces, the pixels used (H, W) and the
        template's unit normals there (p, 3)."""
        mask = np.asarray(mask)
        faces = None
        for images, visibility in chunks:
            grey = as_grey(images)
            m, h, w = grey.shape
            if faces is None:
                tn, pixels = self._template(mask, template_normals, template_depth, h, w)
                faces = _Faces(folder, self.params.chunk_images, int(pixels.sum()))
            elif (h, w) != mask.shape:
                raise ValueError(f"images must all have shape (m, {mask.shape[0]}, {mask.shape[1]}), got {grey.shape}")
            seen = np.isfinite(grey)
            if visibility is not None:
                vis = np.asarray(visibility)
                if vis.shape != (m, h, w):
                    raise ValueError(f"visibility must have shape ({m}, {h}, {w}) like its images, got {vis.shape}")
                if vis.dtype != bool:
                    raise TypeError(f"visibility must be bool, got {vis.dtype}")
                seen &= vis
            if self.params.dark_threshold > 0:
                seen &= ~(grey < self.params.dark_threshold)
            faces.add(np.where(seen[:, pixels], grey[:, pixels], np.nan))
        n = 0 if faces is None else faces.n
        if n < self.params.min_images:
            raise Rejected(f"shape: {n} images, need at least {self.params.min_images} for photometric stereo: "
                           "add photos of the same person")
        kept = faces.count / n >= max(self.params.min_visible, 4.0 / n)
        if kept.sum() < 16:
            raise Rejected(f"shape: only {int(kept.sum())} mask pixels seen by enough images")
        faces.keep(np.flatnonzero(kept))
        use = np.zeros(mask.shape, bool)
        use[pixels] = kept
        return faces, use, tn[kept]

    def _template(self, mask, template_normals, template_depth, h, w):
        """The template's unit normals (P, 3) on the pixels (H, W) of the mask where it has one."""
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
        tnorm = np.linalg.norm(tn, axis=2)
        pixels = mask & np.isfinite(tnorm) & (tnorm > 0)
        return tn[pixels] / tnorm[pixels][:, None], pixels


# ------------------------------------------------------------------ the fits of TemplatePhotometricStereo
# Each fit is a few passes over the faces (:meth:`_Faces.chunks`), with the backend's params ``p``: a
# least-squares step for the lights L is each chunk's own (one light per image); one for S sums every
# chunk's normal equations, pixel by pixel, and solves once they are all in.


def _fill(faces: _Faces, tn: np.ndarray, p):
    """The rank-r model (L, S) whose products fill the missing entries, or None when every entry is seen:
    masked alternating least squares of ``W ⊙ (M - L S)``, started from the template's ``S_t = [1; n_t]``
    (plus, for r > 4, the next components of the pixel-mean-filled matrix), until the filled entries move
    by less than ``fill_tolerance`` (RMS) from one round to the next. Each round is one pass, which also
    measures the last round's move: the rounds stop where the whole-batch fit's did."""
    if faces.all_seen:
        return None
    S = np.vstack([np.ones(len(tn)), tn.T])
    if p.rank > 4:
        col_mean = faces.total / np.maximum(faces.count, 1)
        extra = _top_singular(faces, p.rank, lambda rows, M, W: np.where(W, M, col_mean))[2][4:]
        S = np.vstack([S, extra])
    missing = faces.n * len(faces.count) - int(faces.count.sum())
    last = before = None  # (L, S) of the last round and of the one before it
    for _ in range(p.fill_iterations):
        L = np.empty((faces.n, len(S)))
        G = rhs = 0.0
        moved = 0.0
        SS = _outer_rows(S.T)
        for rows, M, W in faces.chunks():
            L[rows], g, r = _chunk_step(M, W.astype(np.float64), S, SS)
            G, rhs = G + g, rhs + r
            if last is not None:  # the last round's filled entries against those of the round before
                step = last[0][rows] @ last[1]
                if before is not None:
                    step -= before[0][rows] @ before[1]
                moved += float(np.sum(step[~W] ** 2))
        if last is not None and np.sqrt(moved / missing) < p.fill_tolerance:
            return last
        before, last = last, (L, _solve_normal(G, rhs))
        S = last[1]
    return last


def _template_fit(faces: _Faces, tn: np.ndarray, p):
    """The lights and shape (L, S) of the rank-4 factorisation of the filled faces (:func:`_fill`), its 4x4
    ambiguity fixed with the template (see the module docstring)."""
    filled = _fill(faces, tn, p)

    def F(rows, M, W):  # the filled matrix, a chunk of it
        return M if filled is None else np.where(W, M, filled[0][rows] @ filled[1])

    U, s, Vt = _top_singular(faces, 4, F)
    Lt_ = U * np.sqrt(s)  # L~
    St_ = np.sqrt(s)[:, None] * Vt  # S~
    rho_t = np.ones(len(tn))
    for _ in range(p.template_iterations):
        S_t = rho_t[None, :] * np.vstack([np.ones(len(tn)), tn.T])
        # L_t = argmin ||F - L S_t|| = F S_tᵀ (S_t S_tᵀ)⁻¹ and A⁻¹ = argmin ||L~ A⁻¹ - L_t||; as U's columns are
        # orthonormal and Uᵀ F = diag(s) Vt, that is A⁻¹ = S~ S_tᵀ (S_t S_tᵀ)⁻¹: no pass over the images
        A_inv = np.linalg.solve(S_t @ S_t.T, S_t @ St_.T).T
        S = np.linalg.solve(A_inv, St_)
        L = Lt_ @ A_inv
        rho = np.linalg.norm(S[1:4], axis=0)
        rho = rho / max(rho.mean(), 1e-12)
        change = np.sqrt(np.mean((rho - rho_t) ** 2))
        rho_t = rho
        if change < p.template_tolerance:
            break
    return L, S


def _als(faces: _Faces, tn: np.ndarray, L: np.ndarray, S: np.ndarray, p):
    """Template-regularised ALS (see the module docstring), optionally robust (``robust``): the weights of
    each round come from the residuals of the previous one, their scale σ from the median residual over
    the whole collection (:func:`_median`, a pass of its own)."""
    sigma = None  # of the last round's residuals; None: every seen entry weighs 1
    for round_ in range(p.als_iterations):
        new_L = np.empty_like(L)
        G = rhs = 0.0
        SS = _outer_rows(S.T)
        for rows, M, W in faces.chunks():
            if sigma is None:
                Wf = None if faces.all_seen else W.astype(np.float64)
            else:
                Wf = _cauchy(M - L[rows] @ S, max(p.robust * sigma, 1e-12))
                if not faces.all_seen:
                    Wf *= W
            new_L[rows], g, r = _chunk_step(M, Wf, S, SS)
            G, rhs = G + g, rhs + r
        L = new_L
        rho = np.linalg.norm(S[1:4], axis=0)
        prior = rho[None, :] * np.vstack([np.ones_like(rho), tn.T])
        g = p.regularisation * np.trace(L.T @ L) / 4
        if p.prior == "normal":  # a fixed pull on the direction: g (mean ρ / ρ_j)²
            g = g * (rho.mean() / np.maximum(rho, 0.05 * rho.mean())) ** 2
        S = _solve_normal(G, rhs, reg=g, prior=prior)
        if p.robust > 0 and round_ < p.als_iterations - 1:
            def residuals(rows, M, W, L=L, S=S):
                r = np.abs(M - L[rows] @ S)
                return r.ravel() if faces.all_seen else r[W]
            sigma = 1.4826 * _median(faces, residuals, near=None if sigma is None else sigma / 1.4826)
    return L, S


def _cauchy(r: np.ndarray, scale: float) -> np.ndarray:
    """The Cauchy weights 1 / (1 + (r / scale)²) of residuals r, computed in r's place."""
    np.abs(r, out=r)
    np.divide(r, scale, out=r)
    np.square(r, out=r)
    r += 1.0
    return np.reciprocal(r, out=r)


@hookimpl
def persona_register_backends(register):
    register(TemplatePhotometricStereo)

"""Expression-dependent multi-scale blending of aligned photos (paper §5, Eq. 2 and 3).

Every photo i, aligned to the target expression, contributes to each level of a Laplacian
pyramid with the weight

    W^i_l = (e_i + τ l^-β) · (L^i_l)^α,        e_i = exp(-||F^T - F^i||² / 2σ²)

normalised over the photos per pixel and level. ``e_i`` says how close photo i's expression
(its 49 pose-corrected fiducials F^i) is to the target's F^T; ``L^i_l`` is its local detail
(the response of a Laplacian filter) at level l; ``l`` counts from the coarsest level (0).
At l = 0 the uniform term τ·0^-β is infinite: the expression weight drops out and the
coarsest level is the detail-weighted mean of all photos (one consistent colour). At l = 1
the two terms are comparable, and from l = 2 on, τ l^-β (≤ 1e-6 at β = 20) is negligible:
fine detail comes from the photos with the target's expression (ALGORITHMS §12.3-§12.4).

Since ``e_i`` is one number per photo, a level's blend is two matrix-vector products,
``Σ_i W^i lap^i = e @ P + c Σ_i P^i`` and ``Σ_i W^i = e @ Q + c Σ_i Q^i`` with ``P^i = Q^i lap^i``,
``Q^i = (L^i)^α`` and ``c = τ l^-β``: :class:`BlendCache` keeps P and Q, so a new target (a video
frame) costs only these products (the paper's puppetry mode, §6).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from .fiducials import mean_square_distance


def expression_weights(fiducials: np.ndarray, target: np.ndarray, sigma: float, *,
                       relative: bool = False) -> np.ndarray:
    """e_i = exp(-||F^T - F^i||² / 2σ²) for fiducials (n, 49, 2) and a target (49, 2), in
    canonical px (σ = 10 in the paper: a mean displacement of 2 px per point gives 0.14).

    ``relative``: divided by the largest (the nearest photo gets 1), for averages that are
    normalised anyway; it keeps them defined when every e_i underflows (a target far from
    every photo). Points that are NaN in a photo or the target are left out of its distance,
    which is scaled back to all points: a turned photo is compared on its visible half."""
    d2 = np.shape(fiducials)[1] * mean_square_distance(fiducials, target)  # over the shared points, scaled to all
    d2[np.isnan(d2)] = np.inf  # no point in common
    return np.exp(-(d2 - (d2.min() if relative else 0.0)) / (2.0 * sigma ** 2))


def level_bias(levels: int, beta: float, tau: float) -> np.ndarray:
    """τ l^-β for each pyramid array index k (finest k = 0, so l = levels-1-k); inf at l = 0.
    τ = 0: no uniform term at any level, the coarsest included (0·∞ taken as 0)."""
    if tau == 0:
        return np.zeros(levels)
    l = np.arange(levels - 1, -1, -1, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return tau * l ** -beta


def gaussian_pyramid(image: np.ndarray, levels: int) -> list[np.ndarray]:
    """[image, pyrDown(image), ...], ``levels`` arrays, finest first."""
    pyramid = [image]
    for _ in range(levels - 1):
        pyramid.append(cv2.pyrDown(pyramid[-1]))
    return pyramid


def laplacian_pyramid(image: np.ndarray, levels: int) -> list[np.ndarray]:
    """Band-pass levels, finest first; the last is the coarsest Gaussian level. ``pyrUp`` gets
    the finer level's size (``pyrDown`` rounds odd sizes up: 97 -> 49 -> 25; ALGORITHMS §12.4)."""
    gauss = gaussian_pyramid(np.asarray(image, np.float32), levels)
    bands = [fine - cv2.pyrUp(coarse, dstsize=(fine.shape[1], fine.shape[0]))
             for fine, coarse in zip(gauss[:-1], gauss[1:])]
    return bands + [gauss[-1]]


def collapse(pyramid: list[np.ndarray]) -> np.ndarray:
    """The image whose Laplacian pyramid this is (exact inverse of :func:`laplacian_pyramid`)."""
    image = pyramid[-1]
    for band in pyramid[-2::-1]:
        image = cv2.pyrUp(image, dstsize=(band.shape[1], band.shape[0])) + band
    return image


def detail_pyramid(grey: np.ndarray, valid: np.ndarray, levels: int, *, blur: float = 1.0,
                   floor: float = 1e-6, confidence: np.ndarray | None = None) -> list[np.ndarray]:
    """L^i per level: |Laplacian| of the blurred grey image at full resolution, plus ``floor``
    (flat regions keep a weight), zero where the photo is not valid, reduced to each level by
    the Gaussian pyramid, i.e. the local detail energy there (ALGORITHMS §12.3's proposal).
    ``confidence`` (H, W) in [0, 1], if given, multiplies the response before the reduction:
    how much the photo's alignment is trusted there (see :meth:`BlendCache.build`)."""
    g = np.asarray(grey, np.float32)
    if blur > 0:
        g = cv2.GaussianBlur(g, (0, 0), blur)
    response = (np.abs(cv2.Laplacian(g, cv2.CV_32F, ksize=3)) + np.float32(floor)) * valid.astype(np.float32)
    if confidence is not None:
        response *= np.asarray(confidence, np.float32)
    return gaussian_pyramid(response, levels)


@numba.njit(cache=True, nogil=True, fastmath=True)
def _gemv_rows(stack, rows, weights, out):
    """out = Σ_r weights[r] · stack[rows[r]] (a matrix-vector product over the chosen rows of a
    (n, p) matrix, streaming each row once, without gathering them into a copy)."""
    out[:] = 0
    for r in range(rows.shape[0]):
        row, w = stack[rows[r]], weights[r]
        for j in range(out.shape[0]):
            out[j] += w * row[j]


def _product(stack: np.ndarray, rows: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Σ_r weights_r stack[rows_r] for a (n, ...) float32 stack."""
    out = np.empty(int(np.prod(stack.shape[1:])), np.float32)
    _gemv_rows(stack.reshape(len(stack), -1), rows, weights, out)
    return out.reshape(stack.shape[1:])


@dataclass
class BlendCache:
    """The per-photo terms of Eq. 3 that do not depend on the target, level by level.

    weighted[k] : (n, h_k, w_k, C) float32 — P = (L^i)^α · lap^i
    detail[k] : (n, h_k, w_k, 1) float32 — Q = (L^i)^α
    bias : (levels,) — τ l^-β per array index (inf at the coarsest)
    """

    weighted: list[np.ndarray]
    detail: list[np.ndarray]
    bias: np.ndarray

    def __post_init__(self):
        # the uniform term's sums over all photos, shared by every target
        self._weighted_sum = [p.sum(axis=0) for p in self.weighted]
        self._detail_sum = [q.sum(axis=0) for q in self.detail]
        self._energy = {}  # photo_energy's, per level

    def photo_energy(self, k: int) -> np.ndarray:
        """(h_k, w_k) the band energy a photo has at level k about each pixel: the detail-weighted
        mean over the photos of their band's squared value (mean over channels), i.e.
        Σ_i P_i² / Q_i / Σ_i Q_i, smoothed over 2 px. Computed on first use."""
        if k not in self._energy:
            total = np.zeros(self.detail[k].shape[1:3], np.float64)
            for p, q in zip(self.weighted[k], self.detail[k]):
                total += np.divide(np.mean(p ** 2, axis=-1), q[..., 0], out=np.zeros(q.shape[:2], np.float32),
                                   where=q[..., 0] > 0)
            den = self._detail_sum[k][..., 0]
            energy = np.divide(total, den, out=np.zeros_like(total), where=den > 0).astype(np.float32)
            self._energy[k] = cv2.GaussianBlur(energy, (0, 0), 2.0)
        return self._energy[k]

    @classmethod
    def build(cls, images: np.ndarray, valid: np.ndarray, *, levels: int, alpha: float, beta: float,
              tau: float, blur: float = 1.0, floor: float = 1e-6, margin: int = 2,
              confidence: np.ndarray | None = None) -> "BlendCache":
        """images: (n, H, W, C) float aligned photos; valid: (n, H, W) bool; confidence: None or
        (n, H, W) in [0, 1], each photo's local alignment confidence, a factor of its detail
        response L^i (so of its weight at every level): where a photo failed to register
        (a tear, a misplaced feature) it cannot dominate the fine levels however sharp it is.

        A photo's unseen pixels are filled with the mean of the photos that see them before its
        pyramid is built, so its bands carry no edge where its view ends; its weight there is
        zero, and ``margin`` px inside that edge too (resampling blurs the last pixels)."""
        n = len(images)
        seen = valid.sum(axis=0)
        fill = np.einsum("nhw,nhwc->hwc", valid.astype(np.float32), images) / np.maximum(seen, 1)[..., None]
        kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
        weighted, detail = [], []
        for i in range(n):
            image = np.where(valid[i][..., None], images[i], fill).astype(np.float32)
            inner = cv2.erode(valid[i].astype(np.uint8), kernel, borderValue=1) > 0 if margin else valid[i]
            q = detail_pyramid(image.mean(axis=-1), inner, levels, blur=blur, floor=floor,
                               confidence=None if confidence is None else confidence[i])
            bands = laplacian_pyramid(image, levels)
            if i == 0:
                weighted = [np.empty((n, *b.shape), np.float32) for b in bands]
                detail = [np.empty((n, *d.shape, 1), np.float32) for d in q]
            for k in range(levels):
                detail[k][i, ..., 0] = q[k] ** np.float32(alpha)
                weighted[k][i] = bands[k] * detail[k][i]
        return cls(weighted, detail, level_bias(levels, beta, tau))

    @property
    def levels(self) -> int:
        return len(self.weighted)

    def blend(self, e: np.ndarray, *, skip: float = 1e-6, restore: float = 1.0) -> np.ndarray:
        """The blended image (H, W, C) for expression weights e (n,).

        Each level is one matrix-vector product over the photos, compiled so that photos whose
        e is below ``skip`` × max(e) are skipped without copying the others: whatever their
        detail, their share of every level but the two coarsest is below that.

        ``restore`` > 1 (not in the paper): a weighted mean of photos whose fine detail does not
        coincide (skin, pores, hair) has less of it than any one photo; each band but the two
        coarsest is scaled back, pixel by pixel, towards the energy a photo has there
        (:meth:`photo_energy`; the blend's own smoothed over 2 px likewise), by a factor between 1 and
        ``restore``."""
        e = np.asarray(e, np.float64)
        rows = np.flatnonzero(e >= skip * e.max()) if e.max() > 0 else np.zeros(0, np.int64)
        ek = e[rows].astype(np.float32)
        pyramid = []
        for k in range(self.levels):
            c = self.bias[k]
            if np.isinf(c):  # l = 0: uniform, the expression weight drops out
                num, den = self._weighted_sum[k], self._detail_sum[k]
            else:
                num = _product(self.weighted[k], rows, ek) + np.float32(c) * self._weighted_sum[k]
                den = _product(self.detail[k], rows, ek) + np.float32(c) * self._detail_sum[k]
            band = num / np.where(den > 0, den, np.inf)  # 0 where no photo sees the pixel
            if restore > 1 and k < self.levels - 2:
                have = cv2.GaussianBlur(np.mean(band ** 2, axis=-1), (0, 0), 2.0)
                gain = np.sqrt(np.divide(self.photo_energy(k), have, out=np.ones_like(have), where=have > 0))
                band = band * np.clip(gain, 1.0, restore)[..., None]
            pyramid.append(band)
        return collapse(pyramid)

    def weights(self, e: np.ndarray) -> list[np.ndarray]:
        """The normalised W̃^i_l per level, (n, h_k, w_k): for tests and pictures."""
        out = []
        for k in range(self.levels):
            q, c = self.detail[k][..., 0], self.bias[k]
            w = q if np.isinf(c) else (np.asarray(e, np.float32)[:, None, None] + np.float32(c)) * q
            total = w.sum(axis=0)
            out.append(w / np.where(total > 0, total, np.inf))
        return out

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

import functools
from dataclasses import dataclass, field

import cv2
import numpy as np

from .fiducials import mean_square_distance


def expression_weights(fiducials: np.ndarray, target: np.ndarray, sigma: float, *,
                       relative: bool = False, min_photos: float = 0.0, distance=None) -> np.ndarray:
    """e_i = exp(-||F^T - F^i||² / 2σ²) for fiducials (n, 49, 2) and a target (49, 2), in
    canonical px (σ = 10 in the paper: a mean displacement of 2 px per point gives 0.14).

    ``relative``: divided by the largest (the nearest photo gets 1), for averages that are
    normalised anyway; it keeps them defined when every e_i underflows (a target far from
    every photo). Points that are NaN in a photo or the target are left out of its distance,
    which is scaled back to all points: a turned photo is compared on its visible half.

    ``min_photos`` (not in the paper; 0: σ as given): σ is widened, for this target only, to the
    smallest whose weights draw on that many photos (:func:`photos_drawn`, :func:`widened`), so that a
    target few photos are near (an expression B rarely makes) is not made of a handful of photos, their
    accessories and their misalignments.

    ``distance`` (not in the paper): a function (fiducials, target) -> (n,) squared distances (px²) that
    compares one part of the face instead (the heights of the eyes' lids,
    :func:`~persona.plugins.face.fiducials.gap_square_distance`, give the eyes' own weights, which follow how
    open the target's eyes are whatever its mouth does; :func:`~persona.plugins.face.brows.square_distance`
    the brows')."""
    if distance is None:
        d2 = np.shape(fiducials)[1] * mean_square_distance(fiducials, target)  # over the shared points, scaled to all
    else:
        d2 = np.array(distance(fiducials, target), np.float64)
    d2[np.isnan(d2)] = np.inf  # no point in common
    if min_photos > 0:
        sigma = widened(d2, sigma, min_photos)
    return np.exp(-(d2 - (d2.min() if relative else 0.0)) / (2.0 * sigma ** 2))


def photos_drawn(e: np.ndarray) -> float:
    """(Σ e_i)² / Σ e_i²: how many photos weights e (n,) draw on (n for equal weights, 1 for one photo)."""
    e = np.asarray(e, np.float64)
    return float(e.sum() ** 2 / max((e ** 2).sum(), np.finfo(float).tiny))


def widened(d2: np.ndarray, sigma: float, photos: float, *, steps: int = 30) -> float:
    """The smallest σ' ≥ σ (to 0.1 %, by bisection in log σ) whose weights exp(-d²/2σ'²) over the squared
    distances ``d2`` (n,; ``inf`` for a photo with none) draw on ``photos`` photos (:func:`photos_drawn`),
    or on all the finite ones, about equally, when they are fewer; σ itself when its weights draw on that
    many already. The count does not depend on the nearest distance, which is taken off (no underflow)."""
    d2 = np.asarray(d2, np.float64)
    d2 = d2[np.isfinite(d2)]
    d2 = d2 - d2.min() if len(d2) else d2
    want = min(photos, len(d2))

    def drawn(log_s: float) -> float:
        return photos_drawn(np.exp(-d2 / (2.0 * np.exp(log_s) ** 2)))

    low = high = np.log(sigma)
    if len(d2) == 0 or drawn(low) >= want:
        return sigma
    for _ in range(40):  # until σ is past it (4^40: the weights all but equal)
        low, high = high, high + np.log(4.0)
        if drawn(high) >= want:
            break
    for _ in range(steps):
        middle = (low + high) / 2
        low, high = (middle, high) if drawn(middle) < want else (low, middle)
    return float(np.exp(high))


def seen_sums(images: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Σ_i valid_i · image_i (H, W, C), Σ_i valid_i (H, W)) over photos (n, H, W, C): summed over
    shards of a collection, :func:`seen_mean` of them is the collection's."""
    return np.einsum("nhw,nhwc->hwc", valid.astype(np.float32), images), valid.sum(axis=0)


def seen_mean(total: np.ndarray, count: np.ndarray) -> np.ndarray:
    """The mean image of the photos where they see it (0 where none does), from :func:`seen_sums`."""
    return total / np.maximum(count, 1)[..., None]


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


def chosen(e: np.ndarray, skip: float) -> np.ndarray:
    """Expression weights (f, n), one row per target, float32, with those below ``skip`` × their
    row's largest set to 0: whatever their detail, their share of every level but the two coarsest
    is below that, so they are left out of the sums (:class:`BlendSums`)."""
    e = np.atleast_2d(np.asarray(e, np.float64))
    top = e.max(axis=1, keepdims=True)
    return np.where((e >= skip * top) & (top > 0), e, 0.0).astype(np.float32)


def given_back(band: np.ndarray, seen: np.ndarray, photo: float, share: float) -> float:
    """The factor on a blended band (h, w, C) that gives back ``share`` of the energy it lost against
    one photo's (``photo``, the mean over the pixels ``seen``): √(1 + share (E / e - 1)), e the band's
    own mean energy there; 1 where the blend lost nothing."""
    have = float(np.mean(band[seen] ** 2)) if seen.any() else 0.0
    if have <= 0 or photo <= have:
        return 1.0
    return float(np.sqrt(1 + share * (photo / have - 1)))


@dataclass
class BlendTotals:
    """What Eq. 3 takes of every photo whatever the target, per level k: Σ_i P^i, Σ_i Q^i, and
    Σ_i mean_c (P^i)² / Q^i (the numerator of the band energy one photo has: :meth:`photo_energy`);
    and the uniform term's τ l^-β per level. Small (one pyramid each): a blend over photos held
    shard by shard needs only these of the others."""

    weighted: list[np.ndarray]
    detail: list[np.ndarray]
    energy: list[np.ndarray]
    bias: np.ndarray

    @classmethod
    def of(cls, weighted: list[np.ndarray], detail: list[np.ndarray], bias: np.ndarray) -> "BlendTotals":
        energy = []
        for p_k, q_k in zip(weighted, detail):
            total = np.zeros(q_k.shape[1:3], np.float64)
            for p, q in zip(p_k, q_k):
                total += np.divide(np.mean(p ** 2, axis=-1), q[..., 0], out=np.zeros(q.shape[:2], np.float32),
                                   where=q[..., 0] > 0)
            energy.append(total)
        return cls([p.sum(axis=0) for p in weighted], [q.sum(axis=0) for q in detail], energy, np.asarray(bias))

    def __add__(self, other: "BlendTotals") -> "BlendTotals":
        """The totals of two disjoint sets of photos together."""
        return BlendTotals([a + b for a, b in zip(self.weighted, other.weighted)],
                           [a + b for a, b in zip(self.detail, other.detail)],
                           [a + b for a, b in zip(self.energy, other.energy)], self.bias)

    @property
    def levels(self) -> int:
        return len(self.weighted)

    @functools.cached_property
    def photo_energy(self) -> list[float]:
        """Per level, the band energy one photo has, over every pixel a photo sees: the detail-weighted
        mean over the photos of their band's squared value (mean over channels)."""
        out = []
        for energy, detail in zip(self.energy, self.detail):
            seen = detail[..., 0] > 0
            out.append(float(np.mean(energy[seen] / detail[..., 0][seen])) if seen.any() else 0.0)
        return out


@dataclass
class BlendSums:
    """Eq. 3's target-dependent sums for f targets, per level k: ``num[k]`` (f, h_k, w_k, C) =
    Σ_i e_i P^i and ``den[k]`` (f, h_k, w_k, 1) = Σ_i e_i Q^i. Photos can be added a shard at a
    time (:meth:`add`); :meth:`finish` makes the blended images. A target t in ``bands`` is summed only
    over the image rows ``bands[t]`` = (top, bottom) of the finest level (the same band of every level):
    one whose blend is used only there (the eyes' own rows), the rest left at no expression weight."""

    num: list[np.ndarray]
    den: list[np.ndarray]
    bands: dict[int, tuple[int, int]] = field(default_factory=dict)

    @classmethod
    def zeros(cls, targets: int, totals: BlendTotals, bands: dict[int, tuple[int, int]] | None = None) -> "BlendSums":
        return cls([np.zeros((targets, *p.shape), np.float32) for p in totals.weighted],
                   [np.zeros((targets, *q.shape), np.float32) for q in totals.detail], dict(bands or {}))

    def _span(self, t: int, k: int) -> tuple[int, int]:
        """The rows of target t's level k that :meth:`add` sums over."""
        height = self.num[k].shape[1]
        if t not in self.bands:
            return 0, height
        top, bottom = self.bands[t]
        scale = height / self.num[0].shape[1]
        return max(int(np.floor(top * scale)), 0), min(int(np.ceil(bottom * scale)), height)

    def add(self, weighted: list[np.ndarray], detail: list[np.ndarray], e: np.ndarray) -> None:
        """Add photos: their cache levels (m, h_k, w_k, ·) and their :func:`chosen` weights (f, m). The targets
        summed over the same rows are summed together, as one matrix product per level: each photo's
        levels are read once for all of them (a product per target read them once per target)."""
        e = np.asarray(e, np.float32)
        groups: dict[tuple[int, int] | None, list[int]] = {}
        for t in np.flatnonzero(e.any(axis=1)):
            groups.setdefault(self.bands.get(int(t)), []).append(int(t))
        for band, targets in groups.items():
            t0 = targets[0]  # every target of a group sums the same rows
            for k in range(len(self.num)):
                top, bottom = self._span(t0, k)
                for stack, out in ((weighted[k], self.num[k]), (detail[k], self.den[k])):
                    flat, sums = stack.reshape(len(stack), -1), out.reshape(len(out), -1)
                    a, b = top * flat.shape[1] // out.shape[1], bottom * flat.shape[1] // out.shape[1]
                    for t, row in zip(targets, e[targets] @ flat[:, a:b]):
                        sums[t, a:b] += row

    def band(self, totals: BlendTotals, k: int, t: int) -> tuple[np.ndarray, np.ndarray]:
        """Target t's level k, (h_k, w_k, C) (num + c Σ P) / (den + c Σ Q) with Σ over all photos'
        totals (the coarsest, c infinite, the totals' own ratio; 0 where no photo sees the pixel),
        and where a photo sees it (h_k, w_k) bool."""
        c = totals.bias[k]
        if np.isinf(c):  # l = 0: uniform, the expression weight drops out
            num, den = totals.weighted[k], totals.detail[k]
        else:
            num = self.num[k][t] + np.float32(c) * totals.weighted[k]
            den = self.den[k][t] + np.float32(c) * totals.detail[k]
        return num / np.where(den > 0, den, np.inf), den[..., 0] > 0

    def detail_gains(self, totals: BlendTotals, share: float, t: int, *, finest: float | None = None) -> list[float]:
        """Per level but the two coarsest, the factor that gives back ``share`` of the band energy
        target t's blend lost against one photo's (:func:`given_back`), ``finest`` (default: ``share``)
        at the finest level; none where every share is 0."""
        shares = [share if k or finest is None else finest for k in range(totals.levels - 2)]
        if max(shares, default=0) <= 0:
            return []
        return [given_back(*self.band(totals, k, t), totals.photo_energy[k], s) for k, s in enumerate(shares)]

    def finish(self, totals: BlendTotals, *, gains=(), rows=None, held: int | None = None) -> np.ndarray:
        """The blended images (f, H, W, C) of the targets ``rows`` (default: all), each the collapse
        of its levels (:meth:`band`). Not in the paper: level k multiplied by ``gains[k]`` where given
        (:meth:`detail_gains`): a weighted mean of photos whose fine detail does not coincide (skin,
        pores, the exact place of a crease) has less of it than any one photo. With ``held``, what the
        gain adds is target ``held``'s band rather than each target's own: level k + (gains[k] - 1) ×
        the held target's level k, the same in every image, so the detail given back holds still
        while the photos each target takes change."""
        extra = [np.float32(g - 1) * self.band(totals, k, held)[0] for k, g in enumerate(gains)] \
            if held is not None else []
        images = []
        for t in range(len(self.num[0])) if rows is None else rows:
            pyramid = [self.band(totals, k, t)[0] for k in range(totals.levels)]
            for k, gain in enumerate(gains):
                if held is None:
                    pyramid[k] *= np.float32(gain)
                else:
                    pyramid[k] += extra[k]
            images.append(collapse(pyramid))
        return np.stack(images)


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

    @functools.cached_property
    def totals(self) -> BlendTotals:
        """The sums over all photos shared by every target."""
        return BlendTotals.of(self.weighted, self.detail, self.bias)

    @classmethod
    def build(cls, images: np.ndarray, valid: np.ndarray, *, levels: int, alpha: float, beta: float,
              tau: float, blur: float = 1.0, floor: float = 1e-6, margin: int = 2,
              confidence: np.ndarray | None = None, fill: np.ndarray | None = None) -> "BlendCache":
        """images: (n, H, W, C) float aligned photos; valid: (n, H, W) bool; confidence: None or
        (n, H, W) in [0, 1], each photo's local alignment confidence, a factor of its detail
        response L^i (so of its weight at every level): where a photo failed to register
        (a tear, a misplaced feature) it cannot dominate the fine levels however sharp it is.

        A photo's unseen pixels are filled with ``fill`` (H, W, C), by default the mean of the photos
        that see them (:func:`seen_mean`), before its pyramid is built, so its bands carry no edge
        where its view ends; its weight there is zero, and ``margin`` px inside that edge too
        (resampling blurs the last pixels). A cache built a shard of photos at a time is given the
        fill of them all."""
        n = len(images)
        if fill is None:
            fill = seen_mean(*seen_sums(images, valid))
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

    def blend(self, e: np.ndarray, *, skip: float = 1e-6, share: float = 0.0,
              finest: float | None = None) -> np.ndarray:
        """The blended image (H, W, C) for expression weights e (n,): the photos whose e is below
        ``skip`` × max(e) are left out of the sums (:func:`chosen`); ``share`` of the fine energy it
        lost given back, ``finest`` at the finest level (:meth:`BlendSums.detail_gains`)."""
        sums = BlendSums.zeros(1, self.totals)
        sums.add(self.weighted, self.detail, chosen(e, skip))
        return sums.finish(self.totals, gains=sums.detail_gains(self.totals, share, 0, finest=finest))[0]

    def weights(self, e: np.ndarray) -> list[np.ndarray]:
        """The normalised W̃^i_l per level, (n, h_k, w_k): for tests and pictures."""
        out = []
        for k in range(self.levels):
            q, c = self.detail[k][..., 0], self.bias[k]
            w = q if np.isinf(c) else (np.asarray(e, np.float32)[:, None, None] + np.float32(c)) * q
            total = w.sum(axis=0)
            out.append(w / np.where(total > 0, total, np.inf))
        return out

"""Statistics of pose-corrected fiducials across a collection (docs/fiducials.md).

A photo's 49 pose-corrected fiducials F^i may hold NaN points: the frontalizer marks a
landmark not visible where it falls on the self-occluded side of a turned face or has no
preimage on the template. Every statistic here ignores NaN points one by one, so a turned
photo still counts with its visible half, and is robust to a few photos whose landmarks or
pose failed altogether: those lie far from the collection's median shape and are screened
out (the ``screen`` stage) before the mean is taken.
"""

from __future__ import annotations

import warnings

import numpy as np

from .template import generic_template


def median_shape(fiducials: np.ndarray) -> np.ndarray:
    """(k, 2) per-point median of fiducials (n, k, 2) over the photos that see each point;
    NaN where no photo does. A few diverged photos cannot move it."""
    with warnings.catch_warnings():  # an all-NaN point stays NaN, silently
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(np.asarray(fiducials, np.float64), axis=0)


def mean_square_distance(fiducials: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(n,) mean squared distance (px²) of each photo's fiducials (n, k, 2) from a reference shape
    (k, 2), over the points both have (NaN in neither); NaN for a photo with no such point."""
    d2 = np.sum((np.asarray(fiducials, np.float64) - np.asarray(reference, np.float64)) ** 2, axis=-1)
    seen = np.isfinite(d2)
    count = seen.sum(axis=-1)
    return np.where(count > 0, np.where(seen, d2, 0.0).sum(axis=-1) / np.maximum(count, 1), np.nan)


def gap_square_distance(fiducials: np.ndarray, reference: np.ndarray, pairs) -> np.ndarray:
    """(n,) Σ over facing ``pairs`` of points (upper, lower) of the squared difference (px²) between each
    photo's height of the pair, lower minus upper y, in fiducials (n, k, 2), and the reference's (k, 2): how
    far apart a region's openings are (the eyes' lids: ``warp.FACING``) whatever the rest of the face does.
    A pair NaN in a photo or the reference is left out and the sum scaled back to all pairs; NaN when none
    is shared."""
    f, r = np.asarray(fiducials, np.float64), np.asarray(reference, np.float64)
    return scaled_sum(np.stack([((f[:, lo, 1] - f[:, up, 1]) - (r[lo, 1] - r[up, 1])) ** 2 for up, lo in pairs],
                               axis=-1))


def scaled_sum(d2: np.ndarray) -> np.ndarray:
    """(n,) the sum of squared differences (n, k) over the k terms that are finite, scaled back to all k (a
    term a photo does not have, a NaN point, counts as the mean of those it has); NaN where none is."""
    seen = np.isfinite(d2)
    count = seen.sum(axis=-1)
    return np.where(count > 0, np.where(seen, d2, 0.0).sum(axis=-1) * d2.shape[-1] / np.maximum(count, 1), np.nan)


def shape_distance(fiducials: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(n,) RMS distance (px) of each photo's fiducials (n, k, 2) from a reference shape (k, 2),
    over the points both have; NaN for a photo with no such point."""
    return np.sqrt(mean_square_distance(fiducials, reference))


def mean_shape(fiducials: np.ndarray, fallback: np.ndarray | None = None) -> np.ndarray:
    """(k, 2) per-point mean of fiducials (n, k, 2) over the photos that see each point (the
    collection's mean fiducials, taken after the screen); where none does, ``fallback`` (k, 2),
    by default the generic template's 49 fiducials."""
    f = np.asarray(fiducials, np.float64)
    if fallback is None:
        fallback = generic_template().fiducials3d[:, :2]
    seen = np.isfinite(f).all(axis=-1)
    count = seen.sum(axis=0)
    total = np.where(seen[..., None], f, 0.0).sum(axis=0)
    return np.where(count[:, None] > 0, total / np.maximum(count, 1)[:, None], fallback)


def similarity_residual(fiducials: np.ndarray, reference: np.ndarray) -> float:
    """RMS distance (px, at the reference's scale) of one photo's fiducials (k, 2) from a reference shape
    (k, 2) after the similarity (scale, rotation, shift) that fits them to it best, over the points both
    have: how far the photo's shape differs from the reference in everything a similarity cannot take
    out, the face's proportions and its expression. NaN with fewer than 3 such points."""
    f, r = np.asarray(fiducials, np.float64), np.asarray(reference, np.float64)
    seen = np.isfinite(f).all(axis=-1) & np.isfinite(r).all(axis=-1)
    if seen.sum() < 3:
        return float("nan")
    a, b = f[seen] - f[seen].mean(axis=0), r[seen] - r[seen].mean(axis=0)
    u, s, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(u @ vt))  # a rotation, never a mirror
    rotation = u @ np.diag([1.0, d]) @ vt
    scale = (s[0] + d * s[1]) / (a ** 2).sum()
    return float(np.sqrt(np.mean(np.sum((scale * a @ rotation - b) ** 2, axis=-1))))


def rest_shape(fiducials: np.ndarray, share: float = 1.0, fallback: np.ndarray | None = None) -> np.ndarray:
    """(k, 2) a face's neutral from its photos' fiducials (n, k, 2): the :func:`mean_shape` of the ``share``
    of them whose shape lies nearest the generic template's (:func:`similarity_residual`), whose mouth is
    closed and eyes and brows at rest. ``share`` 1 is the paper's neutral, the mean of every photo; a smaller
    share leaves out the photos furthest from a resting face, so that a collection (or a driver's clip)
    that holds an expression most of the time, a one-video puppet that frowns and gapes, still has its
    resting face as neutral; averaged over many photos, where the eyes look and how the head turns even out.
    Photos with fewer than 3 points are never among the nearest."""
    f = np.asarray(fiducials, np.float64)
    if share >= 1 or len(f) == 0:
        return mean_shape(f, fallback)
    template = generic_template().fiducials3d[:, :2]
    distance = np.array([similarity_residual(x, template) for x in f])
    ranked = np.argsort(np.where(np.isfinite(distance), distance, np.inf), kind="stable")
    keep = np.sort(ranked[:max(1, int(round(share * np.isfinite(distance).sum())))])
    return mean_shape(f[keep], fallback)

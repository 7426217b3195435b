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
    d2 = np.stack([((f[:, lo, 1] - f[:, up, 1]) - (r[lo, 1] - r[up, 1])) ** 2 for up, lo in pairs], axis=-1)
    seen = np.isfinite(d2)
    count = seen.sum(axis=-1)
    return np.where(count > 0, np.where(seen, d2, 0.0).sum(axis=-1) * len(pairs) / np.maximum(count, 1), np.nan)


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

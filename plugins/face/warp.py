"""Smoothing thin-plate splines (paper Eq. 1) and warps kept as sampling maps."""

from __future__ import annotations

import warnings
from typing import Literal

import cv2
import numpy as np
from scipy.interpolate import RBFInterpolator

from .template import IDX49

Scaling = Literal["objective", "diagonal", "wahba"]

#: (upper, lower) indices among the 49 fiducials of the points that face each other across an eye
#: (iBUG 37/41, 38/40, 43/47, 44/46: the first four) or the inner lips (61/67, 62/66, 63/65)
FACING = tuple((IDX49.index(a), IDX49.index(b))
               for a, b in ((37, 41), (38, 40), (43, 47), (44, 46), (61, 67), (62, 66), (63, 65)))

#: the upper lip's outer and inner points, and the lower lip's, among the 49 fiducials (the corners,
#: iBUG 48/54/60/64, belong to neither)
UPPER_LIP = tuple(IDX49.index(i) for i in (49, 50, 51, 52, 53, 61, 62, 63))
LOWER_LIP = tuple(IDX49.index(i) for i in (55, 56, 57, 58, 59, 65, 66, 67))


def tps_smoothing(lam: float, n_points: int, scaling: Scaling = "objective") -> float:
    """The diagonal term s of the TPS system (K + sI) for the paper's λ (ALGORITHMS §5.2).

    ``objective``: s = 8πλ, faithful to the written objective (the bending energy of a
    fitted spline is 8π aᵀKa); ``diagonal``: s = λ (λ put on the diagonal, Bookstein style);
    ``wahba``: s = 8πnλ (Wahba's normalised data term).
    """
    if scaling == "objective":
        return 8 * np.pi * lam
    if scaling == "diagonal":
        return float(lam)
    if scaling == "wahba":
        return 8 * np.pi * n_points * lam
    raise ValueError(f"unknown TPS scaling {scaling!r}: use objective, diagonal or wahba")


def compose(values: np.ndarray, at: np.ndarray, border: int = cv2.BORDER_CONSTANT) -> np.ndarray:
    """``values`` (H', W'[, C]) sampled bilinearly at the (H, W, 2) positions ``at`` (x, y): for two
    sampling maps, ``values ∘ at``. ``border``: the cv2 border mode beyond ``values``."""
    return cv2.remap(values, at[..., 0], at[..., 1], cv2.INTER_LINEAR, borderMode=border)


def tps_map(target: np.ndarray, source: np.ndarray, shape: tuple[int, int], *, lam: float = 10.0,
            scaling: Scaling = "objective", step: int = 1) -> np.ndarray:
    """Backward sampling map of the smoothing TPS r with r(target_k) ≈ source_k.

    Parameters
    ----------
    target, source : ndarray, shape (k, 2)
        Corresponding (x, y) points: where each point must land, and where it is now. Pairs with
        a NaN coordinate (a landmark not visible in the photo) are left out.
    shape : (H, W)
        The grid the map is evaluated on.
    lam : float
        λ of Eq. 1 (paper: 10), in the points' pixel units.
    step : int
        Evaluate the spline on every step-th pixel and interpolate bilinearly between
        (the spline is smooth: step 4 differs from exact by hundredths of a pixel, 15x faster).

    Returns
    -------
    map : ndarray, shape (H, W, 2), float32
        For each output pixel, the (x, y) to sample the source image at (``cv2.remap``).
    """
    target, source = np.asarray(target, float), np.asarray(source, float)
    pairs = np.isfinite(target).all(axis=1) & np.isfinite(source).all(axis=1)  # NaN: a point not visible
    spline = RBFInterpolator(target[pairs], source[pairs], kernel="thin_plate_spline",
                             smoothing=tps_smoothing(lam, int(pairs.sum()), scaling), degree=1)
    nodes, points = _nodes(shape, step)
    return _upsample(spline(points).reshape(*nodes, 2).astype(np.float32), shape, step)


def pin(map_: np.ndarray, target: np.ndarray, source: np.ndarray, *, lam: float = 1.0, step: int = 4) -> np.ndarray:
    """A sampling map ``map_`` (H, W, 2) corrected so that it sends each ``target`` point (k, 2, x y)
    to its ``source`` point: the smoothing TPS (λ ``lam``) of the misses ``source - map_(target)``
    is added. Pairs with a NaN are left out."""
    target = np.asarray(target, float)
    at = np.nan_to_num(target).astype(np.float32).reshape(1, -1, 2)
    miss = np.asarray(source, float) - compose(np.asarray(map_, np.float32), at, cv2.BORDER_REPLICATE)[0]
    return map_ + tps_map(target, miss, map_.shape[:2], lam=lam, step=step)


def _nodes(shape: tuple[int, int], step: int) -> tuple[tuple[int, int], np.ndarray]:
    """The coarse grid of every ``step``-th pixel, covering the last pixel: its shape, and its
    nodes' (x, y) as (n, 2)."""
    h, w = shape
    nodes = (-(-(h - 1) // step) + 1, -(-(w - 1) // step) + 1)
    ys, xs = np.mgrid[0:nodes[0], 0:nodes[1]] * step
    return nodes, np.c_[xs.ravel(), ys.ravel()]


def _upsample(coarse: np.ndarray, shape: tuple[int, int], step: int) -> np.ndarray:
    """The map on every pixel from its nodes on every ``step``-th pixel (bilinear)."""
    if step == 1:
        return coarse
    fy, fx = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float32) / step
    return cv2.remap(coarse, fx, fy, cv2.INTER_LINEAR)


def tps_weights(target: np.ndarray, points: np.ndarray, *, lam: float = 10.0,
                scaling: Scaling = "objective") -> np.ndarray:
    """(len(points), len(target)): the smoothing TPS through values at ``target`` points, read at
    ``points``, as a linear operator on those values (``weights @ values``)."""
    target = np.asarray(target, float)
    spline = RBFInterpolator(target, np.eye(len(target)), kernel="thin_plate_spline",
                             smoothing=tps_smoothing(lam, len(target), scaling), degree=1)
    return spline(np.asarray(points, float))


class TpsWarp:
    """The smoothing TPS to fixed ``target`` points as a linear operator on the ``source`` points.

    The spline's coefficients are linear in the values it interpolates, so its coarse map is
    ``weights @ source`` with ``weights`` (nodes x k) fitted once (slower than one :func:`tps_map`).
    Warping many point sets to the same target (every frame of a video) then costs one small
    product each."""

    def __init__(self, target: np.ndarray, shape: tuple[int, int], *, lam: float = 10.0,
                 scaling: Scaling = "objective", step: int = 1):
        self.shape, self.step = tuple(shape), step
        self.nodes, points = _nodes(shape, step)
        self.weights = tps_weights(target, points, lam=lam, scaling=scaling)

    def map(self, source: np.ndarray) -> np.ndarray:
        """(H, W, 2) float32: the backward sampling map of the spline with r(target_k) ≈ source_k."""
        coarse = (self.weights @ np.asarray(source, float)).reshape(*self.nodes, 2).astype(np.float32)
        return _upsample(coarse, self.shape, self.step)


def eye_mouth_scale(fiducials: np.ndarray) -> np.ndarray:
    """(sx, sy) size of a face from its 49 fiducials: the inter-ocular distance, and the
    distance from the eyes' midpoint to the mouth's centre."""
    with warnings.catch_warnings():  # NaN points (not visible) are left out; all-NaN stays NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        eyes_r, eyes_l = np.nanmean(fiducials[19:25], 0), np.nanmean(fiducials[25:31], 0)  # 36-41, 42-47
        mouth = np.nanmean(fiducials[31:43], 0)  # outer lips 48-59
    return np.array([np.linalg.norm(eyes_l - eyes_r), np.linalg.norm(mouth - (eyes_l + eyes_r) / 2)])


def eye_opening(fiducials: np.ndarray) -> float:
    """Mean height (px) between the upper and lower lids of a face's 49 fiducials."""
    return float(gap(fiducials, FACING[:4]))


def lip_gap(fiducials: np.ndarray) -> np.ndarray:
    """(...) mean height (px) between the inner lips of (..., 49, 2) fiducials (0 = closed)."""
    return gap(fiducials, FACING[4:])


def gap(fiducials: np.ndarray, pairs) -> np.ndarray:
    """Mean height of the :data:`FACING` ``pairs`` (lower minus upper) of (..., 49, 2) fiducials."""
    return np.nanmean([fiducials[..., lower, 1] - fiducials[..., upper, 1] for upper, lower in pairs], axis=0)


def retarget(driver: np.ndarray, driver_neutral: np.ndarray, puppet_neutral: np.ndarray,
             max_eye_ratio: float = 2.0, lips: str = "mean", widen: str = "opening") -> np.ndarray:
    """Target fiducials for the puppet: its neutral plus the driver's offsets from the driver's
    neutral, scaled per axis by the two faces' proportions (ALGORITHMS §16.7); the eyes' vertical
    offsets by the two faces' eye openings instead (clipped to [1/max_eye_ratio, max_eye_ratio]),
    so that the driver's blink closes the puppet's eyes, however their sizes differ. Lids and lips
    never pass each other (:func:`close_no_further`).

    lips : "mean" (the paper): the lips move by the driver's offsets from its neutral, about the
        puppet's, so the puppet's mean mouth (open, for a collection of people talking) is its mouth
        at rest. "closed": the gap between the inner lips is the driver's own, scaled by the faces'
        proportions, so the driver's closed lips close the puppet's; the upper and the lower lip
        each move by half the difference (their thickness kept), the corners as in "mean".
        "parted": as "mean", but never less open than "closed": where the driver's mean mouth is
        more open than the puppet's (a driver who smiles or talks through most of the clip), the
        paper's offsets shut the puppet's lips while the driver's are still apart.

    widen : "opening": the eyes open wider than their neutral by the ratio of the faces' eye openings,
        as they close. "face" (not in the paper): by the faces' proportions, the other points' scale: the
        lids still meet when the driver's do, but how far a lid lifts off the eyeball is the eyeball's,
        which goes with the face's size, not with how far apart the lids rest. Each facing pair of lids
        moves by the ratio as a whole; only the part of its offset that parts it wider is scaled anew.

    driver : (n, 49, 2); driver_neutral, puppet_neutral : (49, 2) -> (n, 49, 2)
    """
    sizes = eye_mouth_scale(puppet_neutral) / eye_mouth_scale(driver_neutral)
    scale = np.broadcast_to(sizes, (49, 2)).copy()
    eyes = [IDX49.index(i) for i in range(36, 48)]
    ratio = eye_opening(puppet_neutral) / eye_opening(driver_neutral)
    if np.isfinite(ratio) and ratio > 0:
        scale[eyes, 1] = np.clip(ratio, 1 / max_eye_ratio, max_eye_ratio)
    target = puppet_neutral + (driver - driver_neutral) * scale
    if lips not in ("mean", "parted", "closed"):
        raise ValueError(f'lips: "mean", "parted" or "closed", not "{lips}"')
    if widen not in ("opening", "face"):
        raise ValueError(f'widen: "opening" or "face", not "{widen}"')
    if widen == "face":
        for upper, lower in FACING[:4]:
            half = (driver[..., lower, 1] - driver_neutral[lower, 1]
                    - driver[..., upper, 1] + driver_neutral[upper, 1]) / 2  # > 0: the pair parts wider
            more = np.maximum(np.nan_to_num(half), 0) * (sizes[1] - scale[lower, 1])
            target[..., upper, 1] -= more
            target[..., lower, 1] += more
    if lips != "mean":
        shift = lip_gap(target) - sizes[1] * lip_gap(driver)  # how much more open than the driver's, scaled
        shift = np.nan_to_num(np.minimum(shift, 0) if lips == "parted" else shift)
        target[..., UPPER_LIP, 1] += shift[..., None] / 2
        target[..., LOWER_LIP, 1] -= shift[..., None] / 2
    return close_no_further(target)


def close_no_further(fiducials: np.ndarray) -> np.ndarray:
    """(..., 49, 2) fiducials whose upper lids and lips do not pass below the lower ones: where a
    :data:`FACING` pair crossed (the driver's blink scaled onto a smaller eye overshoots), both
    points take their mean height, i.e. the eye or the mouth is just closed."""
    out = np.array(fiducials, np.float64, copy=True)
    upper, lower = (list(i) for i in zip(*FACING))
    top, bottom = out[..., upper, 1], out[..., lower, 1]
    crossed = top > bottom
    middle = (top + bottom) / 2
    out[..., upper, 1] = np.where(crossed, middle, top)
    out[..., lower, 1] = np.where(crossed, middle, bottom)
    return out

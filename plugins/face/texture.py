"""Aligning a photo collection to a target expression (paper §5, ALGORITHMS §12.2).

Each photo i is warped to the target fiducials F^T in two steps, kept as sampling maps so the
raw photo is sampled once:

1. a smoothing thin-plate spline r_i with r_i(F^T) ≈ F^i (λ = 10), composed with the photo's
   frontalizing map: c_i = fmap_i ∘ r_i;
2. a dense flow w_i from the photo's rank-k projection Î^i to the TPS-warped photo I^i, on the
   basis of all TPS-warped photos: Î^i has the collection's geometry at the target and photo
   i's lighting, so the flow moves what the spline missed (the mouth's inner shape, creases)
   without fighting the light. The map becomes d_i(x) = c_i(x + w_i(x)).

Reference mode (the paper's Fig. 5): when the target is a photo I^T, the flow w_T from I^T to
its own projection Î^T takes the reference grid to the "average" grid, and d_i <- d_i(x + w_T(x))
puts every photo's detail where the reference has it.

Where the flow fails on a photo, its aligned version tears (a seam where the flow jumps) or keeps
a feature away from the target's place. Two local measures of that misfit come with the result,
both blurred squares over σ = ``MISFIT_BLUR`` px on the output grid, for a blend to down-weight
such photos there (``MultiscaleTexture``'s alignment confidence):

* ``stretch``: |∇w_i|², the squared Frobenius norm of the flow's Jacobian (0 for a rigid shift;
  a tear is a jump in w_i);
* ``residual``: the squared difference of the band-passed (difference of Gaussians, σ 1 and
  4 px) grey aligned photo and its projection Î^i, grey in [0, 1]: what the flow could not
  bring onto the collection's geometry at the target.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..kinds import FlowBackend, TexturePhotos
from .blend import seen_mean, seen_sums
from .subspace import project, streamed_svd
from .template import CANONICAL_HEIGHT as H, CANONICAL_WIDTH as W
from .warp import compose, tps_map


#: σ (px) of the blur of the local misfit measures (``Aligned.stretch`` and ``residual``)
MISFIT_BLUR = 3.0


@dataclass(frozen=True)
class Aligned:
    """The collection aligned to one target: rgb (n, H, W, 3) float32 in [0, 255] and
    valid (n, H, W) bool, where each photo saw the aligned pixel; after the dense flow also
    the local misfit measures stretch and residual (n, H, W) float32 (see the module's
    docstring), None for other alignments."""

    rgb: np.ndarray
    valid: np.ndarray
    stretch: np.ndarray | None = None
    residual: np.ndarray | None = None


def _grid() -> np.ndarray:
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    return np.stack([xs, ys], axis=-1)


def _sample(photo: np.ndarray, fmap: np.ndarray) -> np.ndarray:
    return cv2.remap(photo, fmap[..., 0], fmap[..., 1], cv2.INTER_LINEAR).astype(np.float32)


def to_grey(rgb: np.ndarray) -> np.ndarray:
    """Rec. 601 grey in [0, 1] of RGB in [0, 255], (..., 3) -> (...)."""
    return (rgb @ np.float32([0.299, 0.587, 0.114])) / 255


def bandpass(grey: np.ndarray) -> np.ndarray:
    """Difference of Gaussians, σ 1 and 4 px: the fine detail a blend may blur or misplace."""
    return cv2.GaussianBlur(grey, (0, 0), 1.0) - cv2.GaussianBlur(grey, (0, 0), 4.0)


def _stretch(w: np.ndarray) -> np.ndarray:
    """|∇w|² (H, W) of a flow field (H, W, 2): the sum of its four squared derivatives."""
    gx = cv2.Sobel(w, cv2.CV_32F, 1, 0, ksize=3) / 8
    gy = cv2.Sobel(w, cv2.CV_32F, 0, 1, ksize=3) / 8
    return (gx ** 2 + gy ** 2).sum(axis=-1)


def rigid(photos: TexturePhotos) -> Aligned:
    """The frontalized photos, unaligned non-rigidly (the paper's baseline iii)."""
    rgb = np.stack([_sample(p, m) for p, m in zip(photos.photos, photos.maps)])
    return Aligned(rgb, photos.visible.copy())


def tps_aligned(photos: TexturePhotos, target: np.ndarray, *, tps_lambda: float) -> tuple[Aligned, np.ndarray]:
    """Step 1 for every photo: (the TPS-warped photos, their maps (n, H, W, 2) to the raw photos)."""
    n = len(photos)
    maps = np.empty((n, H, W, 2), np.float32)
    rgb = np.empty((n, H, W, 3), np.float32)
    valid = np.empty((n, H, W), bool)
    for i in range(n):
        r = tps_map(target, photos.fiducials[i], (H, W), lam=tps_lambda, step=4)
        maps[i] = compose(photos.maps[i], r)
        rgb[i] = _sample(photos.photos[i], maps[i])
        valid[i] = compose(photos.visible[i].astype(np.float32), r) > 0.99
    return Aligned(rgb, valid), maps


_recent: list[tuple[tuple, TexturePhotos, Aligned]] = []


def align(photos: TexturePhotos, target: np.ndarray, flow: FlowBackend, *, tps_lambda: float = 10.0,
          rank: int = 4, reference: np.ndarray | None = None) -> Aligned:
    """Every photo TPS- and flow-aligned to the target fiducials (49, 2); ``reference`` (H, W, 3)
    is the target photo in reference mode (see the module's docstring).

    The last two results are remembered, so methods that share an alignment (``multiscale``
    and ``prewarped`` on one target, ``static`` on every target) compute it once."""
    key = (np.asarray(target, np.float64).tobytes(), None if reference is None else hash(reference.tobytes()),
           type(flow).__name__, repr(flow.params), tps_lambda, rank)
    for k, p, result in _recent:
        if k == key and p is photos:
            return result
    result = _align(photos, target, flow, tps_lambda, rank, reference)
    _recent[:] = [(key, photos, result)] + _recent[:1]
    return result


def _align(photos, target, flow, tps_lambda, rank, reference) -> Aligned:
    warped, maps = tps_aligned(photos, target, tps_lambda=tps_lambda)
    basis = warped_basis(to_grey(warped.rgb), warped.valid, seen_mean(*seen_sums(warped.rgb, warped.valid)), rank)
    shift = None
    if reference is not None:
        ref = to_grey(np.asarray(reference, np.float32))
        seen = ref > 0
        shift = _grid() + flow.flow(ref, np.clip(project(ref, basis, seen), 0, 1).astype(np.float32), seen)
    return flow_aligned(photos, warped, maps, basis, flow, shift=shift)


def flow_aligned(photos: TexturePhotos, warped: Aligned, maps: np.ndarray, basis: np.ndarray, flow: FlowBackend, *,
                 shift: np.ndarray | None = None) -> Aligned:
    """Step 2 for every photo: the TPS-warped photos (:func:`tps_aligned`: ``warped`` and their
    ``maps``) flowed to their own projections on ``basis`` (k, H, W), the raw photo sampled once
    through both, with the misfit measures; ``shift`` the reference mode's grid (or None)."""
    grey = to_grey(warped.rgb)
    grid = _grid()
    rgb = np.empty_like(warped.rgb)
    valid = np.empty_like(warped.valid)
    stretch = np.empty(valid.shape, np.float32)
    residual = np.empty(valid.shape, np.float32)
    for i in range(len(photos)):
        seen = warped.valid[i]
        projection = np.clip(project(grey[i], basis, seen), 0, 1).astype(np.float32)
        w = flow.flow(projection, grey[i], seen)
        moved = grid + w  # x + w_i(x)
        stretch[i] = _stretch(w)
        if shift is not None:
            moved = compose(moved, shift)  # (x + w_i)(x + w_T(x))
            stretch[i] = compose(stretch[i], shift)
            projection = compose(projection, shift)
        rgb[i] = _sample(photos.photos[i], compose(maps[i], moved))
        valid[i] = compose(seen.astype(np.float32), moved) > 0.99
        residual[i] = (bandpass(to_grey(rgb[i])) - bandpass(projection)) ** 2
        for m in (stretch, residual):
            m[i] = cv2.GaussianBlur(m[i], (0, 0), MISFIT_BLUR)
    rgb[~valid] = 0
    return Aligned(rgb, valid, stretch, residual)


def warped_basis(grey, valid, fill: np.ndarray, rank: int, compute=lambda *arrays: arrays, keep=None) -> np.ndarray:
    """Rank-k basis (k, H, W) of TPS-warped grey photos (n, H, W), NumPy or Dask arrays; unseen
    pixels take the grey of ``fill`` (H, W, 3), the collection's mean where it sees (they carry no
    light of their own). A randomised SVD (subspace.streamed_svd) whose products ``compute`` makes:
    on Dask arrays a pass over the shards each; over the photos where ``keep`` (n,) is true."""
    rows = np.where(valid, grey, to_grey(np.asarray(fill, np.float32))).reshape(len(grey), -1)
    return streamed_svd(rows, rank, compute, keep=keep)[1].reshape(rank, H, W).astype(np.float32)

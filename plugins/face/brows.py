"""The brows' own expression weight: the forehead's texture taken from B's photos whose brows do what the
target's do.

Not in the paper, whose expression weight compares all 49 fiducials at once. The mouth moves furthest, so
it decides which photos a frame's texture is made of, and the brows and forehead come with whatever those
photos' brows were doing: a driver's raised brows drawn with the creases of photos that frowned with their
mouths open as the driver's. Here the region above the eyes (the brows, the forehead, the creases between
the brows down to the eyes' inner corners) is blended with weights of its own, over where each brow's five
points lie from its eye's middle: raised, lowered or drawn together, whatever the mouth does. The eyes take
theirs (``eye_sigma``) and the rest of the face the paper's. It cannot give a face creases none of its
photos has (docs/expression.md, "The brows").
"""

from __future__ import annotations

import cv2
import numpy as np

from .fiducials import scaled_sum
from .template import IDX49

#: per brow (the image's left, then right): its five points and its eye's six among the 49 fiducials
BROWS = ((tuple(IDX49.index(i) for i in range(17, 22)), tuple(IDX49.index(i) for i in range(36, 42))),
         (tuple(IDX49.index(i) for i in range(22, 27)), tuple(IDX49.index(i) for i in range(42, 48))))

#: the upper lids' points with the eyes' corners, left to right across the face (iBUG), along which the
#: region's lower edge runs
_LIDS = tuple(IDX49.index(i) for i in (36, 37, 38, 39, 42, 43, 44, 45))


def _offsets(fiducials: np.ndarray) -> np.ndarray:
    """(..., 10, 2) each brow point's offset from the middle of its eye's six points."""
    f = np.asarray(fiducials, np.float64)
    return np.concatenate([f[..., list(brow), :] - f[..., list(eye), :].mean(axis=-2, keepdims=True)
                           for brow, eye in BROWS], axis=-2)


def square_distance(fiducials: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(n,) Σ over the ten brow points of the squared difference (px²) between each photo's offset of the point
    from its eye's middle, in fiducials (n, 49, 2), and the reference's (49, 2). A point NaN in a photo or the
    reference is left out and the sum scaled back to all ten; NaN when none is shared."""
    return scaled_sum(np.sum((_offsets(fiducials) - _offsets(reference)) ** 2, axis=-1))


def region(neutral: np.ndarray, shape: tuple[int, int], *, above: float = 3.0, blur: float = 3.0) -> np.ndarray:
    """(H, W) float32 in [0, 1]: where a texture at the geometry of the fiducials ``neutral`` (49, 2) shows the
    brows and what they move: every texel above a line ``above`` texels over the upper lids, straight between
    the eyes' inner corners (the creases between the brows reach down there) and level beyond their outer
    ones, feathered by a Gaussian of σ ``blur``. Nothing where a lid's point is unknown."""
    points = np.asarray(neutral, np.float64)[list(_LIDS)]
    if not np.isfinite(points).all():
        return np.zeros(shape, np.float32)
    edge = np.interp(np.arange(shape[1]), points[:, 0], points[:, 1] - above)
    mask = (np.arange(shape[0])[:, None] < edge[None, :]).astype(np.float32)
    return cv2.GaussianBlur(mask, (0, 0), blur) if blur else mask

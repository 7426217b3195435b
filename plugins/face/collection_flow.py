"""Collection flow ([15], ALGORITHMS §6): one photo aligned to its collection's average face.

The photo's frontalizing map (where each canonical pixel is in the photo, from the frontalize
backend) is first bent by a smoothing TPS that takes the collection's mean fiducials to the
photo's own; the photo, warped so, is then aligned by dense flow to its own projection onto the
collection's rank-k appearance subspace (what this face would look like with the collection's
average geometry and its own lighting and expression). The maps are composed and the raw photo
is sampled once, so it is interpolated once, not three times.
"""

from __future__ import annotations

import cv2
import numpy as np

from .subspace import project
from .warp import tps_map


def collection_flow(photo: np.ndarray, to_photo: np.ndarray, fiducials: np.ndarray, visible: np.ndarray,
                    mean_fiducials: np.ndarray, basis: np.ndarray, tps_lambda: float, flow) -> dict[str, np.ndarray]:
    """Align one photo to the collection's average face.

    Parameters
    ----------
    photo : ndarray, shape (h, w, 3), uint8
        The photo as taken.
    to_photo : ndarray, shape (H, W, 2), float32
        Its frontalizing map: the photo's (x, y) seen by each canonical pixel.
    fiducials : ndarray, shape (49, 2)
        Its canonical fiducials (NaN where not seen).
    visible : ndarray, shape (H, W), bool
        The canonical pixels the photo sees.
    mean_fiducials : ndarray, shape (49, 2)
        The collection's mean fiducials.
    basis : ndarray, shape (k, H, W, 3)
        The collection's appearance subspace.
    tps_lambda : float
        Smoothing of the TPS from the mean fiducials to the photo's.
    flow : flow backend
        Its ``flow(target, image, mask)`` gives the flow (H, W, 2) from ``target`` to ``image``.

    Returns
    -------
    dict
        ``collection/rgb`` (H, W, 3) uint8, the photo aligned to the average (0 where not seen);
        ``collection/mask`` (H, W) bool, where it is seen; ``collection/map`` (H, W, 2) float32,
        the photo's (x, y) of each canonical pixel, every warp composed.
    """
    h, w = to_photo.shape[:2]
    tps = tps_map(mean_fiducials, fiducials, (h, w), lam=tps_lambda, step=4)
    bent = cv2.remap(to_photo, tps[..., 0], tps[..., 1], cv2.INTER_LINEAR)
    warped = cv2.remap(photo, bent[..., 0], bent[..., 1], cv2.INTER_LINEAR).astype(np.float32) / 255
    seen = cv2.remap(visible.astype(np.float32), tps[..., 0], tps[..., 1], cv2.INTER_LINEAR) > 0.99
    target = np.clip(project(warped, basis, seen), 0, 1).astype(np.float32)
    field = flow.flow(target, warped, seen)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    fx, fy = xs + field[..., 0], ys + field[..., 1]
    composed = cv2.remap(bent, fx, fy, cv2.INTER_LINEAR)
    rgb = cv2.remap(photo, composed[..., 0], composed[..., 1], cv2.INTER_LINEAR)
    mask = cv2.remap(seen.astype(np.float32), fx, fy, cv2.INTER_LINEAR) > 0.99
    rgb[~mask] = 0
    return {"collection/rgb": rgb, "collection/mask": mask, "collection/map": composed}

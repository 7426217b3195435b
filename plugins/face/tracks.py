"""Per-frame tracks: filling the frames of a video where no face was found."""

from __future__ import annotations

import numpy as np


def bridge(values: np.ndarray, found: np.ndarray) -> np.ndarray:
    """Fill frames without a face by linear interpolation in time between the nearest
    frames with one (held constant before the first and after the last).

    values : (n, ...) float — per-frame values (pose, fiducials), anything where not found; a NaN
        value (a fiducial not visible in that frame) is bridged from the frames that have it, and
        stays NaN only when no frame does
    found : (n,) bool
    """
    values = np.asarray(values, dtype=np.float64)
    if not found.any():
        raise ValueError("no frame has a face: nothing to bridge from")
    frames = np.arange(len(values))
    flat = values.reshape(len(values), -1)
    out = np.empty_like(flat)
    for j in range(flat.shape[1]):
        use = found & np.isfinite(flat[:, j])  # a point not visible in a frame is bridged too
        out[:, j] = np.interp(frames, frames[use], flat[use, j]) if use.any() else np.nan
    return out.reshape(values.shape)

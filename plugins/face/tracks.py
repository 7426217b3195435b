"""Per-frame tracks: filling the frames of a video where no face was found."""

from __future__ import annotations

import numpy as np


def bridge(values: np.ndarray, found: np.ndarray) -> np.ndarray:
    """Fill frames without a face by linear interpolation in time between the nearest
    frames with one (held constant before the first and after the last).

    values : (n, ...) float — per-frame values (pose, fiducials), anything where not found
    found : (n,) bool
    """
    values = np.asarray(values, dtype=np.float64)
    if not found.any():
        raise ValueError("no frame has a face: nothing to bridge from")
    frames = np.arange(len(values))
    flat = values.reshape(len(values), -1)
    out = np.empty_like(flat)
    for j in range(flat.shape[1]):
        out[:, j] = np.interp(frames, frames[found], flat[found, j])
    return out.reshape(values.shape)

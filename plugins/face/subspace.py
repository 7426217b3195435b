"""The low-rank appearance subspace of an aligned collection (Kemelmacher-Shlizerman [14], [15]).

Lambertian faces under first-order spherical-harmonic light span 4 dimensions (an
ambient and three directional components), so the aligned photos of one person lie
near a rank-4 subspace. The mean is not subtracted: it lies in that span. The basis
itself is computed out of core by the DAG (a randomised SVD over shards); here are the
per-photo operations on it.
"""

from __future__ import annotations

import numpy as np


def project(image: np.ndarray, basis: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The rank-k projection Î = Bᵀc of an image, fitted where ``weights`` > 0.

    image : (H, W, C) or (p,) float
    basis : (k, ...) with the image's shape after the first axis; rows orthonormal
    weights : the image's shape without channels (or (p,)), e.g. the visibility mask;
        c = argmin ||w ⊙ (I - Bᵀc)|| (masked least squares), so pixels a photo does not
        see do not pull the fit (ALGORITHMS §7.1).
    """
    k = basis.shape[0]
    b = basis.reshape(k, -1).astype(np.float64)
    x = image.reshape(-1).astype(np.float64)
    if weights is None:
        coef = b @ x
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.size * (x.size // w.size) == x.size and w.size != x.size:
            w = np.repeat(w.reshape(-1), x.size // w.size)  # one weight per pixel, all channels
        w = w.reshape(-1)
        coef = np.linalg.lstsq((b * w).T, x * w, rcond=None)[0]
    return (coef @ b).reshape(image.shape)


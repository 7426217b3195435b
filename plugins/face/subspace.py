"""The low-rank appearance subspace of an aligned collection (Kemelmacher-Shlizerman [14], [15]).

Lambertian faces under first-order spherical-harmonic light span 4 dimensions (an
ambient and three directional components), so the aligned photos of one person lie
near a rank-4 subspace. The mean is not subtracted: it lies in that span. The basis
itself is computed out of core (:func:`streamed_svd`, a randomised SVD whose every pass streams
the shards once); here are that and the per-photo operations on it.
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


def transposed_product(rows, q: np.ndarray, compute, shards: int = 32) -> np.ndarray:
    """rowsᵀ q, (p, l), for a tall dask array ``rows`` (n, p) (or NumPy) and q (n, l), summed in the
    caller ``shards`` chunks of rows at a time. Each chunk's product is a (p, l) array the width of
    a face; in one graph over all of them the workers held many of those at once before the sum,
    and their peak grew with the rows (docs/batch.md)."""
    edges = np.cumsum((0, *getattr(rows, "chunks", ((len(rows),),))[0]))
    total = np.zeros((rows.shape[1], q.shape[1]), np.float64)
    for i in range(0, len(edges) - 1, shards):
        lo, hi = edges[i], edges[min(i + shards, len(edges) - 1)]
        total += compute(rows[lo:hi].T @ q[lo:hi])[0]
    return total


def streamed_svd(rows, rank: int, compute, *, keep=None, oversample: int = 10, power_iterations: int = 2,
                 seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Top ``rank`` singular values and right singular vectors (rank, p) of a tall dask array
    (or NumPy array), over the rows where ``keep`` (n,) bool is true (default: all).

    A randomised SVD (Halko et al. 2011) in which every product with ``rows`` is its own
    computation: each pass streams the shards once and keeps only small (n, l) or (p, l)
    results (the (p, l) ones a few shards at a time, :func:`transposed_product`), so memory does
    not grow with the number of rows (dask's ``svd_compressed`` computes all passes in one graph
    and holds every shard between them).

    The rows left out are set to 0 rather than indexed away: a zero row adds nothing to AᵀA, so
    the singular values and right vectors are those of the kept rows alone, and the array keeps
    its chunks. (Indexing a dask array with the kept rows' positions regroups its chunks: a
    worker's peak then grew with the collection, 0.35 -> 0.67 GiB from 500 to 2,000 rows of a
    face's size, against 0.24 -> 0.27 GiB from 500 to 5,000 with the zeros; docs/batch.md.)
    """
    if keep is not None:
        rows = np.where(np.asarray(keep, bool)[:, None], rows, np.zeros((), rows.dtype))  # dask's where on dask
    p = rows.shape[1]
    omega = np.random.default_rng(seed).standard_normal((p, rank + oversample)).astype(np.float32)
    q = np.linalg.qr(compute(rows @ omega)[0])[0]
    for _ in range(power_iterations):
        z = np.linalg.qr(transposed_product(rows, q.astype(np.float32), compute))[0]
        q = np.linalg.qr(compute(rows @ z.astype(np.float32))[0])[0]
    projected = transposed_product(rows, q.astype(np.float32), compute).T  # Qᵀ A, (l, p)
    _, singular, vt = np.linalg.svd(projected.astype(np.float64), full_matrices=False)
    return singular[:rank], vt[:rank]

import dask
import dask.array as da
import numpy as np

from persona.plugins.face.subspace import streamed_svd


def sync_compute(*arrays):
    return dask.compute(*arrays, scheduler="synchronous")


def test_streamed_svd_finds_the_top_subspace_of_a_tall_array():
    rng = np.random.default_rng(0)
    left, right = rng.normal(size=(60, 4)), rng.normal(size=(4, 500))
    matrix = (left * [9, 5, 3, 2]) @ right + 0.01 * rng.normal(size=(60, 500))
    rows = da.from_array(matrix.astype(np.float32), chunks=(8, 500))  # awkward chunks: 7 full + 1 of 4
    singular, basis = streamed_svd(rows, 4, sync_compute)
    exact = np.linalg.svd(matrix, full_matrices=False)
    np.testing.assert_allclose(singular, exact[1][:4], rtol=1e-3)
    # same subspace: projecting the exact basis onto ours loses nothing
    overlap = np.linalg.svd(basis @ exact[2][:4].T, compute_uv=False)
    assert overlap.min() > 0.9999
    np.testing.assert_allclose(basis @ basis.T, np.eye(4), atol=1e-5)

import dask
import dask.array as da
import numpy as np

from persona.plugins.face.subspace import streamed_svd, transposed_product


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


def test_rows_left_out_do_not_count_and_the_chunks_stay():
    """``keep`` leaves rows out as the SVD of the kept rows alone would: here the left-out rows
    are 100 times larger and of another subspace, so counting them in would change everything."""
    rng = np.random.default_rng(1)
    kept = (rng.normal(size=(40, 4)) * [9, 5, 3, 2]) @ rng.normal(size=(4, 300))
    stray = 100 * rng.normal(size=(20, 300))
    matrix = np.concatenate([kept, stray]).astype(np.float32)
    order = rng.permutation(60)
    keep = order < 40
    rows = da.from_array(matrix[order], chunks=(8, 300))
    singular, basis = streamed_svd(rows, 4, sync_compute, keep=keep)
    exact = np.linalg.svd(kept, full_matrices=False)
    np.testing.assert_allclose(singular, exact[1][:4], rtol=1e-3)
    assert np.linalg.svd(basis @ exact[2][:4].T, compute_uv=False).min() > 0.9999
    # the same on a NumPy array
    np.testing.assert_allclose(streamed_svd(matrix[order], 4, lambda *a: a, keep=keep)[0], singular, rtol=1e-5)


def test_the_wide_products_are_summed_a_few_shards_at_a_time():
    """rowsᵀ q gives a face-wide (p, l) array per shard; each computation takes in at most
    ``shards`` shards of rows, so no worker holds more of those at once, and the sum is exact."""
    rng = np.random.default_rng(2)
    matrix = rng.normal(size=(70, 300)).astype(np.float32)
    q = rng.normal(size=(70, 5)).astype(np.float32)
    read, seen = [], []

    def reading(block, block_info=None):
        read.append(block_info[0]["chunk-location"][0])
        return block

    rows = da.from_array(matrix, chunks=(4, 300)).map_blocks(reading, dtype=matrix.dtype)  # 18 shards, the last of 2

    def counting(*arrays):  # how many shards of rows each computation reads
        read.clear()
        out = sync_compute(*arrays)
        seen.append(len(set(read)))
        return out

    total = transposed_product(rows, q, counting, shards=5)
    np.testing.assert_allclose(total, matrix.T.astype(np.float64) @ q, rtol=1e-4, atol=1e-4)
    assert seen == [5, 5, 5, 3]
    np.testing.assert_allclose(transposed_product(matrix, q, lambda *a: a), total, rtol=1e-5, atol=1e-4)

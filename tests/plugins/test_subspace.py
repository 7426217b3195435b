import numpy as np

from persona.plugins.face.subspace import project


def orthonormal_basis(k, shape, seed=0):
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(int(np.prod(shape)), k)))
    return q.T.reshape(k, *shape)


def test_projection_of_an_image_in_the_span_returns_it():
    basis = orthonormal_basis(4, (20, 15, 3))
    image = np.tensordot([0.5, -1.0, 2.0, 0.3], basis, axes=1)
    np.testing.assert_allclose(project(image, basis), image, atol=1e-10)
    np.testing.assert_allclose(project(image, basis, np.ones((20, 15))), image, atol=1e-10)


def test_masked_projection_ignores_unseen_pixels():
    basis = orthonormal_basis(4, (20, 15, 3), seed=1)
    image = np.tensordot([1.0, 0.2, -0.4, 0.7], basis, axes=1)
    seen = np.ones((20, 15), bool)
    seen[:, :6] = False
    corrupted = image.copy()
    corrupted[~seen] = 5.0  # garbage where the photo does not see
    np.testing.assert_allclose(project(corrupted, basis, seen), image, atol=1e-8)
    assert np.abs(project(corrupted, basis) - image).max() > 0.1  # unmasked, the garbage pulls the fit


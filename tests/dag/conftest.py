"""Fixtures for pipeline tests."""

import shutil

import pytest

from persona.plugins.face import synthetic
from pipeline import local_cluster, make_certificates


@pytest.fixture(scope="session")
def synthetic_photos():
    """24 synthetic photos (seeded) with ground-truth landmarks."""
    return synthetic.make_collection(24, seed=7)


@pytest.fixture
def dask_cluster(tmp_path):
    """A real dask scheduler and two workers on 127.0.0.1, as separate processes."""
    yield from local_cluster(tmp_path)


@pytest.fixture
def tls_cluster(tmp_path):
    """The same speaking TLS only: the scheduler, the workers and the client present one
    certificate of a CA made here (:func:`make_certificates`). Yields (address, {ca_file, cert, key})."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed: it makes the test's certificates")
    from distributed.security import Security

    files = make_certificates(tmp_path / "tls")
    args = ["--tls-ca-file", files["ca_file"], "--tls-cert", files["cert"], "--tls-key", files["key"]]
    security = Security(tls_ca_file=files["ca_file"], tls_client_cert=files["cert"], tls_client_key=files["key"],
                        require_encryption=True)
    cluster = local_cluster(tmp_path, "tls", args, security)
    try:
        yield next(cluster), files
    finally:
        cluster.close()

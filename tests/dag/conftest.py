"""Fixtures for pipeline tests."""

import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from persona.plugins.face import synthetic
from pipeline import make_certificates


@pytest.fixture(scope="session")
def synthetic_photos():
    """24 synthetic photos (seeded) with ground-truth landmarks."""
    return synthetic.make_collection(24, seed=7)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cluster(folder: Path, protocol: str = "tcp", tls: list[str] = (), security=None):
    """A real dask scheduler and two workers on 127.0.0.1, as separate processes; yields the address."""
    port = _free_port()
    address = f"{protocol}://127.0.0.1:{port}"
    dask = str(Path(sys.executable).with_name("dask"))
    env = {**os.environ, "PERSONA_PLUGINS": ""}
    procs = [subprocess.Popen([dask, "scheduler", "--protocol", protocol, "--host", "127.0.0.1", "--port", str(port),
                               "--no-dashboard", *tls], env=env, cwd=folder,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    for _ in range(2):
        procs.append(subprocess.Popen([dask, "worker", address, "--nthreads", "1", "--no-dashboard",
                                       "--host", "127.0.0.1", *tls], env=env, cwd=folder,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    try:
        from distributed import Client

        with Client(address, timeout="60s", security=security) as client:
            client.wait_for_workers(2, timeout=60)
        yield address
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()


@pytest.fixture
def dask_cluster(tmp_path):
    """A real dask scheduler and two workers on 127.0.0.1, as separate processes."""
    yield from _cluster(tmp_path)


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
    cluster = _cluster(tmp_path, "tls", args, security)
    try:
        yield next(cluster), files
    finally:
        cluster.close()

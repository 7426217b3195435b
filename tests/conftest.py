"""Shared test setup.

- tests/ is on sys.path so that test modules can ``import badinput``;
- third-party plugins are not loaded (PERSONA_PLUGINS=""), so whatever happens to be
  installed cannot change the results;
- ``shared_data`` is ../shared/data, and tests that need it skip when it is absent.
"""

import os
import sys
from pathlib import Path

import pytest

_TESTS = Path(__file__).resolve().parent
if str(_TESTS) not in sys.path:
    sys.path.insert(0, str(_TESTS))

os.environ["PERSONA_PLUGINS"] = ""

SHARED_DATA = _TESTS.parent.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not (SHARED_DATA / "collections").is_dir():
        pytest.skip(f"real data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="session")
def s3_server():
    """A real S3 server on 127.0.0.1 (moto's, in a thread) for the session: its storage options
    (``endpoint_url``, ``key``, ``secret``). Skips when moto or s3fs is not installed."""
    pytest.importorskip("s3fs")
    server = pytest.importorskip("moto.server").ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    yield {"endpoint_url": f"http://{host}:{port}", "key": "persona-test-key", "secret": "persona-test-secret"}
    server.stop()


@pytest.fixture
def s3_bucket(s3_server, request):
    """A new, empty bucket on :func:`s3_server`, with this process's storage options set to reach it
    (and reset after): ``(bucket name, storage options)``."""
    import s3fs

    from persona.stores import storage

    name = "t-" + "".join(c if c.isalnum() else "-" for c in request.node.name.lower())[:50].strip("-")
    fs = s3fs.S3FileSystem(**s3_server, skip_instance_cache=True)
    fs.mkdir(name)
    storage.configure(s3_server)
    yield name, s3_server
    storage.configure(None)

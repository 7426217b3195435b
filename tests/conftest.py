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

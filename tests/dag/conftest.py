"""Fixtures for pipeline tests."""

import pytest

from persona.plugins.face import synthetic


@pytest.fixture(scope="session")
def synthetic_photos():
    """24 synthetic photos (seeded) with ground-truth landmarks."""
    return synthetic.make_collection(24, seed=7)

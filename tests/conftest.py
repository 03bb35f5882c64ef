"""Fixtures shared by the test modules."""

from __future__ import annotations

import os
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def real_data() -> Path:
    """The folder of real image sets with ground truth (COLMAP_EXT_DATA, as .ci/run sets
    it); tests that need it are skipped, saying so, when it is not set."""
    data = os.environ.get("COLMAP_EXT_DATA")
    if not data:
        pytest.skip("COLMAP_EXT_DATA is not set (the folder holding templeSparseRing/ and "
                    "dinoSparseRing/): the real-data test is skipped")
    return Path(data)

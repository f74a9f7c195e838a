"""Shared fixtures: the bundled real data, loaded once per test session."""

import os
from pathlib import Path

# One BLAS thread: the solvers work on many small matrices, where OpenBLAS's threads on a
# loaded 2-core machine made products 10-50x slower (measured in the spacetime tests).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import pytest

from datapaths import DATA, LAYOUTS, PERFORMANCES, RIGS, ROOT  # noqa: E402,F401


@pytest.fixture(scope="session")
def data_dir():
    return DATA


@pytest.fixture(scope="session")
def rigs():
    """All bundled rigs by file stem, read once."""
    from core.io.gltf import read_rig

    return {p.stem: read_rig(p) for p in sorted(RIGS.glob("*.glb"))}


@pytest.fixture(scope="session")
def ict(rigs):
    return rigs["ict_facekit"]


@pytest.fixture(scope="session")
def rocketbox(rigs):
    return rigs["rocketbox_female_adult_02"]


@pytest.fixture(scope="session")
def tiger(rigs):
    return rigs["jeeliz_tiger"]

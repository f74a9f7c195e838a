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


@pytest.fixture(scope="session")
def hidden_rocketbox(tmp_path_factory):
    """A copy of the Rocketbox GLB with every shape renamed ``shape_NNN`` (same order), written by
    the project's GLB writer, with its layout copied as the sidecar ``<rig>.layout.json``
    (:func:`core.io.rigs.write_renamed_rig`, as scripts/quality_cases.py makes its case C)."""
    from core.io.rigs import write_renamed_rig

    return write_renamed_rig(RIGS / "rocketbox_female_adult_02.glb", tmp_path_factory.mktemp("hidden") / "rocketbox_hidden.glb")

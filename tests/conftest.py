"""Test-session settings shared by every test module."""

import os
from pathlib import Path

import pytest

# Same single-threaded BLAS as the product (see backend/cli.py): before numpy is imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


@pytest.fixture(scope="session")
def sim_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 12 s small-boat recording, simulated once per test session and shared by the
    backend and page tests (directory name ``small-boat-12s``)."""
    from recordings.sim.simulate import simulate

    path = tmp_path_factory.mktemp("recordings") / "small-boat-12s"
    simulate("small-boat", 1, path, duration_s=12, progress=False)
    return path

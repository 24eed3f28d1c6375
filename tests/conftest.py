"""Shared fixtures of the whole suite (tests/fppsim, tests/uhrnet and the cross-package tests here).

- ``tests/`` is put on ``sys.path`` so every test module imports ``_helpers`` (the ../shared paths,
  computed once, and tiny dataset writers).
- ``one_thread``: torch on one thread (tiny models on a shared 2-core machine run faster and steadier).
- ``shared_meshes`` / ``real_sample``: the third-party test data, or a clean skip when it is absent.
- ``native_dataset``: a small native dataset written by fppsim's own writer (not by hand).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

# before any test module imports pyrender (some do at collection, e.g. pytest.importorskip): off-screen GL, as
# fppsim.rendering sets it, so every test file also passes when run alone from a plain shell
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _helpers import REAL_SAMPLE, SHARED_MESHES  # noqa: E402


@pytest.fixture
def one_thread():
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def shared_meshes() -> Path:
    if not SHARED_MESHES.is_dir():
        pytest.skip("../shared/meshes absent")
    return SHARED_MESHES


@pytest.fixture
def real_sample() -> Path:
    if not (REAL_SAMPLE / "height_map.npy").is_file():
        pytest.skip("../shared/real-sample absent")
    return REAL_SAMPLE


@pytest.fixture
def native_dataset(tmp_path) -> Path:
    """Four 32 x 64 native samples (with PSP arrays) written through fppsim.dataio.formats."""
    from _helpers import write_native

    write_native(tmp_path / "native", n=4, psp=True)
    return tmp_path / "native"

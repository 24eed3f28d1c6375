"""fppsim.rendering.shapes: the project's own sculpture-like meshes and the shipped assets/meshes files."""

from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
import trimesh

from fppsim.rendering.shapes import ASSETS, SHAPES, asset_name, export_ply_bytes, make_shape

ASSET_DIR = Path(__file__).resolve().parents[2] / "fppsim" / "data" / "meshes"


@lru_cache(maxsize=None)
def _shape(kind, seed):
    return make_shape(kind, seed)


@pytest.mark.parametrize("seed", [0, 7])
@pytest.mark.parametrize("kind", SHAPES)
def test_shape_is_closed_solid_of_sculpture_size(kind, seed):
    m = _shape(kind, seed)
    assert m.is_watertight and m.is_winding_consistent
    assert m.volume > 0
    assert np.all(m.extents > 5.0), m.extents
    assert 60.0 <= m.extents.max() <= 120.0, m.extents
    assert 5000 <= len(m.faces) <= 30000, len(m.faces)
    assert np.isfinite(m.vertices).all()
    # rests on the plane, centred in x and y
    assert m.bounds[0, 2] == pytest.approx(0.0, abs=1e-9)
    assert np.allclose(m.bounds[:, :2].sum(axis=0), 0.0, atol=1e-6)
    assert len(m.split(only_watertight=False)) == 1


@pytest.mark.parametrize("kind", SHAPES)
def test_same_seed_same_mesh_other_seed_other_mesh(kind):
    a = _shape(kind, 0)
    b = make_shape(kind, 0)
    assert np.array_equal(a.faces, b.faces)
    assert np.array_equal(a.vertices, b.vertices)
    c = _shape(kind, 7)
    assert len(c.vertices) != len(a.vertices) or not np.allclose(c.vertices, a.vertices)


def test_make_shape_rejects_unknown_kind_and_accepts_fixed_size():
    with pytest.raises(ValueError, match="unknown shape kind"):
        make_shape("teapot", 0)
    with pytest.raises(ValueError, match="non-negative"):
        make_shape("vase", -1)
    assert make_shape("vase", 3, size_mm=80.0).extents.max() == pytest.approx(80.0)


def test_ply_export_is_byte_stable():
    m = _shape("relief", 0)
    assert export_ply_bytes(m) == export_ply_bytes(make_shape("relief", 0))


def test_shipped_assets_load_and_match_regeneration():
    files = sorted(ASSET_DIR.glob("*.ply"))
    assert {f.name for f in files} == {asset_name(k, s) for k, s in ASSETS}
    assert 5 <= len(files) <= 8
    assert sum(f.stat().st_size for f in files) < 3.2e6
    for kind, seed in ASSETS:
        shipped = trimesh.load(ASSET_DIR / asset_name(kind, seed), force="mesh")
        fresh = _shape(kind, seed)
        assert shipped.is_watertight
        assert len(shipped.vertices) == len(fresh.vertices)
        assert len(shipped.faces) == len(fresh.faces)
        assert np.allclose(shipped.bounds, fresh.bounds, atol=1e-3)
        assert shipped.volume == pytest.approx(fresh.volume, rel=1e-4)

"""Issue 11: work split over two threads gives the very bits of doing it in one piece."""

from __future__ import annotations

import multiprocessing
import threading

import numpy as np
import pytest

from fppsim.phase import psp, triangulation
from fppsim.threads import helper_pool, map_bands, row_bands
from fppsim.geometry.rig import Device, Rig, make_default_rig


def _small_rig(height=37, width=53):
    """The default rig with a small, odd-sized camera (same centre of view, uneven bands)."""
    r = make_default_rig()
    K = r.camera.K.copy()
    K[0, 2], K[1, 2] = (width - 1) / 2, (height - 1) / 2
    K[:2, :2] *= width / r.camera.width
    return Rig(Device(K=K, R=r.camera.R, t=r.camera.t, width=width, height=height), r.projector, periods=80.0)


def _distorted_rig():
    r = make_default_rig()
    proj = r.projector
    proj = Device(K=proj.K, R=proj.R, t=proj.t, width=proj.width, height=proj.height, dist=[0.05, -0.02, 1e-3, 0, 0])
    return Rig(r.camera, proj, periods=80.0)


def _camera_distorted_rig():
    r = make_default_rig()
    c = r.camera
    cam = Device(K=c.K, R=c.R, t=c.t, width=c.width, height=c.height, dist=[-0.08, 0.05, 1e-3, -5e-4, 0.01])
    return Rig(cam, r.projector, periods=80.0)


def _stacks(rig, dtype, seed=3):
    """PSP stacks (1, 8, 80 periods, 4 steps) of a tilted plane with a bump, some dark and saturated
    regions and noise: every mask of the decode has both values somewhere."""
    rng = np.random.default_rng(seed)
    H, W = rig.camera.height, rig.camera.width
    y, x = np.mgrid[0:H, 0:W] / np.array([H, W])[:, None, None]  # 0..1 down and across
    span = 0.9 * min(2.0 * W, rig.projector.width)  # under 2 projector columns a pixel: orders stay consistent
    col = (x + 0.05 * np.exp(-((x - 0.5) ** 2 + (y - 0.3) ** 2) / 0.01)) * span
    for b in row_bands(H, 2)[1:]:
        # one-row ridges a full period high beside the band seam: the rows next to the seam agree with
        # their own row and the row across the seam, not with the ridge, so their order check needs the
        # row across the seam (the halo) to come out as in one piece
        col[b.start + 1] += rig.projector.width / 80
        col[b.start - 2] += rig.projector.width / 80
    A = np.where(x < 0.1, 5.0, 120.0)  # dark strip: low modulation
    B = np.where(y > 0.85, 0.0, 90.0)  # no fringes at the bottom: fails the modulation threshold
    out = {}
    for f in (1, 8, 80):
        phi = 2 * np.pi * f * col / rig.projector.width
        imgs = [A + B * np.cos(phi + 2 * np.pi * n / 4) + rng.normal(0, 2, (H, W)) for n in range(4)]
        stack = np.stack(imgs)
        out[f] = np.clip(np.rint(stack), 0, 255).astype(np.uint8) if dtype == np.uint8 else stack.astype(dtype)
    return out


def _same(a: psp.Decoded, b: psp.Decoded):
    for name in ("phase", "order", "height", "quality", "reliable", "consistent", "valid"):
        x, y = getattr(a, name), getattr(b, name)
        if x is None or y is None:
            assert x is None and y is None, name
            continue
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert np.array_equal(x, y, equal_nan=True), name


@pytest.mark.parametrize("rig_factory", [make_default_rig, _distorted_rig, _camera_distorted_rig, _small_rig])
@pytest.mark.parametrize("dtype", [np.uint8, np.float64])
def test_decode_in_two_bands_equals_one_piece(rig_factory, dtype):
    rig = rig_factory()
    stacks = _stacks(rig, dtype)
    one = psp.decode_stacks(stacks, rig, (1, 8, 80))
    assert one.valid.any() and not one.valid.all() and not one.consistent.all() and not one.quality.all()
    _same(psp.decode_stacks(stacks, rig, (1, 8, 80), threads=2), one)
    # without a rig, without the neighbour check, with a contrast threshold
    _same(psp.decode_stacks(stacks, None, (1, 8, 80), threads=2), psp.decode_stacks(stacks, None, (1, 8, 80)))
    kw = dict(neighbour_check=False, min_ratio=0.3, min_modulation=10.0)
    _same(psp.decode_stacks(stacks, rig, (1, 8, 80), threads=2, **kw), psp.decode_stacks(stacks, rig, (1, 8, 80), **kw))


def test_decode_of_pixel_lists_and_tiny_images_stays_in_one_piece():
    rig = _small_rig(height=12, width=20)  # fewer rows than one band's 16
    stacks = _stacks(rig, np.uint8)
    _same(psp.decode_stacks(stacks, rig, (1, 8, 80), threads=2), psp.decode_stacks(stacks, rig, (1, 8, 80)))
    flat = {f: s.reshape(4, -1) for f, s in stacks.items()}  # (N, pixels): nothing to split
    kw = dict(neighbour_check=False)
    _same(psp.decode_stacks(flat, None, (1, 8, 80), threads=2, **kw), psp.decode_stacks(flat, None, (1, 8, 80), **kw))


def test_triangulate_rows_is_the_band_of_the_whole():
    rig = make_default_rig()
    rng = np.random.default_rng(6)
    phase = rng.uniform(0, 2 * np.pi * rig.periods, (rig.camera.height, rig.camera.width))
    mask = rng.random(phase.shape) < 0.8
    whole = triangulation.height_from_phase(rig, phase, mask=mask)
    band = slice(96, 208)
    assert np.array_equal(triangulation.height_from_phase(rig, phase[band], mask=mask[band], rows=band), whole[band],
                          equal_nan=True)
    with pytest.raises(ValueError, match="not the 112 x 640"):
        triangulation.height_from_phase(rig, phase[:100], rows=band)
    with pytest.raises(ValueError, match="without distortion"):
        triangulation.height_from_phase(_distorted_rig(), phase[band], rows=band)


@pytest.mark.parametrize("height,count", [(352, 2), (37, 2), (1000, 3), (16, 2), (17, 2), (5, 4), (0, 2), (100, 1)])
def test_row_bands_cover_the_rows_once_from_multiples_of_16(height, count):
    bands = row_bands(height, count)
    assert 1 <= len(bands) <= count
    covered = [r for b in bands for r in range(height)[b]]
    assert covered == list(range(height))
    assert all(b.start % 16 == 0 for b in bands)


def test_map_bands_keeps_order_waits_for_every_job_and_reraises():
    done = []

    def job(rows):
        done.append(rows.start)
        if rows.start == 0:
            raise KeyError("first band failed")
        return threading.current_thread().name

    bands = [slice(0, 16), slice(16, 32), slice(32, 40)]
    with pytest.raises(KeyError, match="first band failed"):
        map_bands(job, bands)
    assert sorted(done) == [0, 16, 32]  # the helper's jobs finished before the error was raised
    names = map_bands(lambda rows: (rows.start, threading.current_thread().name), bands)
    assert [n[0] for n in names] == [0, 16, 32]
    assert names[0][1] == threading.current_thread().name and names[1][1].startswith("fppsim-helper")
    # called on the helper itself: runs in place instead of waiting for itself
    inner = helper_pool().submit(map_bands, lambda rows: rows.start, bands).result(timeout=30)
    assert inner == [0, 16, 32]


def _bands_in_child(_):
    return map_bands(lambda rows: rows.stop - rows.start, row_bands(100, 2))


def test_helper_works_in_a_forked_worker():
    """A worker forked after the parent used its helper gets a helper of its own (none would run)."""
    if "fork" not in multiprocessing.get_all_start_methods():
        pytest.skip("no fork on this platform")
    map_bands(lambda rows: None, row_bands(100, 2))  # the parent's helper exists
    with multiprocessing.get_context("fork").Pool(1) as pool:
        assert pool.map_async(_bands_in_child, [0]).get(timeout=60) == [[64, 36]]


def test_scene_geometry_reports_a_failed_projector_render():
    """The camera side runs on the helper while the shadow map renders; a failed render is the error."""
    from fppsim.rendering.render import scene_geometry

    class Renderer:
        calls = 0

        def depth(self, device, meshes, scale=1):
            Renderer.calls += 1
            if Renderer.calls == 2:
                raise RuntimeError("projector render failed")
            return np.full((device.height * scale, device.width * scale), np.inf)

    with pytest.raises(RuntimeError, match="projector render failed"):
        scene_geometry(make_default_rig(), [], Renderer())
    assert helper_pool().submit(lambda: 7).result(timeout=30) == 7  # the helper is free again


def test_scene_geometry_called_on_the_helper_runs_in_place():
    """Started from the helper thread, the camera side runs at once instead of waiting for the helper."""
    from fppsim.rendering.render import scene_geometry

    class Renderer:
        def depth(self, device, meshes, scale=1):
            return np.full((device.height * scale, device.width * scale), np.inf)

    rig = make_default_rig()
    geom = helper_pool().submit(scene_geometry, rig, [], Renderer()).result(timeout=60)
    here = scene_geometry(rig, [], Renderer())
    assert all(np.array_equal(getattr(geom, k), getattr(here, k), equal_nan=True) for k in geom.__dataclass_fields__)


def test_helper_jobs_keep_the_callers_floating_point_error_state():
    """numpy's errstate (a context variable) travels to the helper's band: a division by zero there
    raises, or stays quiet, as it would on the calling thread."""
    import warnings

    def divide(rows):
        return np.ones(rows.stop - rows.start) / np.zeros(rows.stop - rows.start)

    bands = [slice(0, 16), slice(16, 32)]
    with np.errstate(divide="raise"), pytest.raises(FloatingPointError):
        map_bands(lambda rows: divide(rows) if rows.start else None, bands)  # fails on the helper only
    with np.errstate(divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isinf(map_bands(divide, bands)[1]).all()


def test_banded_decode_refuses_what_the_one_piece_decode_refuses():
    rig = make_default_rig()
    stacks = _stacks(rig, np.uint8)
    uneven = {1: stacks[1][:, :64], 8: stacks[8][:, :100], 80: stacks[80][:, :100]}
    for threads in (1, 2):
        with pytest.raises(ValueError):
            psp.decode_stacks(uneven, None, (1, 8, 80), threads=threads)
    cropped = {f: s[:, :300] for f, s in stacks.items()}  # not the camera's 352 rows
    for threads in (1, 2):
        with pytest.raises(ValueError, match="camera is 352 x 640"):
            psp.decode_stacks(cropped, rig, (1, 8, 80), threads=threads)


def test_camera_ray_cache_holds_four_cameras_when_filled_from_two_threads():
    from concurrent.futures import ThreadPoolExecutor

    base = _small_rig(20, 30).camera
    cams = [Device(K=base.K * np.array([[1 + i / 100, 1, 1], [1, 1 + i / 100, 1], [1, 1, 1]]), R=base.R, t=base.t,
                   width=30, height=20) for i in range(12)]
    with ThreadPoolExecutor(2) as pool:
        got = list(pool.map(triangulation._camera_rays, cams * 2))
    assert len(triangulation._RAYS) <= 4
    for cam, (origin, d) in zip(cams * 2, got):
        o2, d2 = cam.pixel_rays(cam.pixel_grid())
        assert np.array_equal(origin, o2) and np.array_equal(d, d2)

"""The generator's fast paths give the same bits as the plain computations they replace."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest

from fppsim.phase import psp, triangulation
from fppsim.phase import wrap
from fppsim.dataio.encoding import save_npz
from fppsim.dataio.formats import LabelTransform
from fppsim.dataio.writers import export_figshare, write_sample_folder
from fppsim.dataio.writers import BackgroundWriter, FigshareRows, figshare_rows


def _float_path(stack, shifts=None):
    """wrapped_phase's float64 tensordot reference, spelled out."""
    I = np.asarray(stack, dtype=np.float64)
    w = psp._shift_weights(psp._resolve_shifts(I.shape[0], shifts))
    A, c, s = (np.tensordot(w[k], I, axes=1) for k in range(3))
    return psp.phase_from_sums(s, c), A, (2.0 / I.shape[0]) * np.hypot(s, c)


@pytest.mark.parametrize("steps", [3, 4, 5, 6, 8])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_integer_phase_sums_equal_float_path_bitwise(steps, dtype):
    rng = np.random.default_rng(steps)
    hi = 256 if dtype == np.uint8 else 4096
    stack = rng.integers(0, hi, size=(steps, 37, 53)).astype(dtype)
    stack[:, :3] = 0  # zero sums: +0.0 on both paths
    stack[:, 3:6] = stack[:1, 3:6]  # no modulation
    got = psp.wrapped_phase(stack)
    for a, b in zip(got, _float_path(stack)):
        assert a.dtype == np.float64 and np.array_equal(a, b) and np.array_equal(np.signbit(a), np.signbit(b))


def test_integer_path_only_for_exact_cases():
    w4 = psp._shift_weights(psp.phase_shifts(4))
    assert psp._exact_int_sums(np.zeros((4, 2, 2), np.uint8), w4) is not None
    assert psp._exact_int_sums(np.zeros((4, 2, 2), np.float32), w4) is None  # floats: tensordot
    assert psp._exact_int_sums(np.zeros((4, 2, 2), np.int16), w4) is None  # signed: -0.0 possible
    w3 = psp._shift_weights(psp.phase_shifts(3))
    assert psp._exact_int_sums(np.zeros((3, 2, 2), np.uint8), w3) is None  # sin(2 pi/3) is not dyadic


def test_camera_rays_cache_matches_and_is_read_only():
    from fppsim.geometry.rig import Rig

    cam = Rig.default().camera
    o, d = triangulation._camera_rays(cam)
    o2, d2 = cam.pixel_rays(cam.pixel_grid())
    assert np.array_equal(o, o2) and np.array_equal(d, d2)
    assert triangulation._camera_rays(cam)[1] is d
    with pytest.raises(ValueError):
        d[0, 0, 0] = 1.0


def test_normals_per_plane_match_stacked_formula():
    from fppsim.rendering.render import _normals_from_points

    def reference(P, c):  # the (H, W, 3) formulation
        def smaller_step(axis):
            fwd = np.diff(P, axis=axis, append=np.take(P, [-1], axis=axis))
            bwd = np.diff(P, axis=axis, prepend=np.take(P, [0], axis=axis))
            fn, bn = np.linalg.norm(fwd, axis=-1), np.linalg.norm(bwd, axis=-1)
            fn = np.where(np.isfinite(fn) & (fn > 0), fn, np.inf)
            bn = np.where(np.isfinite(bn) & (bn > 0), bn, np.inf)
            return np.where((fn <= bn)[..., None], fwd, bwd)

        n = np.cross(smaller_step(1), smaller_step(0))
        with np.errstate(invalid="ignore", divide="ignore"):
            n = n / np.linalg.norm(n, axis=-1, keepdims=True)
        n[np.sum(n * (c - P), axis=-1) < 0] *= -1
        n[~np.all(np.isfinite(n), axis=-1)] = (0.0, 0.0, 1.0)
        return n

    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:80, 0:120].astype(float)
    z = 20 * np.sin(xx / 9) * np.cos(yy / 7) + 30 * (xx > 60) + rng.normal(0, 0.01, xx.shape)
    P = np.stack([0.5 * xx, 0.5 * yy, z], -1).astype(np.float32)
    P[rng.random(xx.shape) < 0.05] = np.nan
    P[:, :2] = np.nan
    c = np.array([10.0, -20.0, 900.0], np.float32)
    with np.errstate(invalid="ignore"):
        ref = reference(P, c)
    assert np.array_equal(_normals_from_points(P, c), ref)


def test_save_npz_round_trip_fixed_bytes_and_stored_noise(tmp_path):
    rng = np.random.default_rng(0)
    arrays = {"noise": rng.standard_normal((200, 300)).astype(np.float32),
              "smooth": np.zeros((200, 300), np.float32), "small": np.arange(5, dtype=np.float32)}
    save_npz(tmp_path / "a.npz", arrays)
    save_npz(tmp_path / "b.npz", arrays)
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    with np.load(tmp_path / "a.npz") as z:
        assert all(np.array_equal(z[k], arrays[k]) for k in arrays)
    info = {i.filename: i for i in zipfile.ZipFile(tmp_path / "a.npz").infolist()}
    assert info["noise.npy"].compress_type == zipfile.ZIP_STORED  # deflate would not pay
    assert info["smooth.npy"].compress_type == zipfile.ZIP_DEFLATED
    assert all(i.date_time == (1980, 1, 1, 0, 0, 0) for i in info.values())


def test_npz_members_are_standard_deflate(tmp_path):
    """zlib-ng writes the members; the stdlib zlib (what np.load and zipfile use) must inflate them."""
    import zlib

    rng = np.random.default_rng(3)
    arrays = {"height": np.where(rng.random((352, 640)) < 0.5, 0, rng.uniform(0, 50, (352, 640))).astype(np.float32),
              "mask": (rng.random((352, 640)) < 0.7).astype(np.float32)}
    save_npz(tmp_path / "a.npz", arrays)
    with zipfile.ZipFile(tmp_path / "a.npz") as zf:
        assert zf.testzip() is None  # CRCs of the inflated members
        for info in zf.infolist():
            assert info.compress_type == zipfile.ZIP_DEFLATED
            raw = zf.fp  # the member's deflate stream, inflated by the stdlib zlib directly
            raw.seek(info.header_offset + 26)
            skip = int.from_bytes(raw.read(2), "little") + int.from_bytes(raw.read(2), "little")
            raw.seek(skip, 1)
            data = zlib.decompress(raw.read(info.compress_size), -15)
            key = info.filename[:-4]
            assert data.endswith(arrays[key].tobytes()) and len(data) == info.file_size


@pytest.mark.parametrize("shape", [(352, 640), (1, 1), (1, 9), (7, 1), (3, 4)])
def test_encode_png_pixels_read_back_by_pillow_and_opencv(shape):
    import io

    import cv2
    from PIL import Image

    from fppsim.dataio.encoding import encode_png

    rng = np.random.default_rng(sum(shape))
    img = rng.integers(0, 256, shape, dtype=np.uint8)
    img[: shape[0] // 2] = np.clip(img[: shape[0] // 2], 250, 255)  # wrap-around differences in the filter
    data = encode_png(img)
    Image.open(io.BytesIO(data)).verify()  # chunk CRCs and structure
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(data))), img)
    assert np.array_equal(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED), img)
    colour = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)  # other images: OpenCV's encoder
    assert np.array_equal(cv2.imdecode(np.frombuffer(encode_png(colour), np.uint8), cv2.IMREAD_UNCHANGED), colour)
    view = np.asfortranarray(img)[:, ::-1]  # any layout
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(encode_png(view)))), view)


@pytest.mark.parametrize("bad", [np.zeros((0, 4), np.uint8), np.zeros((3, 4), np.float32), np.zeros((3, 4), bool),
                                 np.zeros((3, 4), np.int8), np.zeros(5, np.uint8), np.zeros((3, 4, 2), np.uint8)])
def test_encode_png_refuses_what_a_png_cannot_hold_exactly(bad):
    from fppsim.dataio.encoding import encode_png

    with pytest.raises(ValueError, match=r"encode_png: .*got"):
        encode_png(bad)


def test_save_npz_keeps_zero_d_and_empty_shapes(tmp_path):
    arrays = {"scalar": np.array(3.5, np.float32), "empty": np.zeros((0, 5), np.float32)}
    save_npz(tmp_path / "a.npz", arrays)
    with np.load(tmp_path / "a.npz") as z:
        assert z["scalar"].shape == () and z["scalar"] == 3.5 and z["empty"].shape == (0, 5)


def test_background_writer_runs_in_order_and_reraises():
    done = []
    w = BackgroundWriter()
    for k in range(5):
        w.submit(done.append, k)
    w.flush()
    assert done == list(range(5))

    def boom():
        raise OSError("disk full")

    w.submit(boom)
    w.submit(done.append, 99)  # may be skipped: an earlier job failed
    with pytest.raises(OSError, match="disk full"):
        w.flush()
    w.close()
    assert 99 not in done


def test_streamed_figshare_rows_equal_export(tmp_path):
    rng = np.random.default_rng(1)
    t = LabelTransform()
    rows = FigshareRows(tmp_path / "stream", 3, 12, 16)
    for k in range(3):
        fringe = rng.integers(0, 256, (12, 16)).astype(np.uint8)
        arrays = {"height": rng.uniform(0, 40, (12, 16)).astype(np.float32),
                  "mask": (rng.random((12, 16)) > 0.3).astype(np.float32)}
        write_sample_folder(tmp_path / "native", f"{k:06d}", {"fringe.png": fringe}, arrays, {"index": k})
        rows.put(k, *figshare_rows(fringe, arrays, t))
    assert not (tmp_path / "stream" / "Z.npy").exists()
    assert rows.commit() == 3
    export_figshare(tmp_path / "native", tmp_path / "export", t,
                    folders=[tmp_path / "native" / f"{k:06d}" for k in range(3)])
    for name in ("f1_80.npy", "Z.npy"):
        assert (tmp_path / "stream" / name).read_bytes() == (tmp_path / "export" / name).read_bytes()
    incomplete = FigshareRows(tmp_path / "partial", 2, 12, 16)
    with pytest.raises(ValueError, match="missing"):
        incomplete.commit()
    incomplete.discard()
    assert not list((tmp_path / "partial").iterdir())


def test_keyed_meshes_render_like_unkeyed_ones_and_hide_afterwards():
    import trimesh

    from fppsim.rendering.render import DepthRenderer, Instance
    from fppsim.geometry.rig import Rig

    rig = Rig.default()
    s = trimesh.creation.icosphere(3, radius=20.0)
    b = trimesh.creation.box(extents=(30.0, 20.0, 10.0))
    poses = []
    for x in (-60.0, 0.0, 60.0):
        T = np.eye(4)
        T[:3, 3] = (x, 10.0, 20.0)
        poses.append(T)
    r = DepthRenderer()
    plain = r.depth(rig.camera, [Instance(s.vertices, s.faces, poses[0]), Instance(s.vertices, s.faces, poses[1]),
                                 Instance(b.vertices, b.faces, poses[2])])
    keyed = [Instance(s.vertices, s.faces, poses[0], "s"), Instance(s.vertices, s.faces, poses[1], "s"),
             Instance(b.vertices, b.faces, poses[2], "b")]
    assert np.array_equal(r.depth(rig.camera, keyed), plain)  # the same mesh twice in one scene
    only_box = r.depth(rig.camera, keyed[2:])  # the spheres stay uploaded but hidden
    alone = DepthRenderer().depth(rig.camera, [Instance(b.vertices, b.faces, poses[2])])
    assert np.array_equal(only_box, alone)
    r.close()


# ------------------------------------------------------------------------- issue 11: generator cost
def test_phase_tables_hold_the_float_path_for_every_pair():
    """The 8-bit four-step lookup tables equal phase_from_sums / hypot on every (PSin, PCos) pair,
    evaluated in another (shuffled) order."""
    stack = np.zeros((4, 2, 2), np.uint8)
    w = psp._shift_weights(psp.phase_shifts(4))
    phase_t, mod_t, n_c, offset = psp._phase_tables(4, psp._exact_int_sums(stack, w), stack.dtype)
    v = np.arange(-255, 256, dtype=float)
    c, s = np.tile(v, v.size), np.repeat(v, v.size)
    order = np.random.default_rng(0).permutation(c.size)
    assert np.array_equal(psp.phase_from_sums(s[order], c[order]), phase_t[order])
    assert np.array_equal(0.5 * np.hypot(s[order], c[order]), mod_t[order])
    assert np.array_equal((s * n_c + c + offset).astype(int), np.arange(c.size))
    assert psp._phase_tables(4, psp._exact_int_sums(stack.astype(np.uint16), w), np.dtype(np.uint16)) is None


def test_wrap_and_mod_fast_paths_equal_the_formulas():
    def wrap_ref(p):
        w = p - psp.TWO_PI * np.ceil((p - np.pi) / psp.TWO_PI)
        return np.where(w <= -np.pi, w + psp.TWO_PI, np.where(w > np.pi, w - psp.TWO_PI, w))

    rng = np.random.default_rng(2)
    edges = np.array([-0.0, 0.0, np.pi, -np.pi, np.nextafter(-np.pi, 0), np.nextafter(np.pi, 0), 1e-300])
    inside = np.concatenate([rng.uniform(-np.pi + 1e-9, np.pi, 5000), edges[[0, 1, 2, 5, 6]]])
    for p in (inside, np.concatenate([inside, edges]), rng.uniform(-9, 9, 5000), np.array([np.nan, 1.0])):
        got, ref = wrap(p), wrap_ref(p)
        assert np.array_equal(got, ref, equal_nan=True) and np.array_equal(np.signbit(got), np.signbit(ref))
    for x in (rng.uniform(-psp.TWO_PI, psp.TWO_PI, 5000), np.concatenate([edges, [-psp.TWO_PI, psp.TWO_PI]]),
              rng.uniform(-30, 30, 5000), np.array([np.inf, -1.0, np.nan])):
        with np.errstate(invalid="ignore"):
            got, ref = psp._mod_two_pi(x), np.mod(x, psp.TWO_PI)
        assert np.array_equal(got, ref, equal_nan=True) and np.array_equal(np.signbit(got), np.signbit(ref))


def test_order_consistency_counts_like_agree_versus_disagree():
    def reference(phase, valid):
        valid = valid & np.isfinite(phase)
        H, W = phase.shape
        pp, vp = np.pad(np.where(valid, phase, 0.0), 1), np.pad(valid, 1)
        agree, disagree = np.zeros((H, W), int), np.zeros((H, W), int)
        for dy in range(3):
            for dx in range(3):
                if dy == dx == 1:
                    continue
                nv = vp[dy:dy + H, dx:dx + W]
                close = np.abs(pp[dy:dy + H, dx:dx + W] - phase) < np.pi
                agree += nv & close
                disagree += nv & ~close
        return valid & (agree >= disagree)

    rng = np.random.default_rng(4)
    phase = np.cumsum(rng.uniform(0, 0.5, (40, 60)), axis=1)
    phase[rng.random(phase.shape) < 0.1] += 2 * np.pi * rng.integers(-2, 3)
    phase[rng.random(phase.shape) < 0.03] = np.nan
    valid = rng.random(phase.shape) < 0.9
    assert np.array_equal(psp.order_consistency(phase, valid), reference(phase, valid))


@pytest.mark.parametrize("distorted", [False, True])
def test_height_from_phase_is_the_triangulated_height(distorted):
    from fppsim.geometry.rig import Rig

    rig = Rig.default()
    if distorted:
        rig.projector.dist = np.array([0.05, -0.02, 0.001, 0.0, 0.0])
    rng = np.random.default_rng(6)
    cam = rig.camera
    phase = rng.uniform(0, 2 * np.pi * rig.periods, (cam.height, cam.width))
    mask = rng.random(phase.shape) < 0.8
    tri = triangulation.triangulate(rig, phase, mask=mask)
    h = triangulation.height_from_phase(rig, phase, mask=mask)
    assert np.array_equal(h, tri.height, equal_nan=True)
    pix = rng.uniform(0, 50, (7, 5, 2))
    ph = rng.uniform(0, 2 * np.pi * rig.periods, (7, 5))
    assert np.array_equal(triangulation.height_from_phase(rig, ph, pixels=pix), triangulation.triangulate(rig, ph, pixels=pix).height,
                          equal_nan=True)


def test_plane_by_plane_geometry_equals_the_broadcast_formulas():
    from fppsim.geometry.rig import Rig, along_rays

    rng = np.random.default_rng(8)
    origin, dirs = rng.normal(size=3) * 100, rng.normal(size=(9, 11, 3))
    depth = rng.uniform(1, 900, (9, 11))
    assert np.array_equal(along_rays(origin, depth, dirs), origin + depth[..., None] * dirs)
    d32 = depth.astype(np.float32)
    assert np.array_equal(along_rays(origin, d32, dirs.astype(np.float32)),
                          origin + d32[..., None] * dirs.astype(np.float32))
    assert np.array_equal(along_rays(origin, np.float64(3.0), dirs[0, 0]), origin + 3.0 * dirs[0, 0])
    cam = Rig.default().camera
    X = rng.uniform(-300, 300, (9, 11, 3))
    assert np.array_equal(cam.world_to_device(X), X @ cam.R.T + cam.t)
    assert np.array_equal(cam.world_to_device(X[0, 0]), X[0, 0] @ cam.R.T + cam.t)


def test_prefetched_noise_is_the_generator_draws_in_order():
    from fppsim.rendering.optics.noise import PrefetchedNormals

    pre = PrefetchedNormals(np.random.default_rng(5), (7, 9), 3)
    ref = np.random.default_rng(5)
    for _ in range(3):
        got = pre.standard_normal((7, 9), dtype=np.float32)
        assert got.dtype == np.float32 and np.array_equal(got, ref.standard_normal((7, 9), dtype=np.float32))
    with pytest.raises(RuntimeError, match="3 float32 draws"):
        pre.standard_normal((7, 9), dtype=np.float32)
    with pytest.raises(RuntimeError, match="asked for"):
        PrefetchedNormals(np.random.default_rng(5), (7, 9), 3).standard_normal((9, 7), dtype=np.float32)

    class Broken:
        def standard_normal(self, *args, **kwargs):
            raise MemoryError("no room for noise")

    with pytest.raises(MemoryError, match="no room"):
        PrefetchedNormals(Broken(), (2, 2), 2).standard_normal((2, 2), dtype=np.float32)


def test_synthesize_with_prefetched_noise_equals_drawing_in_place(monkeypatch, tmp_path):
    """The noise drawn ahead on the helper thread gives the very images of drawing it image by image."""
    import trimesh

    from fppsim.rendering import synth
    from fppsim.generation import load_assets
    from fppsim.rendering.render import DepthRenderer
    from fppsim.geometry.rig import Rig

    trimesh.creation.box(extents=(60.0, 40.0, 25.0)).export(tmp_path / "box.ply")
    assets, _ = load_assets([str(tmp_path / "box.ply")])
    config = synth.SynthConfig(rig=Rig.default(), psp_freqs=(1, 8), psp_steps=3, min_object_fraction=0.0)
    r = DepthRenderer()
    images, arrays, _ = synth.synthesize(1, 7, assets, config, r)
    monkeypatch.setattr(synth, "noise_source", lambda rng, optics, shape, count: rng)
    images2, arrays2, _ = synth.synthesize(1, 7, assets, config, r)
    r.close()
    assert images.keys() == images2.keys() and all(np.array_equal(images[k], images2[k]) for k in images)
    assert all(np.array_equal(arrays[k], arrays2[k], equal_nan=True) for k in arrays)

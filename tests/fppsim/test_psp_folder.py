"""fppsim.dataio.readers / fppsim.dataio.writers, the .mat folder layout: <root>/PSin, PCos, Fringe (Order), iPattern, one variable per .mat."""

import numpy as np
import pytest
import scipy.io

from fppsim.phase import psp
from _helpers import synthesize_stack
from fppsim.errors import PSPMatError
from fppsim.dataio.readers import is_psp_folder, iter_psp_folder, list_psp_ids, load_psp_folder_sample
from fppsim.dataio.writers import save_psp_folder_sample, sums_from_phase

TWO_PI = 2 * np.pi


def _truth(h=24, w=40, seed=0):
    """An absolute phase like the benchmark's (0 .. 2 pi 57), an invalid shadow and an image."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    phase = 0.3 + TWO_PI * 56.5 * xx / (w - 1) - 0.02 * yy + rng.normal(0, 0.01, (h, w))
    valid = np.ones((h, w), bool)
    valid[5:12, 3:9] = False
    img = rng.integers(1, 256, (h, w), dtype=np.uint8)
    img[~valid] = 0
    return phase, valid, img


def _write_benchmark_style(root, sid, phase, valid, img, B=37.5):
    """Write files as the public data store them, independently of save_psp_folder_sample: PSin and PCos
    are B sin/cos of the phase, Order = floor(phase / 2 pi) (wrapped part in [0, 2 pi)), doubles."""
    for sub in ("PSin", "PCos", "Fringe", "iPattern"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    k = np.floor(phase / TWO_PI)
    scipy.io.savemat(root / "PSin" / f"{sid}.mat", {"PSin": np.where(valid, B * np.sin(phase), 0.0)})
    scipy.io.savemat(root / "PCos" / f"{sid}.mat", {"PCos": np.where(valid, B * np.cos(phase), 0.0)})
    scipy.io.savemat(root / "Fringe" / f"{sid}.mat", {"Order": np.where(valid, k, 0.0)})
    scipy.io.savemat(root / "iPattern" / f"{sid}.mat", {"iPattern": img})


def test_reads_the_benchmark_layout(tmp_path):
    phase, valid, img = _truth()
    for sid in ("10", "2", "1"):
        _write_benchmark_style(tmp_path, sid, phase, valid, img)
    assert is_psp_folder(tmp_path) and not is_psp_folder(tmp_path / "PSin")
    assert list_psp_ids(tmp_path) == ["1", "2", "10"]  # numeric order
    s = load_psp_folder_sample(tmp_path, "2")
    np.testing.assert_array_equal(s.valid, valid)
    np.testing.assert_allclose(s.phase[valid], phase[valid], atol=1e-9)
    assert np.isnan(s.phase[~valid]).all()
    assert s.image.dtype == np.uint8
    np.testing.assert_array_equal(s.image, img)
    np.testing.assert_array_equal(s.order[valid], np.floor(phase / TWO_PI)[valid])
    assert s.meta["id"] == "2" and s.path.endswith("PSin/2.mat")
    # the other convention reads the same sums with centred wrapping: differs by 2 pi where sin < 0
    f = load_psp_folder_sample(tmp_path, "2", convention="fppsim")
    diff = (s.phase - f.phase)[valid]
    np.testing.assert_allclose(np.sin(phase[valid]) < 0, np.isclose(diff, TWO_PI))
    assert np.allclose(diff[~np.isclose(diff, TWO_PI)], 0)
    # the opposite sine sign
    g = load_psp_folder_sample(tmp_path, "2", negate_sin=True)
    np.testing.assert_allclose(np.sin(g.wrapped[valid]), -np.sin(phase[valid]), atol=1e-9)
    got = [sid for sid, _ in iter_psp_folder(tmp_path, image=False)]
    assert got == ["1", "2", "10"]


@pytest.mark.parametrize("convention", ["benchmark", "fppsim"])
def test_write_round_trip(tmp_path, convention):
    phase, valid, img = _truth(seed=3)
    psin, pcos, order = sums_from_phase(phase, valid, modulation=50.0, convention=convention)
    paths = save_psp_folder_sample(tmp_path, "0007", psin, pcos, order, img)
    assert [p.parent.name for p in paths] == ["PSin", "PCos", "Fringe", "iPattern"]
    # the files are plain one-variable MATLAB files
    m = scipy.io.loadmat(tmp_path / "Fringe" / "0007.mat")
    assert [k for k in m if not k.startswith("__")] == ["Order"]
    assert scipy.io.loadmat(tmp_path / "iPattern" / "0007.mat")["iPattern"].dtype == np.uint8
    s = load_psp_folder_sample(tmp_path, "0007", convention=convention)
    np.testing.assert_array_equal(s.valid, valid)
    np.testing.assert_allclose(s.phase[valid], phase[valid], atol=1e-9)
    # the same phase comes out of fppsim.phase.psp's own chain (phase sums of a 4-step stack)
    stack = synthesize_stack(phase, 100.0, 50.0, n_steps=4)
    ps, pc = psp.phase_sums(stack)
    np.testing.assert_allclose(ps[valid], 2 * psin[valid], atol=1e-6)  # (N/2) B with N = 4
    np.testing.assert_allclose(pc[valid], 2 * pcos[valid], atol=1e-6)
    assert not list(tmp_path.rglob(".*tmp"))


def test_errors_name_the_file(tmp_path):
    phase, valid, img = _truth()
    _write_benchmark_style(tmp_path, "1", phase, valid, img)
    _write_benchmark_style(tmp_path, "2", phase, valid, img)
    (tmp_path / "Fringe" / "2.mat").unlink()
    with pytest.raises(PSPMatError, match=r"ids differ between folders: Fringe lacks 2$"):
        list_psp_ids(tmp_path)
    (tmp_path / "PSin" / "2.mat").unlink()
    (tmp_path / "PCos" / "2.mat").unlink()
    (tmp_path / "iPattern" / "2.mat").unlink()
    scipy.io.savemat(tmp_path / "PCos" / "1.mat", {"cosine": np.zeros((24, 40)), "other": 1.0})
    with pytest.raises(PSPMatError, match=r"PCos/1\.mat: no variable 'PCos' \(variables: cosine, other\)"):
        load_psp_folder_sample(tmp_path, "1")
    scipy.io.savemat(tmp_path / "PCos" / "1.mat", {"PCos": np.zeros((24, 41))})
    with pytest.raises(PSPMatError, match=r"PCos/1\.mat: shape \(24, 41\) differs from PSin's \(24, 40\)"):
        load_psp_folder_sample(tmp_path, "1")
    import shutil

    shutil.rmtree(tmp_path / "Fringe")
    shutil.rmtree(tmp_path / "iPattern")
    with pytest.raises(PSPMatError, match=r"missing folder\(s\) Fringe, iPattern \(found: PCos, PSin\)"):
        list_psp_ids(tmp_path)
    (tmp_path / "x").write_bytes(b"not a mat file at all, just bytes" * 10)
    with pytest.raises(PSPMatError, match=r"x: not a MATLAB \.mat file"):
        from fppsim.dataio.readers import read_mat_variable
        read_mat_variable(tmp_path / "x", "PSin")
    with pytest.raises(PSPMatError, match=r"shape \(3, 3\) differs from PSin's \(2, 2\)"):
        save_psp_folder_sample(tmp_path / "w", "1", np.zeros((2, 2)), np.zeros((2, 2)), np.zeros((3, 3)))
    assert not (tmp_path / "w").exists()


def _v73_header() -> bytes:
    text = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Sun Nov 22 00:00:00 2026 HDF5 schema 1.00 ."
    return text.ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02" + b"IM"


def test_matlab_v73_read_through_h5py(tmp_path):
    h5py = pytest.importorskip("h5py")
    phase, valid, img = _truth()
    _write_benchmark_style(tmp_path, "1", phase, valid, img)
    path = tmp_path / "PSin" / "1.mat"
    psin = scipy.io.loadmat(path)["PSin"]
    path.unlink()
    with h5py.File(path, "w", userblock_size=512) as h5:
        h5["PSin"] = psin.T  # MATLAB writes column-major
    with open(path, "r+b") as fh:
        fh.write(_v73_header())
    s = load_psp_folder_sample(tmp_path, "1")
    np.testing.assert_allclose(s.phase[valid], phase[valid], atol=1e-9)


def test_matlab_v73_without_h5py_is_one_line(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "h5py", None)  # import h5py raises ImportError
    phase, valid, img = _truth()
    _write_benchmark_style(tmp_path, "1", phase, valid, img)
    (tmp_path / "PSin" / "1.mat").write_bytes(_v73_header().ljust(512, b"\x00") + b"\x89HDF\r\n\x1a\n" + b"\x00" * 64)
    with pytest.raises(PSPMatError, match=r"PSin/1\.mat: MATLAB v7\.3 \(HDF5\) file; install h5py"):
        load_psp_folder_sample(tmp_path, "1")


def test_export_native_dataset(tmp_path):
    from _helpers import write_native

    from fppsim.dataio.readers import load_native_sample
    from fppsim.dataio.writers import export_psp_folders

    ids = write_native(tmp_path / "nat", n=3, h=16, w=24, seed=0)
    for sid in ids:  # give the samples a real projector phase
        d = tmp_path / "nat" / sid
        z = dict(np.load(d / "arrays.npz"))
        z["phase_true"] = (0.4 + TWO_PI * 80 * np.arange(24)[None, :] / 912 * np.ones((16, 1))).astype(np.float32)
        np.savez_compressed(d / "arrays.npz", **z)
    with pytest.raises(PSPMatError, match="no phase_psp, mask_psp"):
        export_psp_folders(tmp_path / "nat", tmp_path / "out")
    assert export_psp_folders(tmp_path / "nat", tmp_path / "out", source="true") == ids
    assert list_psp_ids(tmp_path / "out") == ids
    for sid in ids:
        s = load_psp_folder_sample(tmp_path / "out", sid)
        n = load_native_sample(tmp_path / "nat" / sid, meta=False)
        valid = n["mask"] > 0.5
        np.testing.assert_array_equal(s.valid, valid)
        np.testing.assert_allclose(s.phase[valid], n["phase_true"][valid], atol=1e-5)
        np.testing.assert_array_equal(s.image, n["fringe"])


def test_an_ipattern_that_is_not_a_2d_image_is_named(tmp_path):
    """QA: an iPattern saved in colour, (H, W, 3), in a folder of single-shot images alone was read as an image
    3 px wide: predict said "image is 64x32; the model needs at least 16x16 pixels". Now the file and its shape."""
    from fppsim.dataio.readers import load_ipattern

    (tmp_path / "iPattern").mkdir()
    grey = np.full((32, 64), 100, np.uint8)
    scipy.io.savemat(tmp_path / "iPattern" / "1.mat", {"iPattern": np.dstack([grey] * 3)})
    with pytest.raises(PSPMatError, match=r"1\.mat: iPattern must be a 2-D grey image, got shape \(32, 64, 3\)"):
        load_ipattern(tmp_path / "iPattern" / "1.mat")
    scipy.io.savemat(tmp_path / "iPattern" / "1.mat", {"iPattern": grey[None]})  # a singleton axis is squeezed
    assert load_ipattern(tmp_path / "iPattern" / "1.mat").shape == (32, 64)



def test_a_frames_digest_is_the_same_whichever_way_it_is_read_nan_pixels_too(tmp_path):
    """PspMat.digest: one frame's files hash alike under every convention and sine sign (negate_sin undone), also
    when its PSin holds NaN (negating a NaN flips its sign bit; multiplying it by -1 does not flip it back), and the
    stored dtype of the sums does not matter; another frame hashes otherwise."""
    phase, valid, img = _truth()
    _write_benchmark_style(tmp_path / "a", "0", phase, valid, img)
    for var in ("PSin", "PCos"):  # NaN pixels (another lab's invalid marker), stored as float32
        path = tmp_path / "a" / var / "0.mat"
        a = scipy.io.loadmat(path)[var].astype(np.float32)
        a[:2, :5] = np.nan
        scipy.io.savemat(path, {var: a})
    readings = [dict(convention=c, negate_sin=n) for c in ("benchmark", "fppsim", "auto") for n in (False, True)]
    digests = {str(kw): load_psp_folder_sample(tmp_path / "a", "0", **kw).digest() for kw in readings}
    assert len(set(digests.values())) == 1, digests
    for var in ("PSin", "PCos"):  # the same values stored as float64: the same frame
        path = tmp_path / "a" / var / "0.mat"
        scipy.io.savemat(path, {var: scipy.io.loadmat(path)[var].astype(np.float64)})
    assert load_psp_folder_sample(tmp_path / "a", "0", negate_sin=True).digest() in digests.values()
    _write_benchmark_style(tmp_path / "b", "0", phase + 0.5, valid, img)
    assert load_psp_folder_sample(tmp_path / "b", "0").digest() not in digests.values()


def test_a_wrapped_phase_with_one_order_everywhere_is_named(tmp_path, capsys):
    """A lab with wrapped phase only writes Order 0 everywhere: fit-rig called it 'no reference plane in view' (FP672/541
    with Order 0: 'the plane model fits the scans poorly ... give --distance, --baseline, --projector-side'; given
    those, 'the fringes are horizontal'), and evaluate-phase scored the wrapped phase. Now one line naming the Fringe
    file, exit 1; a phase of less than one period with Order 0 everywhere is still read."""
    from fppsim.cli import main

    phase, valid, img = _truth()
    _write_benchmark_style(tmp_path / "wrapped", "1", phase, valid, img)
    scipy.io.savemat(tmp_path / "wrapped" / "Fringe" / "1.mat", {"Order": np.zeros(phase.shape)})
    with pytest.raises(PSPMatError, match=r"Fringe/1\.mat: Order is 0 at every valid pixel .* a wrapped phase"):
        load_psp_folder_sample(tmp_path / "wrapped", "1")
    assert main(["fit-rig", str(tmp_path / "wrapped"), "--out", str(tmp_path / "rig.json")]) == 1
    err = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
    assert len(err) == 1 and "Fringe/1.mat: Order is 0 at every valid pixel" in err[0], err
    assert not (tmp_path / "rig.json").exists()
    slow = 0.3 + 0.9 * TWO_PI * np.mgrid[0:24, 0:40][1] / 39.0  # under one period: one order is right
    _write_benchmark_style(tmp_path / "one", "1", slow, valid, img)
    s = load_psp_folder_sample(tmp_path / "one", "1")
    assert np.allclose(s.phase[valid], slow[valid])


def test_a_folder_of_plain_images_is_told_it_needs_the_scans(tmp_path):
    import cv2

    for i in range(2):
        cv2.imwrite(str(tmp_path / f"frame{i}.png"), np.zeros((8, 8), np.uint8))
    with pytest.raises(PSPMatError, match=r"missing folder\(s\) PSin, PCos, Fringe, iPattern \(found: none\).*"
                                          r"holds 2 plain image\(s\), which carry no phase-shifting phase"):
        list_psp_ids(tmp_path)


def test_a_folder_of_fppsims_own_psp_samples_is_told_how_to_write_them(tmp_path):
    """QA: fppsim's own PSP output (``<id>/psp/``, what fit-rig reads) given to evaluate-phase / train --val-phase,
    which read the public layout only, said 'missing folder(s)' and no more; now it names the samples and the
    writer of the public layout."""
    for sid in ("000002", "000003"):
        (tmp_path / sid / "psp").mkdir(parents=True)
        (tmp_path / sid / "arrays.npz").write_bytes(b"")
    with pytest.raises(PSPMatError, match=r"missing folder\(s\) PSin.*it holds 2 of fppsim's own phase-shifting "
                                          r"sample\(s\) \(<id>/psp/\).*export_psp_folders"):
        list_psp_ids(tmp_path)


def test_one_order_under_one_period_read_the_wrong_way_is_a_misreading_not_a_wrapped_phase(tmp_path):
    """Order 0 everywhere and a phase under one period is absolute; read with the wrong --convention it wraps once
    (2.7 % of the steps), while the way it is written does not: that is the misreading note (--convention
    benchmark), not 'Fringe/ must hold each pixel's fringe order' (which only a phase that wraps every way read is)."""
    phase, valid, img = _truth()
    slow = 0.3 + 0.9 * TWO_PI * np.mgrid[0:24, 0:40][1] / 39.0
    _write_benchmark_style(tmp_path, "1", slow, valid, img)
    s = load_psp_folder_sample(tmp_path, "1", convention="fppsim")
    assert s.meta["misread"]["best"][0] == "benchmark"

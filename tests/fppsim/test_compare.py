"""fppsim.fitting.compare (real vs synthetic statistics), the fringe measurements of fppsim.phase.measure and the
any-layout numpy reader fppsim.dataio.readers.open_labelled / grey_sample that compare-real uses."""

import json
import cv2
import numpy as np
import pytest

from fppsim.fitting import compare

from fppsim.phase import measure

from fppsim.dataio import readers
from fppsim.dataio.formats import LabelTransform

from _helpers import REAL_SAMPLE as REAL
H, W = 176, 320


def _fringe(period, h=H, w=W, a=60.0, b=40.0, noise=1.5, seed=0, phase_bump=None):
    """8-bit vertical fringes with a known period, slight row-to-row phase drift and noise."""
    rng = np.random.default_rng(seed)
    x = np.arange(w)[None, :]
    y = np.arange(h)[:, None]
    phi = 2 * np.pi * x / period + 0.2 * y / h
    if phase_bump is not None:
        phi = phi + phase_bump
    img = a + b * np.cos(phi) + rng.normal(0, noise, (h, w))
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _scene(h=H, w=W, seed=0):
    """(gray uint8, label float32): plane at -97 label, a bump object, a shadow strip of -105."""
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - w * 0.45) / (w * 0.15)) ** 2 + ((yy - h * 0.5) / (h * 0.25)) ** 2
    height_mm = np.where(r2 < 1, 30.0 * np.sqrt(np.clip(1 - r2, 0, 1)), 0.0)
    label = (height_mm * 6.0 - 97.0 + 0.5 * np.sin(xx / 37.0)).astype(np.float32)
    shadow = (r2 >= 1) & (xx > w * 0.6) & (xx < w * 0.66) & (np.abs(yy - h * 0.5) < h * 0.25)
    label[shadow] = -105.0
    gray = _fringe(11.6, h, w, seed=seed, phase_bump=height_mm / 13.1 * 2 * np.pi)
    gray[shadow] = 0
    return gray, label


@pytest.mark.parametrize("period", [11.6, 9.0])
def test_period_estimate_within_one_percent(period):
    g = _fringe(period)
    assert measure.estimate_period(g) == pytest.approx(period, rel=0.01)
    # invalid holes (filled with the row mean) do not bias it
    valid = np.ones(g.shape, bool)
    valid[40:120, 100:170] = False
    g2 = g.copy()
    g2[~valid] = 0
    assert measure.estimate_period(g2, valid) == pytest.approx(period, rel=0.01)
    # a gamma-distorted (harmonic-rich), darker fringe
    gam = np.clip(255 * (g / 255.0) ** 2.2 * 3.0, 0, 255).astype(np.uint8)
    assert measure.estimate_period(gam) == pytest.approx(period, rel=0.01)
    q = measure.quarter_periods(g)
    assert q.shape == (4,) and np.allclose(q, period, rtol=0.01)


def test_quarters_see_a_period_that_changes_across_the_image():
    left, right = _fringe(12.0), _fringe(10.0, seed=1)
    g = np.concatenate([left, right], axis=1)
    q = measure.quarter_periods(g)
    assert q[[0, 2]] == pytest.approx([12.0, 12.0], rel=0.01)
    assert q[[1, 3]] == pytest.approx([10.0, 10.0], rel=0.01)
    s = compare.sample_stats(g, np.full(g.shape, -97.0, np.float32))
    assert s["period_q_min_px"] == pytest.approx(10.0, rel=0.01)
    assert s["period_q_max_px"] == pytest.approx(12.0, rel=0.01)
    assert s["period_left_px"] == pytest.approx(12.0, rel=0.01)
    assert s["period_right_px"] == pytest.approx(10.0, rel=0.01)


def test_no_fringe_gives_nan_period():
    flat = np.full((64, 128), 80, np.uint8)
    assert np.isnan(measure.estimate_period(flat))


def test_modulation_and_background_of_a_known_fringe():
    g = _fringe(11.6, a=70.0, b=30.0, noise=0.5)
    b, a = measure.fringe_modulation(g, 11.6)
    assert np.median(b) == pytest.approx(30.0, rel=0.03)
    assert np.median(a) == pytest.approx(70.0, rel=0.03)


def test_sample_stats_percentiles_fractions_and_coverage_match_numpy():
    gray, label = _scene()
    s = compare.sample_stats(gray, label)
    valid = label != -105.0
    assert [s["intensity_p1"], s["intensity_p50"], s["intensity_p99"]] == pytest.approx(
        np.percentile(gray.astype(float), [1, 50, 99]))
    assert s["intensity_valid_p50"] == pytest.approx(np.median(gray[valid]))
    assert [s["height_p1"], s["height_p50"], s["height_p99"]] == pytest.approx(
        np.percentile(label[valid].astype(float), [1, 50, 99]))
    assert s["invalid_fraction"] == pytest.approx((~valid).mean())
    assert s["below_threshold_fraction"] == pytest.approx((label <= -100).mean())
    assert s["plane_level"] == pytest.approx(-97.0, abs=0.5)
    obj = valid & (label > -97.0 + 12.0)
    assert s["object_fraction"] == pytest.approx(obj.mean(), abs=0.01)
    assert 25.0 <= s["relief_p99_mm"] <= 30.5
    assert s["period_px"] == pytest.approx(11.6, rel=0.02)
    assert s["modulation_gray"] == pytest.approx(40.0, rel=0.1)


def test_plane_modulation_right_over_left_of_a_known_ramp():
    """Fringe amplitude rising linearly from 20 to 50 gray levels across a flat plane (with an object in
    the middle that the ratio must ignore): right quarter over left quarter = the ramp's medians."""
    h, w = 176, 320
    x = np.arange(w)
    amp = 20.0 + 30.0 * x / (w - 1)
    rng = np.random.default_rng(1)
    gray = 80.0 + amp[None, :] * np.cos(2 * np.pi * x[None, :] / 11.6) + rng.normal(0, 0.5, (h, w))
    gray = np.clip(np.rint(gray), 0, 255).astype(np.uint8)
    label = np.full((h, w), -97.0, np.float32)
    label[60:120, 140:180] = 60.0  # object, not plane
    q = w // 4
    expected = np.median(amp[-q:]) / np.median(amp[:q])
    s = compare.sample_stats(gray, label)
    assert s["plane_modulation_lr"] == pytest.approx(expected, rel=0.03)
    assert expected > 1.8  # the ramp is steep enough for the check to mean something
    flat = np.clip(np.rint(80.0 + 30.0 * np.cos(2 * np.pi * x[None, :] / 11.6) + 0 * label), 0, 255).astype(np.uint8)
    assert compare.sample_stats(flat, label)["plane_modulation_lr"] == pytest.approx(1.0, abs=0.02)


@pytest.mark.parametrize("deg", [-1.35, 0.0, 2.0, 6.0])
def test_fringe_tilt_of_rotated_fringes(deg):
    """Lines u - v tan(theta) = const lean right going down by theta: the measured angle is theta."""
    h, w = 176, 320
    v, u = np.mgrid[0:h, 0:w]
    rng = np.random.default_rng(2)
    phi = 2 * np.pi * (u - v * np.tan(np.radians(deg))) / 11.6
    gray = np.clip(np.rint(70 + 40 * np.cos(phi) + rng.normal(0, 1.0, (h, w))), 0, 255).astype(np.uint8)
    mask = np.ones((h, w), bool)
    mask[40:100, 100:200] = False  # an object elsewhere must not matter
    gray[40:100, 100:200] = rng.integers(0, 255, (60, 100))
    assert measure.fringe_tilt(gray, 11.6, mask) == pytest.approx(deg, abs=0.05, rel=0.02)
    label = np.where(mask, -97.0, 80.0).astype(np.float32)
    assert compare.sample_stats(gray, label)["fringe_tilt_deg"] == pytest.approx(deg, abs=0.05, rel=0.02)


def _write_native(root, samples, with_mask_key=True):
    root.mkdir(parents=True, exist_ok=True)
    lines = []
    for i, (gray, label) in enumerate(samples):
        sid = f"{i:06d}"
        d = root / sid
        d.mkdir()
        cv2.imwrite(str(d / "fringe.png"), gray)
        mask = (label != -105.0).astype(np.float32)
        height = np.where(mask > 0, (label + 97.0) / 6.0, 0.0).astype(np.float32)
        np.savez_compressed(d / "arrays.npz", height=height, mask=mask, depth=np.zeros_like(height))
        lines.append(json.dumps({"id": sid, "seed": i}))
    (root / "manifest.jsonl").write_text("\n".join(lines) + "\n")


def test_three_layouts_read_the_same_samples(tmp_path):
    samples = [_scene(seed=s) for s in range(3)]
    fr = np.stack([g.astype(np.float32) / 127.5 - 1 for g, _ in samples])[..., None]
    zz = np.stack([lab for _, lab in samples])[..., None]
    (tmp_path / "fig").mkdir()
    np.save(tmp_path / "fig" / "f1_80.npy", fr)
    np.save(tmp_path / "fig" / "Z.npy", zz)
    (tmp_path / "one").mkdir()
    np.save(tmp_path / "one" / "fringe_pattern.npy", fr[0, ..., 0])
    np.save(tmp_path / "one" / "height_map.npy", zz[0, ..., 0])
    _write_native(tmp_path / "nat", samples)

    fig = readers.open_labelled(tmp_path / "fig")
    one = readers.open_labelled(tmp_path / "one")
    nat = readers.open_labelled(tmp_path / "nat")
    assert (fig.layout, len(fig.ids())) == ("figshare", 3)
    assert (one.layout, len(one.ids())) == ("real-sample", 1)
    assert (nat.layout, len(nat.ids())) == ("native", 3)
    for i in range(3):
        g_f, l_f = readers.grey_sample(fig, i)
        g_n, l_n = readers.grey_sample(nat, i)
        assert np.array_equal(g_f, samples[i][0]) and np.array_equal(g_n, samples[i][0])
        assert np.array_equal(l_f, samples[i][1])
        assert np.allclose(l_n, samples[i][1], atol=1e-3)
    g1, l1 = readers.grey_sample(one, 0)
    assert np.array_equal(g1, samples[0][0]) and np.array_equal(l1, samples[0][1])

    # (N, H, W) stacks are accepted too
    (tmp_path / "fig3").mkdir()
    np.save(tmp_path / "fig3" / "f1_80.npy", fr[..., 0])
    np.save(tmp_path / "fig3" / "Z.npy", zz[..., 0])
    assert len(readers.open_labelled(tmp_path / "fig3").ids()) == 3

    a = compare.dataset_stats(tmp_path / "fig")
    b = compare.dataset_stats(tmp_path / "nat")
    for k, v in a["stats"].items():
        assert b["stats"][k] == pytest.approx(v, rel=1e-3, abs=1e-3), k
    assert a["n_samples"] == 3 and len(a["per_sample"]) == 3
    assert compare.dataset_stats(tmp_path / "fig", max_samples=2)["n_samples"] == 2

    res = compare.compare_real(tmp_path / "one", tmp_path / "nat", max_samples=2)
    assert res["synthetic"]["n_samples"] == 2 and res["real"]["layout"] == "real-sample"
    table = compare.format_comparison(res)
    for name in ("fringe period (px)", "invalid fraction", "height p99", "object coverage", "modulation"):
        assert name in table
    assert str(tmp_path / "one") in table and str(tmp_path / "nat") in table
    json.dumps(res)  # plain types only


def test_native_preset_is_configurable(tmp_path):
    gray, label = _scene()
    _write_native(tmp_path / "nat", [(gray, label)])
    transform = LabelTransform(units_per_mm=10.0, plane_offset=0.0, invalid_value=-1.0)
    _, lab = readers.grey_sample(readers.open_labelled(tmp_path / "nat", transform), 0, transform)
    valid = label != -105.0
    assert np.allclose(lab[valid], (label[valid] + 97.0) / 6.0 * 10.0, atol=1e-3)
    assert np.all(lab[~valid] == -1.0)


def test_bad_folders_raise_value_error_naming_the_folder(tmp_path):
    with pytest.raises(ValueError, match="no dataset found") as e:
        readers.open_labelled(tmp_path)
    assert str(tmp_path) in str(e.value)
    with pytest.raises(ValueError, match="not a folder"):
        readers.open_labelled(tmp_path / "missing")
    (tmp_path / "bad").mkdir()
    np.save(tmp_path / "bad" / "f1_80.npy", np.zeros((2, 8, 16, 1), np.float32))
    np.save(tmp_path / "bad" / "Z.npy", np.zeros((3, 8, 16, 1), np.float32))
    with pytest.raises(ValueError, match="3 samples but f1_80.npy has 2"):
        readers.open_labelled(tmp_path / "bad")
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "manifest.jsonl").write_text("")
    with pytest.raises(ValueError, match="no samples"):
        readers.open_labelled(tmp_path / "empty")


@pytest.mark.skipif(not (REAL / "fringe_pattern.npy").is_file(), reason="../shared/real-sample not present")
def test_real_sample_statistics():
    res = compare.dataset_stats(REAL)
    s = res["stats"]
    assert res["layout"] == "real-sample" and res["shape"] == [352, 640]
    assert 11.0 <= s["period_px"] <= 12.3
    assert 11.0 <= s["period_q_min_px"] <= s["period_q_max_px"] <= 12.3
    assert round(s["invalid_fraction"] * 352 * 640) == 15563
    assert 30 <= s["intensity_p50"] <= 45  # a dark image: measured 35 (38 over valid pixels)
    assert 175 <= s["intensity_p99"] <= 195
    assert -100 <= s["plane_level"] <= -94
    assert 0.10 <= s["object_fraction"] <= 0.40
    assert s["height_p99"] > 100
    assert s["modulation_gray"] > 10
    assert 1.05 <= s["plane_modulation_lr"] <= 1.4  # the real projector's light: about 1.14x left to right
    assert -1.6 <= s["fringe_tilt_deg"] <= -1.1  # the real fringes lean: 8.6 px over the 352 rows


def test_horizontal_fringes_give_the_same_statistics_as_vertical_ones():
    """compare-real's statistics of an image and of its transpose (fringes across the image) agree: the
    fringe measurements run across the fringes either way (a 10 px period, contrast 0.6)."""
    import numpy as np

    from fppsim.fitting.compare import sample_stats

    yy, xx = np.mgrid[0:120, 0:160]
    g = (100 + 60 * np.cos(2 * np.pi * xx / 10)).astype(np.uint8)
    lab = np.zeros(g.shape, np.float32)
    a, b = sample_stats(g, lab), sample_stats(np.ascontiguousarray(g.T), lab.T)
    assert a["period_px"] == pytest.approx(10.0, abs=0.05) and b["period_px"] == pytest.approx(a["period_px"])
    assert b["contrast"] == pytest.approx(a["contrast"]) == pytest.approx(0.6, abs=0.03)

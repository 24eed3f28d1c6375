"""The level / relief split of the object error on real data (uhrnet.workflows.sim2real.real_metrics.error_split, issue 32):
synthetic label maps whose regions, offsets and relief are known by construction."""

import numpy as np
import pytest

from uhrnet.workflows.sim2real import error_split, markdown_report, object_regions, real_metrics

PLANE = -97.0  # figshare labels: label = 6 * mm - 97


def _two_regions(h=60, w=100):
    """A plane with two separate rectangular objects, A (20 mm, 20 x 30 px) and B (35 mm, 16 x 20 px)."""
    label = np.full((h, w), PLANE)
    a = np.zeros((h, w), bool)
    a[10:30, 10:40] = True
    b = np.zeros((h, w), bool)
    b[35:51, 60:80] = True
    label[a] = PLANE + 6 * 20.0
    label[b] = PLANE + 6 * 35.0
    return label, a, b


def _checker(shape):
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    return np.where((yy + xx) % 2 == 0, 1.0, -1.0)


def test_constant_offsets_plus_zero_mean_relief_split_exactly():
    label, a, b = _two_regions()
    relief = 0.7 * _checker(label.shape)  # +-0.7 mm: mean and median 0 on each region (even pixel counts)
    offset = np.where(a, 3.0, 0.0) + np.where(b, -5.0, 0.0)
    pred = label + 6.0 * (offset + np.where(a | b, relief, 0.0))
    m = real_metrics(pred, label, label > -100)
    na, nb = a.sum(), b.sum()
    level = np.sqrt((na * 3.0 ** 2 + nb * 5.0 ** 2) / (na + nb))
    assert m["object_regions"] == 2 and m["object_small_regions"] == 0
    for key in ("object_level_rmse_mm", "object_level_rmse_mean_mm"):
        assert m[key] == pytest.approx(level, abs=1e-9)
    for key in ("object_relief_rmse_mm", "object_relief_rmse_mean_mm"):
        assert m[key] == pytest.approx(0.7, abs=1e-9)
    assert m["object_rmse_mm"] == pytest.approx(np.sqrt(level ** 2 + 0.7 ** 2), abs=1e-9)
    split = error_split((pred - label) / 6.0, a | b)
    assert [(r["area_px"], r["median_mm"], r["mean_mm"]) for r in split["per_region"]] == [
        (600, pytest.approx(3.0), pytest.approx(3.0)), (320, pytest.approx(-5.0), pytest.approx(-5.0))]


def test_relief_only_error_has_no_level():
    label, a, b = _two_regions()
    yy, xx = np.mgrid[0:label.shape[0], 0:label.shape[1]]
    relief = 2.0 * np.sin(2 * np.pi * xx / 10.0)  # whole periods across each region's width: mean 0, median 0
    pred = label + 6.0 * np.where(a | b, relief, 0.0)
    m = real_metrics(pred, label, label > -100)
    assert m["object_level_rmse_mm"] == pytest.approx(0.0, abs=1e-9)
    assert m["object_level_rmse_mean_mm"] == pytest.approx(0.0, abs=1e-9)
    assert m["object_relief_rmse_mm"] == pytest.approx(m["object_rmse_mm"], abs=1e-12)
    assert m["object_rmse_mm"] == pytest.approx(2.0 / np.sqrt(2), rel=1e-9)


def test_skewed_errors_mean_split_adds_up_and_median_split_uses_each_regions_median():
    label, a, b = _two_regions()
    rng = np.random.default_rng(3)
    err = rng.exponential(2.0, label.shape) - 1.0 + np.where(b, 4.0, 0.0)  # skewed: median != mean
    split = error_split(err, a | b)
    e = np.concatenate([err[a], err[b]])
    total = np.sqrt(np.mean(e ** 2))
    assert split["rmse_mm"] == pytest.approx(total)
    assert split["level_rmse_mean_mm"] ** 2 + split["relief_rmse_mean_mm"] ** 2 == pytest.approx(total ** 2, rel=1e-12)
    # the median split, from the construction's own masks (not the labelling under test)
    med = {k: np.median(err[m]) for k, m in (("a", a), ("b", b))}
    lvl = np.concatenate([np.full(a.sum(), med["a"]), np.full(b.sum(), med["b"])])
    assert split["level_rmse_mm"] == pytest.approx(np.sqrt(np.mean(lvl ** 2)))
    assert split["relief_rmse_mm"] == pytest.approx(np.sqrt(np.mean((e - lvl) ** 2)))
    # the mean is the least-squares offset: the median split's relief is never smaller
    assert split["relief_rmse_mm"] > split["relief_rmse_mean_mm"]
    assert split["level_rmse_mm"] ** 2 + split["relief_rmse_mm"] ** 2 != pytest.approx(total ** 2, rel=1e-6)


def test_regions_are_8_connected_and_small_specks_are_counted_apart():
    obj = np.zeros((40, 40), bool)
    obj[5:15, 5:15] = True
    obj[15:25, 15:25] = True  # touches the first square at one corner only: one region
    obj[30, 30] = obj[35, 2] = True  # two one-pixel specks
    labels, n = object_regions(obj)
    assert n == 3 and len(np.unique(labels[5:25, 5:25][obj[5:25, 5:25]])) == 1
    err = np.where(obj, 1.0, 0.0)
    err[30, 30] = 10.0  # a speck is its own level: its error is all level
    s = error_split(err, obj)
    assert (s["regions"], s["small_regions"]) == (1, 2)
    assert s["small_region_fraction"] == pytest.approx(2 / 202)
    assert s["relief_rmse_mm"] == 0.0 and s["level_rmse_mm"] == pytest.approx(s["rmse_mm"])
    assert [r["area_px"] for r in s["per_region"]] == [200]


def test_no_object_pixels_or_a_nan_error_give_nan():
    s = error_split(np.zeros((8, 8)), np.zeros((8, 8), bool))
    assert np.isnan(s["level_rmse_mm"]) and s["regions"] == 0 and s["per_region"] == []
    obj = np.zeros((8, 8), bool)
    obj[2:6, 2:6] = True
    err = np.zeros((8, 8))
    err[3, 3] = np.nan
    s = error_split(err, obj, min_region_px=4)
    assert np.isnan(s["rmse_mm"]) and np.isnan(s["relief_rmse_mean_mm"]) and s["regions"] == 1
    with pytest.raises(ValueError, match="differ"):
        error_split(np.zeros((4, 4)), np.zeros((4, 5), bool))


def test_report_rows_show_level_and_relief_per_row_and_per_image():
    real = {"object_rmse_mm": 6.0, "object_level_rmse_mm": 4.5, "object_relief_rmse_mm": 4.1,
            "object_level_rmse_mean_mm": 4.2, "object_relief_rmse_mean_mm": 4.29, "object_median_abs_mm": 3.0,
            "object_within_1mm": 0.2, "object_coverage": 1.0, "valid_rmse_mm": 3.0, "flat_object_rmse_mm": 39.9,
            "true_object_mean_mm": 39.6, "pred_object_mean_mm": 37.0}
    image = {"folder": "/x/real-sample", "index": 0, **{k: real[k] for k in real if k.startswith("object_")},
             "object_regions": 2, "object_region_errors": [{"area_px": 30000, "median_mm": 4.04, "mean_mm": 4.0},
                                                           {"area_px": 900, "median_mm": -1.0, "mean_mm": -1.1}]}
    report = {"config": {"scale": "cpu", "count": 400, "seed": 100, "model": "unet", "base_channels": 16,
                         "epochs": 10, "batch_size": 2, "lr": 5e-4, "loss": "compound", "object_mm": 1.0},
              "variants": [{"name": "s0", "generate": [], "train": ["--seed", "0"], "real": real,
                            "timing": {}, "rows": [{"row": "s0", "real": real, "real_per_image": [image]}]}]}
    md = markdown_report(report)
    assert "| row | object RMSE (mm) | level (mm) | relief (mm) | level / relief, mean split (mm) |" in md
    assert "| s0 | 6.00 | 4.50 | 4.10 | 4.20 / 4.29 | 3.00 | 20.0% | 100.0% |" in md
    assert "| s0 | real-sample/0 | 6.00 | 4.50 | 4.10 | 4.20 / 4.29 | 2 | 30000 px +4.0; 900 px -1.0 |" in md
    # a row measured before the split: blank cells, no per-image line
    old = {k: v for k, v in real.items() if "level" not in k and "relief" not in k}
    report["variants"][0]["rows"] = [{"row": "s0", "real": old}]
    md = markdown_report(report)
    assert "| s0 | 6.00 |  |  |  | 3.00 |" in md and "level and relief" not in md

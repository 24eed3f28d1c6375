"""The one opener of real data (``fppsim.dataio.readers.open_source``): every layout recognised, with what it provides."""

from __future__ import annotations

import shutil

import cv2
import numpy as np

from _helpers import write_figshare, write_native
from fppsim.dataio.readers import open_source
from fppsim.dataio.writers import save_psp_folder_sample, sums_from_phase


def _scan(root, n: int = 2, h: int = 16, w: int = 24):
    u = np.arange(w, dtype=np.float64)
    phase = np.broadcast_to(2 * np.pi * u / 8 + 1.0, (h, w)).copy()
    s, c, o = sums_from_phase(phase)
    image = (100 + 80 * np.cos(phase)).astype(np.uint8)
    for k in range(n):
        save_psp_folder_sample(root, f"{k + 1}", s, c, o, image)
    return phase, image


def test_every_kind_and_what_it_provides(tmp_path):
    fr, z = write_figshare(tmp_path / "fig", n=3, h=16, w=24)
    src = open_source(tmp_path / "fig")
    assert src.kind == "figshare" and src.ids() == ["0", "1", "2"] and src.complete_pair[0] == "figshare"
    assert np.array_equal(src.height_labels(), z[..., 0]) and src.phase("0") is None
    ids, imgs = zip(*src.fringe_images())
    assert ids == ("0", "1", "2") and imgs[0].dtype == np.uint8 and imgs[0].shape == (16, 24)

    write_figshare(tmp_path / "pair", n=1, h=16, w=24, fringe_name="fringe_pattern.npy", label_name="height_map.npy")
    assert open_source(tmp_path / "pair").kind == "real-sample"

    write_native(tmp_path / "nat", n=2, h=16, w=24)
    src = open_source(tmp_path / "nat")
    assert src.kind == "native" and src.has_manifest and src.height_labels() is None
    assert [i for i, _ in src.fringe_images()] == src.ids() and len(src.ids()) == 2

    phase, image = _scan(tmp_path / "scan")
    src = open_source(tmp_path / "scan")
    assert src.kind == "psp" and src.is_psp and src.has_images and src.ids() == ["1", "2"]
    assert np.allclose(src.phase("1"), phase) and np.array_equal(dict(src.fringe_images())["2"], image)
    shutil.copytree(tmp_path / "scan" / "iPattern", tmp_path / "shots" / "iPattern")
    src = open_source(tmp_path / "shots")
    assert src.kind == "ipattern" and src.ids() == ["1", "2"] and src.phase("1") is None
    shutil.copytree(tmp_path / "scan" / "Fringe", tmp_path / "broken" / "Fringe")
    assert open_source(tmp_path / "broken").kind == "psp-partial" and open_source(tmp_path / "broken").is_psp
    assert open_source(tmp_path).scan_folders() == ["broken", "nat", "scan", "shots"]

    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), image)
    np.save(tmp_path / "imgs" / "b.npy", image[None])
    assert open_source(tmp_path / "imgs").kind == "folder"
    assert [i for i, _ in open_source(tmp_path / "imgs").fringe_images()] == ["a"]
    assert open_source(tmp_path / "imgs" / "a.png").kind == "image"
    src = open_source(tmp_path / "imgs" / "b.npy")
    assert src.kind == "npy" and np.array_equal(next(src.fringe_images())[1], image)
    assert open_source(tmp_path / "nowhere").kind == "missing"


def test_a_scan_folder_wins_over_a_pair_it_also_holds(tmp_path):
    """As every command read it before: the phase-shifting sub-folders first, the pair still named."""
    _scan(tmp_path / "x")
    write_figshare(tmp_path / "x", n=1, h=16, w=24)
    src = open_source(tmp_path / "x")
    assert src.kind == "psp" and src.pair is not None and src.pair[0].name == "f1_80.npy"

"""Shared test helpers: the ../shared paths (computed once here) and tiny on-disk datasets.

The fringe encodes the height in a way a tiny CNN learns in a few epochs: vertical fringes whose
brightness envelope grows with the height (plus a phase shift), on a dark plane, with a projector
shadow (invalid pixels) beside each object. Label transform: the figshare preset
(label = 6 * height_mm - 97, invalid = -105 with fringe -1 there).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"  # third-party test data beside the checkout; tests skip cleanly without it
SHARED_MESHES = SHARED / "meshes"
REAL_SAMPLE = SHARED / "real-sample"


def scene(rng: np.random.Generator, h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(fringe8 uint8, height_mm float32, valid bool) of one random scene of 1-2 blobs."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    height = np.zeros((h, w))
    valid = np.ones((h, w), bool)
    for _ in range(int(rng.integers(1, 3))):
        cy, cx = rng.uniform(0.25, 0.75) * h, rng.uniform(0.2, 0.7) * w
        r = rng.uniform(0.12, 0.25) * min(h, w)
        peak = rng.uniform(10, 40)
        blob = peak * np.clip(1 - ((yy - cy) ** 2 + (xx - cx) ** 2) / r**2, 0, None) ** 0.5
        height = np.maximum(height, blob)
        shadow = ((yy - cy) ** 2 + (xx - cx - r - 2) ** 2 < (0.35 * r) ** 2) & (blob == 0)
        valid &= ~shadow
    envelope = 0.25 + 0.6 * height / 40.0
    fringe = 255 * envelope * (0.5 + 0.5 * np.cos(2 * np.pi * xx / 11.6 + 0.2 * height))
    fringe += rng.normal(0, 2.0, (h, w))
    fringe8 = np.clip(np.round(fringe), 0, 255).astype(np.uint8)
    fringe8[~valid] = 0
    return fringe8, height.astype(np.float32), valid


def write_figshare(folder, n: int = 8, h: int = 32, w: int = 64, seed: int = 0, squeeze: bool = False,
                   fringe_name: str = "f1_80.npy", label_name: str = "Z.npy") -> tuple[np.ndarray, np.ndarray]:
    """f1_80.npy + Z.npy, float32 (N, H, W, 1), figshare encoding. Returns (fringes, labels)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    fr = np.empty((n, h, w, 1), np.float32)
    z = np.empty((n, h, w, 1), np.float32)
    for i in range(n):
        f8, hmm, valid = scene(rng, h, w)
        fr[i, ..., 0] = f8.astype(np.float32) / 127.5 - 1
        lab = (hmm * 6.0 - 97.0).astype(np.float32)
        lab[~valid] = -105.0
        fr[i, ..., 0][~valid] = -1.0
        z[i, ..., 0] = lab
    if squeeze:
        fr, z = fr[..., 0], z[..., 0]
    np.save(folder / fringe_name, fr)
    np.save(folder / label_name, z)
    return fr, z


def write_native(folder, n: int = 8, h: int = 32, w: int = 64, seed: int = 0, psp: bool = False) -> list[str]:
    """fppsim native layout written by fppsim's own writer (write_sample_folder + reconcile)."""
    from fppsim.formats import reconcile, sample_id
    from fppsim.writers import write_sample_folder

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    ids = []
    for i in range(n):
        sid = sample_id(i)
        f8, hmm, valid = scene(rng, h, w)
        arrays = {"height": hmm, "depth": (500.0 - hmm).astype(np.float32),
                  "phase_true": np.zeros_like(hmm), "mask": valid.astype(np.float32)}
        if psp:
            arrays.update(height_psp=hmm + np.float32(0.01), mask_psp=valid.astype(np.float32),
                          phase_psp=np.zeros_like(hmm))
        meta = {"index": i, "seed": i, "version": "test", "rig": {}, "objects": [],
                "stats": {"valid_fraction": float(valid.mean())}}
        write_sample_folder(folder, sid, {"fringe.png": f8}, arrays, meta)
        ids.append(sid)
    reconcile(folder)
    return ids


def train_tiny(out, *data_args, model: str = "unet", epochs: int = 1, extra=()) -> Path:
    """Train a tiny model through the CLI (base 4 channels); returns the run folder."""
    from uhrnet.cli import main

    rc = main(["train", *map(str, data_args), "--model", model, "--base-channels", "4", "--epochs", str(epochs),
               "--loss", "l2", "--lr", "1e-3", "--out", str(out), "--no-progress", *map(str, extra)])
    assert rc == 0
    return Path(out)

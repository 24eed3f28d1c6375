"""Preview figure of native samples: fringe | height (mm) | mask, one row per sample."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from fppsim.dataio.formats import read_manifest
from fppsim.dataio.readers import load_native_sample
from fppsim.plots import pyplot, save_figure
from fppsim.errors import InputError

__all__ = ["write_preview"]


def write_preview(root: str | os.PathLike, path: str | os.PathLike, max_samples: int = 3) -> Path:
    """Write a PNG with up to ``max_samples`` rows (fringe, height in mm, valid mask); returns its path."""
    plt = pyplot()
    root, path = Path(root), Path(path)
    records = read_manifest(root)[:max_samples]
    if not records:
        raise InputError(f"{root}: no finished samples to preview")
    fig, axes = plt.subplots(len(records), 3, figsize=(15, 3.0 * len(records)), squeeze=False)
    for row, rec in zip(axes, records):
        s = load_native_sample(root / rec["id"])
        mask = s["mask"] > 0
        height = np.where(mask, s["height"], np.nan)
        row[0].imshow(s["fringe"], cmap="gray", vmin=0, vmax=255)
        row[0].set_title(f"{rec['id']}: fringe (8-bit)")
        im = row[1].imshow(height, cmap="viridis")
        row[1].set_title("height (mm above plane; shadows blank)")
        fig.colorbar(im, ax=row[1], fraction=0.03)
        row[2].imshow(mask, cmap="gray", vmin=0, vmax=1)
        row[2].set_title(f"valid mask ({100 * mask.mean():.1f}% valid)")
        for ax in row:
            ax.set_axis_off()
    fig.tight_layout()
    save_figure(fig, path, dpi=80)
    plt.close(fig)
    return path

"""What ``uhrnet predict`` writes of a height map besides the ``.npy``: the float32 TIFF, the colour preview and the
binary PLY point cloud (through a rig's camera rays, or on the pixel grid)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fppsim.files import atomic_path
from fppsim.geometry.rig import check_image_size
from uhrnet.errors import ConfigError

__all__ = ["points_from_rig", "points_from_grid", "write_ply", "write_tiff", "write_preview"]


def points_from_rig(rig, height_mm: np.ndarray) -> np.ndarray:
    """World points (H, W, 3) where each camera pixel's ray reaches world z = height (mm)."""
    check_image_size(rig, height_mm.shape, "", who="the rig camera is", error=ConfigError,
                     template="{who} {camera} but the image is {got}")
    cam = rig.camera
    return cam.ray_cut(cam.pixel_grid(), height_mm.astype(np.float64))[1]


def points_from_grid(height_mm: np.ndarray, pixel_size: float) -> np.ndarray:
    h, w = height_mm.shape
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    return np.stack([uu * pixel_size, (h - 1 - vv) * pixel_size, height_mm.astype(np.float64)], axis=-1)


def write_ply(path: Path, points: np.ndarray, grey: np.ndarray) -> int:
    """Binary little-endian PLY with float x, y, z and uchar red, green, blue; returns the point count."""
    ok = np.isfinite(points).all(axis=-1)
    pts, g = points[ok].astype(np.float32), grey[ok].astype(np.uint8)
    rec = np.empty(len(pts), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                    ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rec["red"] = rec["green"] = rec["blue"] = g
    header = ("ply\nformat binary_little_endian 1.0\ncomment uhrnet predicted height, millimetres\n"
              f"element vertex {len(rec)}\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(rec.tobytes())
    return len(rec)


def write_tiff(path: Path, array: np.ndarray) -> None:
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(np.ascontiguousarray(array, dtype=np.float32)).save(tmp, format="TIFF")


def write_preview(path: Path, height_mm: np.ndarray, cmap: str, vrange) -> None:
    from matplotlib import colormaps  # (colour maps only: no figure, so no backend to set up)

    finite = height_mm[np.isfinite(height_mm)]
    if vrange is None:
        vrange = np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0)
    lo, hi = float(vrange[0]), float(vrange[1])
    scaled = np.clip((height_mm - lo) / (hi - lo if hi > lo else 1.0), 0, 1)
    rgb = (colormaps[cmap](np.nan_to_num(scaled))[..., :3] * 255).round().astype(np.uint8)
    rgb[~np.isfinite(height_mm)] = 128
    import cv2

    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), rgb[..., ::-1]):
            raise OSError(f"cannot write {path}")

"""Synthetic scenes shaped like a rig's own frames: the ``scenes`` section that ``fppsim fit-rig`` (without
``--base``) writes into the rig file, which ``fppsim generate --scenes auto`` renders.

A scene scaled as a whole gives the same images, and so does a steeper triangulation angle with lower
objects: what the frames fix is each object's extent in camera pixels and its relief in radians of phase.
Through the rig chosen for them (distance and baseline given, or assumed) these become millimetres:

    extent_mm = extent_px * distance / focal_px,     relief_mm: Phi(relief_mm) - Phi(0) = relief_rad

at the image centre (:func:`relief_height`). The scenes' ranges are these times fixed
proportions (:data:`FOOTPRINT_PER_EXTENT`, :data:`RELIEF_PER_RELIEF`): the ones under which the figshare rig's
held-out frame FP1523/1201, as fit-rig measures it (largest object 107 mm across, phase relief 27.9 rad =
30.3 mm through the default rig's geometry), gives the default :class:`fppsim.rendering.scene.SceneRanges` (70-140 mm across,
relief capped at 35-55 mm). So the scenes follow the frames at whatever depth scale the rig has, from a
figurine to a face that fills the view, instead of the depth scale being bent to fit fixed scenes.

The measures: the largest object (a connected region of lit pixels with fringes off the plane; with no plane in
view, of pixels with a phase; the longer side of its bounding box; one that reaches the image border is at least
that big) and the objects' phase relief (99th percentile of
the phase off the plane, phase-shifting scans only). Without a relief (plain fringe images, or no plane
to measure it from) the relief cap keeps the default scenes' proportion to the footprint.
"""

from __future__ import annotations

import numpy as np

__all__ = ["FOOTPRINT_PER_EXTENT", "RELIEF_PER_RELIEF", "DEFAULT_FOOTPRINT", "DEFAULT_MAX_RELIEF",
           "DEFAULT_PEDESTAL", "relief_height", "frame_scenes", "scenes_line"]

# the default SceneRanges' (fppsim.rendering.scene; not imported: it brings trimesh into fit-rig's start)
DEFAULT_FOOTPRINT = (70.0, 140.0)
DEFAULT_MAX_RELIEF = (35.0, 55.0)
DEFAULT_PEDESTAL = (10.0, 35.0)
# FP1523/1201 as fit-rig measures it (107 mm, 30 mm) -> the default ranges (70-140 mm, 35-55 mm)
FOOTPRINT_PER_EXTENT = (0.65, 1.3)
RELIEF_PER_RELIEF = (1.15, 1.8)


def relief_height(rig, relief_rad: float) -> float:
    """The height (mm) above the plane whose phase at the image centre differs from the plane's by
    ``relief_rad`` through ``rig`` (the phase shift per mm grows with the height: a constant rate from the
    plane would overstate a 40 mm relief by about 10 %); NaN beyond 90 % of the camera's height."""
    cam = rig.camera
    h = np.linspace(0.0, 0.9 * float(cam.center[2]), 4096)
    uv = np.tile(np.array([[cam.width // 2, cam.height // 2]], np.float64), (h.size, 1))
    shift = np.abs(rig.phase_at_height(h, uv) - rig.phase_at_height(0.0, uv[:1])[0])
    past = np.nonzero(np.isfinite(shift) & (shift >= relief_rad))[0]
    if not past.size:
        return float("nan")
    k = int(past[0])
    if k == 0:
        return 0.0
    return float(np.interp(relief_rad, shift[k - 1:k + 1], h[k - 1:k + 1]))


def frame_scenes(extent_px: float, relief_rad: float, rig, at_border: bool = False) -> dict | None:
    """The scene ranges (mm) for frames whose largest object is ``extent_px`` camera pixels across and whose
    objects' phase relief is ``relief_rad`` (0: not measured), seen through ``rig`` (its camera height above
    the plane and focal length, :func:`relief_height`; module docstring). ``at_border``: the object reaches
    the image border (its extent is a lower bound).

    Returns the rig file's ``scenes`` mapping: ``footprint`` and ``max_relief`` ([lo, hi] mm), the
    ``pedestal_height`` range scaled with the relief cap, and ``measured`` (the measures, in words); None
    when no object was measured (the default scenes stay)."""
    distance, focal = float(rig.camera.center[2]), float(rig.camera.K[0, 0])
    if not (extent_px > 0 and distance > 0 and focal > 0):
        return None
    extent = extent_px * distance / focal
    footprint = [round(extent * k, 1) for k in FOOTPRINT_PER_EXTENT]
    measured = (f"largest object {extent_px:.0f} px across{' (it reaches the image border: at least)' if at_border else ''}"
                f", {extent:.0f} mm at {distance:.0f} mm")
    relief = relief_height(rig, relief_rad) if relief_rad > 0 else float("nan")
    if relief > 0:
        max_relief = [round(relief * k, 1) for k in RELIEF_PER_RELIEF]
        measured += f"; phase relief {relief_rad:.1f} rad, {relief:.0f} mm through the rig"
    else:
        ratio = footprint[1] / DEFAULT_FOOTPRINT[1]
        max_relief = [round(v * ratio, 1) for v in DEFAULT_MAX_RELIEF]
        measured += "; relief not measured: the default scenes' proportion to the footprint"
    scale = max_relief[1] / DEFAULT_MAX_RELIEF[1]
    pedestal = [round(v * scale, 1) for v in DEFAULT_PEDESTAL]
    return {"footprint": footprint, "max_relief": max_relief, "pedestal_height": pedestal, "measured": measured}


def scenes_line(scenes: dict | None) -> str:
    """The report's line on the scenes (fit-rig's and generate's words for the same section)."""
    if scenes is None:
        return (f"no object measured: the default scenes ({DEFAULT_FOOTPRINT[0]:.0f}-{DEFAULT_FOOTPRINT[1]:.0f} mm "
                f"across, relief capped at {DEFAULT_MAX_RELIEF[0]:.0f}-{DEFAULT_MAX_RELIEF[1]:.0f} mm)")
    (a, b), (c, d) = scenes["footprint"], scenes["max_relief"]
    return f"objects {a:.0f}-{b:.0f} mm across, relief capped at {c:.0f}-{d:.0f} mm ({scenes['measured']})"

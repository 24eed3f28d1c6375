"""What ``fppsim fit-rig`` without ``--base`` found (:class:`StartRigResult`, made by
:func:`fppsim.fitting.rig_start.rig_from_images`) and its report: what the images told and what was assumed,
one line each (:func:`first_lines` before the fit, :func:`start_lines` after it); nothing here fits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fppsim.fitting.frame_scenes import scenes_line
from fppsim.fitting.plane_phase import PlanePhaseFit
from fppsim.geometry.rig import Rig
from fppsim.phase.fringe_axis import rig_phase_gradient
from fppsim.phase.plane import PLANE_SIDES, plane_sides, sides_reached

__all__ = ["StartRigResult", "POOR_PLANE_SHARE", "POOR_PLANE_RAD", "plane_fits_poorly", "plane_image_share",
           "plane_side_shares", "poor_plane_words", "first_lines", "start_lines"]

# the plane model fits scans poorly (no plane in view, or a phase read the wrong way) on less than this share of
# the IMAGE or beyond this median residual (rad): the real frames with a plane fit to 0.03-0.15 rad on 19-76 % of
# the image (FP147's face fills the view: 19 %); FP1523 and FP672 with their plane blacked out leave a plane model
# 6 % (a figurine's smooth front fits it to 0.15 rad on 42 % of the valid pixels, which share of the valid
# pixels alone would take for a plane). Both margins are thin (FP147's face on black, 62 % of the view: 0.31 rad,
# 40 % of the image), and a smooth object on black passes both (a tilted slab, 37 % of the image, 0.00 rad), so the
# plane pixels must also reach beyond the view as a reference plane does (fppsim.phase.plane.PLANE_SIDES sides,
# evaluate-phase's rule): frames with their plane reach 3-4 sides (FP147's plane beside its face: 2), FP1523, FP672
# and the pair on black 0-1; an object the borders cut reaches them too (FP147's face on black: 2-3 sides), which
# only its residual refuses
POOR_PLANE_SHARE = 0.1
POOR_PLANE_RAD = 0.25


@dataclass
class StartRigResult:
    """What :func:`fppsim.fitting.rig_start.rig_from_images` found: the fitted ``rig``, the plane-phase ``fit``,
    the maps' ``kind`` (``"phase"`` or ``"fringe images"``), how many, the measured plane ``gradient`` (rad/px), the fringe
    ``axis``, the projector ``side`` (+1: raised surfaces lower the phase) and where it came from, the
    assumptions made (``assumed``: name -> value), the report ``lines``, what the frames show of their objects
    (``extent_px``, ``at_border``, ``relief_rad``) and the synthetic ``scenes`` that follow them
    (:func:`fppsim.fitting.frame_scenes.frame_scenes`, through this ``rig``)."""

    rig: Rig
    fit: PlanePhaseFit
    kind: str
    n_maps: int
    gradient: tuple
    axis: str
    side: int
    side_source: str
    where: str
    sensitivity: float
    assumed: dict
    lines: list
    images: list = field(default_factory=list, repr=False)
    params: tuple = ()  # the plane fit's parameters (PLANE_PARAMS, + LENS_PARAMS when a lens was fitted)
    lens: tuple | None = None  # (pinhole rad, with k1 rad, k1) when a lens was tried
    relief_rad: float = 0.0  # the objects' phase relief (scans)
    extent_px: float = 0.0  # the largest object's extent
    at_border: bool = False  # it reaches the image border (at least that big)
    no_plane: bool = False  # no plane in view: the projector's pose is assumed (given distance, baseline, side)
    absolute: bool = True  # the maps are measured absolute phase (scans), not single-shot phase
    scenes: dict | None = None  # the rig file's scenes (fppsim.fitting.frame_scenes)

    def to_dict(self) -> dict:
        cam = self.rig.camera
        return {"source": self.kind, "maps": self.n_maps, "camera_px": [cam.width, cam.height],
                "camera_focal_px": float(cam.K[0, 0]), "gradient_rad_per_px": list(self.gradient),
                "fringes": self.axis, "projector": self.where, "projector_side_from": self.side_source,
                "centre_sensitivity_rad_per_mm": self.sensitivity, "assumed": self.assumed,
                "objects": {"largest_px": self.extent_px, "at_border": self.at_border, "relief_rad": self.relief_rad},
                "scenes": self.scenes, "no_plane": self.no_plane,
                "plane_fit": self.fit.to_dict()}




def plane_fits_poorly(fit: PlanePhaseFit) -> bool:
    """The plane model explains the scans' phase poorly: on under :data:`POOR_PLANE_SHARE` of the image
    (:func:`plane_image_share`), with a median residual above :data:`POOR_PLANE_RAD`, or on pixels that reach fewer
    than :data:`fppsim.phase.plane.PLANE_SIDES` of the image's sides (:func:`plane_side_shares`): no reference plane
    in view (a smooth object on black can follow the model on most of the few valid pixels, or on a third of the
    image inside it), or a phase written another way than it was read."""
    return (plane_image_share(fit) < POOR_PLANE_SHARE or fit.median_rad > POOR_PLANE_RAD
            or sides_reached(plane_side_shares(fit)) < PLANE_SIDES)


def plane_image_share(fit: PlanePhaseFit) -> float:
    """The plane pixels' share of the whole image, mean over the maps."""
    return float(np.mean([np.mean(p) for p in fit.planes]))


def plane_side_shares(fit: PlanePhaseFit) -> list[float]:
    """The share of each image side (top, bottom, left, right) the plane pixels reach
    (:func:`fppsim.phase.plane.plane_sides`), mean over the maps, as :func:`plane_image_share`: the maps share one
    plane fit, and an object hiding a side in one map hides it in the mean only in part. The masks hold only pixels
    with a phase: an invalid border narrower than the band (1 % of the shorter side, at least 2 px) is crossed; a
    plain image's single-shot phase, ragged at the borders, loses some (FP1523 as a PNG: 31 % of its left side, 9 %
    at the edge itself)."""
    return [float(x) for x in np.mean([plane_sides(p) for p in fit.planes], axis=0)]


def poor_plane_words(fit: PlanePhaseFit) -> str:
    """How the plane model fits, as the lines that call it poor say it."""
    return (f"{fit.median_rad:.2f} rad on {np.mean(fit.plane_share):.0%} of the valid pixels, "
            f"{plane_image_share(fit):.0%} of the image, reaching {sides_reached(plane_side_shares(fit))} of its 4 "
            f"sides; a reference plane: {POOR_PLANE_SHARE:.0%} of the image or more, within {POOR_PLANE_RAD:g} rad, "
            f"reaching {PLANE_SIDES} or more")


SATURATED_SHARE = 0.1
"""An image with this share of its pixels at its own maximum or more is over-exposed (a camera image has a few)."""


def saturation_words(images) -> str:
    """``''``, or the clause that names an over-exposed image among ``images`` (objects with ``gray`` and ``name``):
    a saturated plane shows no fringes, so the plane model cannot find it (a frame with 48 % of its pixels at 255 was
    refused as having no plane in view, without a word of why)."""
    shares = [(float(np.mean(g >= g.max())), im.name) for im in images  # a black or flat image has no bright end
              if (g := np.asarray(im.gray, np.float64)).size and np.isfinite(g.max()) and g.max() > max(g.min(), 0)]
    share, name = max(shares, default=(0.0, ""))
    return (f"; {name} has {share:.0%} of its pixels saturated (at its maximum, no fringes there): lower the "
            "exposure" if share >= SATURATED_SHARE else "")


def first_lines(path, maps, kind: str, images) -> list[str]:
    """What was read: how many maps of which kind, their size, and how the scans' files were read."""
    H, W = maps[0].phase.shape
    what = "phase-shifting scan(s): absolute phase" if kind == "phase" else "fringe image(s): single-shot phase"
    lines = [f"{path}: {len(maps)} {what}, {W} x {H} px"]
    note = next((im.read_as for im in images if im.read_as), None)  # the first scan read another way stands for all
    return lines + ([note] if note else [])


def _fringes_source(r: StartRigResult) -> str:
    """Where a rig without a plane in view got its fringe period (the fringes line's tail)."""
    if not r.no_plane:
        return ""
    if "fringe_period" in r.assumed:
        return ("; NOT identifiable without the plane: measured on the objects, whose surfaces widen or narrow the "
                "fringes; give --fringe-period PX (the plane's, from any frame that shows it) if you know it")
    return "; the period given (--fringe-period), no lean"


def _camera_and_fringes(r: StartRigResult) -> list[str]:
    cam, (W, H) = r.rig.camera, (r.rig.camera.width, r.rig.camera.height)
    fov_now = math.degrees(2 * math.atan((W / 2.0) / cam.K[0, 0]))
    gu, gv = rig_phase_gradient(r.rig)  # the fitted rig's, at the image centre
    period = 2 * math.pi / math.hypot(gu, gv)
    # the lines' angle from the image's vertical (horizontal), positive leaning right going down (up)
    lean = math.degrees(math.atan(-gv / gu)) if r.axis == "vertical" else math.degrees(math.atan(-gu / gv))
    grows = ("to the right" if r.gradient[0] > 0 else "to the left") if r.axis == "vertical" else \
        ("downwards" if r.gradient[1] > 0 else "upwards")
    conv = "measured" if r.absolute else "a convention: one fringe image cannot tell"
    return [f"camera     {W} x {H} px (the images'); focal {cam.K[0, 0]:.1f} px = {fov_now:.1f} deg across: "
            + ("given" if "fov_deg" not in r.assumed else "NOT identifiable from images: assumed (the default rig's "
                                                          "field of view; --fov DEG or --focal PX)"),
            f"fringes    {r.axis}: {period:.2f} px per period at the centre, the phase grows {grows} ({conv}), "
            f"lines {lean:+.2f} deg off the image axis" + _fringes_source(r),
            f"projector  {r.where}: {r.side_source}"]


def _depth(r: StartRigResult) -> list[str]:
    cam, s, assumed = r.rig.camera, r.sensitivity, r.assumed
    base_mm = float(np.linalg.norm(r.rig.projector.center[:2] - cam.center[:2]))
    d_txt = "assumed: the default rig's" if "distance_mm" in assumed else "given"
    b_txt = "assumed: 0.66 x the distance, the default rig's angle" if "baseline_mm" in assumed else "given"
    lines = [f"depth      distance {cam.center[2]:.0f} mm ({d_txt}), baseline {base_mm:.0f} mm ({b_txt})"]
    if "distance_mm" in assumed or "baseline_mm" in assumed:
        lines.append("           NOT identifiable from images without height labels (the scene scaled as a whole "
                     "looks the same): give --distance and --baseline if you know them; the scenes follow the "
                     "frames at any scale")
    lines.append(f"           a raised surface shifts the phase by {s:+.3f} rad/mm at the image centre "
                 f"(one fringe period per {2 * math.pi / abs(s):.1f} mm of height)")
    where = ("the rig file's scenes, which fppsim generate renders" if r.scenes is not None else
             "the rig file records none, so fppsim generate renders the default ones")  # (it said 'the rig file's')
    lines.append(f"scenes     {scenes_line(r.scenes)}: {where}")
    return lines


def _plane_and_lens(r: StartRigResult) -> list[str]:
    fit, rig, params, lens = r.fit, r.rig, r.params, r.lens
    share = float(np.mean(fit.plane_share))
    if r.no_plane:
        return [f"plane fit  none: the plane model fits poorly ({poor_plane_words(fit)}), no reference plane in "
                "view; the projector's "
                "pose is ASSUMED (aimed at the view's centre from the given distance, baseline and side), "
                f"{rig.periods:.2f} periods across it from the "
                + ("objects' fringe period" if "fringe_period" in r.assumed else "given fringe period"),
                "not fitted the projector's yaw, pitch and roll beyond the fringes' direction; lens distortion"]
    p = fit.params
    pose = ", ".join(f"{k} {math.degrees(v):+.2f} deg" for k, v in p.items() if k not in ("periods", "k1"))
    lines = [f"plane fit  {', '.join(p)}: median |residual| {fit.median_rad:.3f} rad (RMS {fit.rms_rad:.3f}) on "
             f"{share:.0%} of the valid pixels (start: {fit.start_median_rad:.2f} rad); {pose}, "
             f"{rig.periods:.2f} periods across the projector"]
    if not r.absolute:
        lines.append("           (from single-shot phase: phase-shifting scans pin the plane's phase better)")
    elif plane_fits_poorly(fit):
        lines.append(f"           the plane model fits poorly ({poor_plane_words(fit)}): check that the scans show "
                     "the reference plane and how their phase is written (--convention, --negate-sin)")
    if "k1" in params:
        lines.append(f"lens       the camera's radial distortion k1 {fit.params['k1']:+.4f} (OpenCV, for the focal "
                     f"length above): the plane's phase fits {lens[0]:.3f} rad as a pinhole, {lens[1]:.3f} with it")
    elif lens is not None:
        lines.append(f"lens       no distortion fitted: k1 {lens[2]:+.4f} would leave {lens[1]:.3f} rad of the "
                     f"pinhole's {lens[0]:.3f} ({1 - lens[1] / lens[0]:.0%} gained: too little)")
    lines.append(f"not fitted {'the lens beyond k1' if 'k1' in params else 'lens distortion (none in the rig)'}; the "
                 f"projector's resolution ({rig.projector.width} x {rig.projector.height}, only the periods across it "
                 "matter)")
    return lines


def start_lines(r: StartRigResult) -> list[str]:
    """The report after the fit: camera, fringes, projector side, depth scale, plane fit, lens."""
    return _camera_and_fringes(r) + _depth(r) + _plane_and_lens(r)

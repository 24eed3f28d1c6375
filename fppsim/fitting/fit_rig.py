"""Fit a rig's projector pose and fringe period to real fringe images (``fppsim fit-rig``).

The fringe period a camera sees on the reference plane follows from the rig alone: a camera pixel
``(u, v)`` sees the plane point ``X(u, v)``, which the projector sees at column ``u_p(X)``; the pattern
``cos(2 pi f u_p / W_p)`` therefore has the horizontal period (camera pixels)

    T(u, v) = W_p / (f |d u_p / d u|)

(:func:`period_map` in :mod:`fppsim.fitting.fit_periods`; no rendering). A projector whose axis is not exactly parallel to the camera's
shows a period that drifts across the image, as the real figshare rig does (about 11.96 px in the left
half, 11.49 px in the right). :func:`measure_bands` measures the period per column band and per row band
of real images (plane pixels only where labels exist) with :func:`fppsim.phase.measure.estimate_period`, and
:func:`fit_rig` adjusts a few projector parameters (yaw / pitch / roll about the projector's centre,
baseline, periods across the projector, projector focal length) with :func:`scipy.optimize.least_squares`
until the band periods of :func:`period_map` match, and the fringe lines' angle on the plane
(:func:`plane_tilt` against :func:`fppsim.phase.measure.fringe_tilt` of the images: a rolled projector tilts
them; the real figshare rig by about -1.35 deg). The camera stays fixed; after every change the
projector's principal point is re-centred (lens shift) so the camera's view of the plane stays lit.

The height sensitivity (the fringe shift per mm a rig predicts, checked against labelled images) is
:mod:`fppsim.fitting.height_sensitivity`; :func:`fit_baseline` chooses the baseline with it. The whole
``fppsim fit-rig`` workflow (read the images, measure, fit, write the rig) is
:func:`fit_rig_images` (:class:`FitRigConfig`); the images come from :func:`fppsim.dataio.readers.load_fringe_images`.

Units: mm, radians, camera pixels for periods.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from fppsim.commands import ReportLines
from fppsim.errors import UsageError
from fppsim.files import JSON_SUFFIXES, RIG_SUFFIXES, Output, atomic_write_text, check_outputs, holds_keys, json_text
from fppsim.fitting.fit_depth import fit_depth, format_depth_fit
from fppsim.fitting.fit_periods import (PARAMETERS, BandPeriods, RigFit, adjust_rig, base_values, fit_rig_periods,
                                        format_fit, measure_bands)
from fppsim.fitting.height_sensitivity import centre_sensitivity, sensitivity_check
from fppsim.dataio.readers import FringeImage, check_read_convention, load_fringe_images
from fppsim.geometry.rig import Rig, RigError, check_image_size, load_rig
from fppsim.phase.fringe_axis import fringe_axis, rig_phase_gradient

__all__ = ["BaselineFit", "fit_baseline", "format_baseline_fit", "check_fit_options", "FitRigConfig",
           "FitRigResult", "fit_rig_images"]

@dataclass
class BaselineFit:
    """Result of :func:`fit_baseline`: the chosen baseline (mm), the period fit at it (``fit.rig`` is the
    fitted rig), the scan (baseline, mean coherence) and the per-image checks at the chosen baseline."""

    baseline: float
    fit: RigFit
    scan: list
    checks: list
    sensitivity: float

    def to_dict(self) -> dict:
        return {"baseline_mm": self.baseline, "centre_sensitivity_rad_per_mm": self.sensitivity,
                "scan": [{"baseline_mm": b, "coherence": c} for b, c in self.scan],
                "checks": [c.to_dict() for c in self.checks]}


def fit_baseline(images: list[FringeImage], measured: BandPeriods, base: Rig,
                 params: tuple[str, ...] = ("yaw", "focal"), baselines=None, refine: float = 2.0,
                 smooth: float = 4.0) -> BaselineFit | None:
    """Choose the camera-projector baseline whose height sensitivity matches labelled real images.

    For each candidate baseline (mm, default 120..480 in steps of 15) the rig's other ``params`` are
    refitted to the measured band periods (:func:`fit_rig`, so the plane's period map stays the real
    one; ``yaw`` when none is left besides the baseline), then :func:`sensitivity_check` scores every labelled image; the score is the object-pixel
    weighted mean coherence. The best grid point is refined in steps of ``refine`` mm. The baselines are
    distances: the projector stays on the base rig's side of the camera (a projector left of it, world -x,
    stays left; placing every candidate at +x turned such a rig's height sensitivity round). Returns None when
    no image has height labels with enough object pixels (plain images, phase-only folders).
    """
    labelled = [im for im in images if im.height_mm is not None]
    if not labelled:
        return None
    params = tuple(p for p in params if p != "baseline") or ("yaw",)  # the period map needs one to fit
    grid = np.arange(120.0, 481.0, 15.0) if baselines is None else np.asarray(baselines, dtype=np.float64)
    side = -1.0 if base_values(base)["baseline"] < 0 else 1.0  # the projector's side of the camera (world x)

    cache: dict = {}

    def score(b: float):
        b = round(float(b), 3)
        if b not in cache:
            try:
                fit = fit_rig_periods(measured, adjust_rig(base, baseline=side * b), params)
            except RigError:
                cache[b] = (-1.0, None, [])
                return cache[b]
            checks = [c for c in (sensitivity_check(fit.rig, im, smooth) for im in labelled) if c is not None]
            if not checks:
                cache[b] = (float("nan"), fit, [])
            else:
                wts = np.array([c.n_object for c in checks], dtype=np.float64)
                cache[b] = (float(np.sum(wts * [c.coherence for c in checks]) / wts.sum()), fit, checks)
        return cache[b]

    coarse = [(float(b), score(b)[0]) for b in grid]
    if all(not np.isfinite(c) for _, c in coarse):
        return None
    best = max((c, b) for b, c in coarse if np.isfinite(c))[1]
    step = float(np.min(np.diff(np.sort(grid)))) if len(grid) > 1 else 0.0
    if refine and step > refine:
        for b in np.arange(best - step + refine, best + step, refine):
            if b > 0:
                score(b)
    scan = sorted((b, v[0]) for b, v in cache.items() if np.isfinite(v[0]) and v[1] is not None)
    best = max(scan, key=lambda t: t[1])[0]
    _, fit, checks = cache[round(best, 3)]
    return BaselineFit(float(best), fit, scan, checks, centre_sensitivity(fit.rig))


def format_baseline_fit(fit: BaselineFit) -> str:
    """Plain-text summary of :func:`fit_baseline`: the coherence scan and the chosen baseline."""
    lines = ["height sensitivity from the labels (re-projected surface vs real fringes; 1 = matches)",
             f"{'baseline mm':>12}{'coherence':>11}"]
    lines += [f"{b:>12.1f}{c:>11.3f}" for b, c in fit.scan]
    slopes = [c.slope for c in fit.checks if np.isfinite(c.slope)]
    lines.append(f"chosen baseline {fit.baseline:.1f} mm: {abs(fit.sensitivity):.3f} rad of fringe shift per mm "
                 f"at the image centre; residual slope {np.median(slopes) if slopes else float('nan'):+.4f} rad/mm "
                 f"over {len(fit.checks)} labelled image(s)")
    return "\n".join(lines)


# ====================================================================== the fit-rig workflow
@dataclass
class FitRigConfig:
    """What ``fppsim fit-rig`` does (the fields are its flags).

    real : real fringe images (any layout :func:`fppsim.dataio.readers.load_fringe_images` reads).
    out : the fitted rig file (.json, or .yaml/.yml); refused if it exists unless ``force``.
    base : rig to start from (camera kept fixed); None: the packaged default rig.
    params : names of :data:`fppsim.fitting.fit_periods.PARAMETERS` to fit. col_bands, row_bands : bands measured (>= 1 each).
    max_images : evenly spaced images read (>= 1).
    convention / negate_sin : how the public layout's PSin / PCos / Order make the phase
        (:func:`fppsim.dataio.readers.load_psp_folder_sample`).
    sensitivity : ``"auto"``: with height labels, first choose the baseline whose fringe shift per mm
        matches them (:func:`fit_baseline`), then fit ``params`` at it; ``"off"``: keep the base baseline.
    json : also write measured / base / fitted band periods (and the sensitivity scan) there.
    """

    real: str | os.PathLike
    out: str | os.PathLike
    base: str | os.PathLike | None = None
    params: tuple[str, ...] = ("yaw", "roll", "periods")
    col_bands: int = 4
    row_bands: int = 3
    max_images: int = 20
    sensitivity: str = "auto"
    json: str | os.PathLike | None = None
    force: bool = False
    convention: str = "auto"
    negate_sin: bool = False

    def __post_init__(self):
        check_fit_options(self)


def check_fit_options(cfg) -> None:
    """:class:`fppsim.errors.UsageError` (exit 2) for a fit-rig option wrong on its own: the band counts,
    ``max_images``, ``params``, ``sensitivity`` and ``convention`` of ``cfg`` (every fit-rig configuration has
    them)."""
    for key in ("col_bands", "row_bands", "max_images"):
        if getattr(cfg, key) < 1:
            raise UsageError(f"--{key.replace('_', '-')} must be >= 1, got {getattr(cfg, key)}")
    unknown = [p for p in cfg.params if p not in PARAMETERS]
    if unknown or not cfg.params:
        raise UsageError(f"--params: unknown or no parameter(s) to fit: {', '.join(unknown) or 'none'} "
                         f"(known: {', '.join(PARAMETERS)})")
    if cfg.sensitivity not in ("auto", "off"):
        raise UsageError(f"--sensitivity must be 'auto' or 'off', got {cfg.sensitivity!r}")
    check_read_convention(cfg.convention)


@dataclass
class FitRigResult:
    """What :func:`fit_rig_images` did: the images' ``layout`` and count, the period ``fit`` (``fit.rig``
    is the rig written to ``out``), the baseline fit when the sensitivity was fitted, and the report
    ``lines`` (what ``fppsim fit-rig`` prints); ``depth``: the :class:`fppsim.fitting.fit_depth.DepthFit` when
    ``distance`` was fitted."""

    layout: str
    n_images: int
    fit: RigFit
    baseline: BaselineFit | None
    out: Path
    lines: list[str]
    depth: object = None

    def to_dict(self) -> dict:
        """The JSON document of ``FitRigConfig.json``: the period fit (and ``sensitivity``, ``depth``)."""
        doc = self.fit.to_dict()
        if self.baseline is not None:
            doc["sensitivity"] = self.baseline.to_dict()
        if self.depth is not None:
            doc["depth"] = self.depth.to_dict()
        return doc


def unused_label_options(config, labelled: bool, axis: str = "vertical") -> None:
    """Without a base rig (:class:`fppsim.fitting.rig_start.StartRigConfig`) the period-fit options
    ``config.label_options`` names as given (and a ``distance`` fit) steer only the label-based fit: refused
    (:class:`UsageError`) when it cannot run, the images having no height labels or their fringes not being
    vertical (``axis``), instead of being ignored."""
    given = tuple(config.label_options) + (("--params distance",) if "distance" in config.params
                                           and "--params" not in config.label_options else ())
    why = ("needs height labels" if not labelled else
           "reads vertical fringes" if axis != "vertical" else None)
    if given and why:
        has = "none" if not labelled else f"{axis} fringes"
        raise UsageError(f"{', '.join(given)}: without --base these steer only the label-based fit, which {why}; "
                         f"{config.real} has {has}: drop them (the rig from the images fits its own parameters), "
                         "or give --base RIG")


def fit_rig_images(config: FitRigConfig, echo: Callable[[str], None] | None = None) -> FitRigResult:
    """Read real fringe images, measure their band periods (:func:`measure_bands`), fit the rig (the
    baseline first with ``sensitivity="auto"`` and labelled images: :func:`fit_baseline`; else
    :func:`fit_rig`), write it to ``config.out`` (and the JSON report). ``echo`` receives every report
    line as soon as it is known (the command line passes ``print``); the lines are also in the result.
    """
    lines = ReportLines(echo)
    say = lines.say
    out, *_ = check_outputs([Output("--out", config.out, RIG_SUFFIXES, "a rig file",
                                    holds_keys("camera", "projector")),
                             Output("--json", config.json, JSON_SUFFIXES, "the JSON report",
                                    holds_keys("params", "measured"))],
                            inputs=[config.real, config.base], force=config.force)  # before any work
    base = load_rig(config.base)
    if fringe_axis(rig_phase_gradient(base)) != "vertical":  # the band periods below are read across vertical fringes
        raise RigError(f"--base {config.base}: its fringes are horizontal (the projector above or below the camera); "
                       "fit-rig with --base fits vertical fringes only: leave --base out (the rig is then built "
                       "from the images)")
    images, layout = load_fringe_images(config.real, config.max_images, convention=config.convention,
                                        negate_sin=config.negate_sin)
    if images:  # before measuring: another rig's images fail there with a less telling message
        check_image_size(base, images[0].gray.shape, "", template="the images are {got} px but the rig's camera is "
                         "{camera}", sep=" x ")
    measured = measure_bands(images, config.col_bands, config.row_bands)
    say(f"{config.real}: {len(images)} image(s), layout {layout}")
    note = next((im.read_as for im in images if im.read_as), None)  # the first scan read another way stands for the folder
    if note:
        say(note)
    dfit = None
    if "distance" in config.params:
        # distance (with the baseline) comes from the labels' phase-height relation, not the period map
        if config.sensitivity != "auto":
            raise RigError("fitting 'distance' needs the height labels: drop it from the parameters or use "
                           "sensitivity 'auto'")
        dfit = fit_depth(images, measured, base, config.params)
        if dfit is None:
            raise RigError("fitting 'distance' needs images with height labels, objects and projector shadows "
                           "(figshare folder or the real-sample pair)")
        say(format_depth_fit(dfit))
        say("")
    bfit = fit_baseline(images, measured, base, config.params) \
        if config.sensitivity == "auto" and dfit is None else None
    if dfit is not None:
        fit = dfit.fit  # the period fit at the chosen distance and baseline
    elif bfit is not None:
        say(format_baseline_fit(bfit))
        say("")
        fit = bfit.fit  # the period fit at the chosen baseline: nothing to refit
    else:
        if config.sensitivity == "auto":
            say("height sensitivity: no labelled images with enough object pixels; baseline kept")
        fit = fit_rig_periods(measured, base, config.params)
    say(format_fit(fit))
    fit.rig.save(out)
    say(f"rig: {out}")
    result = FitRigResult(layout, len(images), fit, bfit, out, list(lines), dfit)
    if config.json:
        atomic_write_text(config.json, json_text(result.to_dict(), indent=1))
    return result

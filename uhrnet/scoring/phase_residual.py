"""Calibration-free phase residual: predicted heights checked against real absolute phase (no height
labels), for one image (:func:`fit_phase`, :func:`evaluate_phase`; plain numpy) and for a folder of
real phase-shifting data (:func:`evaluate_phase_folder`, which ``uhrnet evaluate-phase`` calls).

On a fringe projection rig the absolute phase of a camera pixel is, to a very good approximation,
a smooth function of the pixel position (the reference plane's phase) plus a smooth function of the
height above the plane. Without a calibration the two are unknown, so they are fitted:

    Phi(x, y) ~ sum_{i + j <= d} c_ij x^i y^j  +  a h(x, y)  +  b h(x, y)^2

by least squares over the valid pixels, ``x, y`` being the pixel column / row scaled to [-1, 1] and
``h`` the predicted height in mm. A good height prediction leaves a small residual; a flat prediction
(``h = 0``) leaves the whole relief. Reported (per image):

* ``rmse_rad``: RMSE of the residual phase (rad) over the fitted pixels;
* ``relief_rms_rad``: RMS of the relief phase, the residual of the plane-only fit (``a = b = 0``);
* ``explained``: fraction of the relief phase explained, ``1 - SS_res / SS_relief`` (1 = perfect, 0 = no
  better than a flat predictor, negative impossible for least squares);
* ``a_rad_per_mm, b_rad_per_mm2`` and the plane coefficients; ``rmse_mm_equiv = rmse_rad / |a|``, the
  residual expressed in mm at the fitted phase-per-mm scale (rough: ignores the h^2 term); over a folder,
  the images' mean residual over their mean ``|a|``.

A second score fits the plane polynomial on the reference plane's own pixels alone (``plane_pixels``; the
folder evaluation finds them in the real phase, :func:`fppsim.phase.plane.phase_plane_masks`), then ``a, b``
with that plane held: when an object covers much of the view the all-pixel plane bows at the object's edge
(up to +-10 rad seen on a life-size head), which penalises the flat prediction and the network alike. The
all-pixel score stays the default (it needs no plane in view, and every earlier number is in it); the
report gives both, each with its flat baseline. A frame with no plane in view (:func:`view_plane`: the plane found
reaches fewer than two of the image's sides; or a ``--rig`` recording none) has no second score: null, said.

``robust=True`` replaces least squares by a few iteratively reweighted (Huber) iterations, which keeps
shadow edges, wrong fringe orders and prediction outliers from dominating; the reported sums are then
over the same pixels, unweighted.

Folder evaluation (:func:`evaluate_phase_folder`, :class:`PhaseEvalConfig`): reads the folder layout
of the public phase-retrieval data (``<root>/PSin``, ``PCos``, ``Fringe``, ``iPattern``, one
``<id>.mat`` each; :mod:`fppsim.dataio.readers`), predicts a height map from every iPattern image and fits the
real absolute phase as above. Writes to ``--out``: ``phase_results.md``, ``phase_results.json`` (per
model and image: residual phase RMSE in rad, fraction of the relief phase explained, fitted
coefficients; the same for the flat h = 0 baseline) and ``figures/<id>.png`` (single-shot image,
relief phase, each model's predicted height and residual phase map). torch and the checkpoints are
imported only there.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from fppsim.files import atomic_write_text, json_text
from fppsim.geometry.rig import check_image_size
from fppsim.owned import claim, output_folder
# the side rule's one owner is fppsim (fit-rig judges the same way); re-exported here under its old names
from fppsim.phase.plane import (PLANE_SIDE_BAND, PLANE_SIDE_SHARE, PLANE_SIDES, phase_plane_masks, plane_sides,
                                poly_basis, poly_terms, sides_reached)
from uhrnet.errors import ConfigError, DataError, InputError, UsageError
from fppsim.errors import NoPhaseError, PSPMatError, RigError
from fppsim.dataio.readers import load_ipattern, open_source, reading_note
from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint
from uhrnet.data.datasets import parse_size
from uhrnet.device import select_device
from uhrnet.scoring.chosen_frames import chosen_frames, chosen_words, phase_frames
from uhrnet.scoring.evaluation import check_name_count, model_names
from uhrnet.scoring.phase_report import frame_line, markdown, plot_phase_residuals
from uhrnet.scoring.reference_slips import frame_slips, slip_line, slip_markdown, slip_scores
from uhrnet.physics.orientation import flipped_warning, lean_warning
from uhrnet.inference.prediction import (NO_RIG_HINT, path_estimate, predict_labels, refine_rig_for,
                                        refine_with_phase, shape_note)

#: the name evaluate-phase's files carry in their folder's ownership record (:mod:`fppsim.owned`)
EVALUATE_PHASE_TOOL = "uhrnet evaluate-phase"

__all__ = ["PhaseFit", "fit_phase", "evaluate_phase", "PhaseEvalConfig", "evaluate_phase_folder",
           "markdown", "plot_phase_residuals", "PhaseValidation", "PLANE_SIDE_SHARE",
           "PLANE_SIDES", "PLANE_SIDE_BAND", "plane_sides", "view_plane"]


@dataclass
class PhaseFit:
    """Result of :func:`fit_phase` for one image (see the module docstring for the meaning)."""
    rmse_rad: float
    relief_rms_rad: float
    explained: float
    a_rad_per_mm: float
    b_rad_per_mm2: float
    rmse_mm_equiv: float
    plane_coefficients: list
    plane_terms: list
    pixels: int
    degree: int
    robust: bool
    plane_pixels: int | None = None  # None: the plane fitted with the heights on every pixel; else on these alone

    def to_dict(self) -> dict:
        return asdict(self)


def _solve(A: np.ndarray, b: np.ndarray, robust: bool, iterations: int, huber: float) -> np.ndarray:
    """Least squares (or Huber IRLS) coefficients; all-zero columns get coefficient 0."""
    live = np.any(A != 0, axis=0)
    coef = np.zeros(A.shape[1])
    if not live.any():
        return coef
    Al = A[:, live]
    # column scaling keeps lstsq well conditioned when h^2 reaches thousands of mm^2
    scale = np.sqrt((Al * Al).mean(axis=0))
    scale[scale == 0] = 1.0
    As = Al / scale
    sol = np.linalg.lstsq(As, b, rcond=None)[0]
    if robust:
        for _ in range(iterations):
            r = b - As @ sol
            s = 1.4826 * np.median(np.abs(r - np.median(r)))
            if not s > 0:
                break
            k = huber * s
            wgt = np.where(np.abs(r) <= k, 1.0, k / np.maximum(np.abs(r), 1e-300))
            sw = np.sqrt(wgt)
            sol = np.linalg.lstsq(As * sw[:, None], b * sw, rcond=None)[0]
    coef[live] = sol / scale
    return coef


def fit_phase(phase: np.ndarray, height_mm: np.ndarray, valid: np.ndarray | None = None, degree: int = 3,
              robust: bool = False, iterations: int = 5, huber: float = 1.345, max_pixels: int | None = 200_000,
              return_residual: bool = False, plane_pixels: np.ndarray | None = None):
    """Fit ``phase ~ plane(x, y) + a h + b h^2`` over valid pixels (see the module docstring).

    Parameters
    ----------
    phase : (H, W) absolute phase, rad (NaN where invalid).
    height_mm : (H, W) predicted height above the reference plane, mm (NaN where the prediction is
        invalid); all zeros is the flat baseline.
    valid : (H, W) bool, pixels to use (also restricted to finite phase and height).
    degree : total degree of the plane polynomial (default 3).
    robust : Huber IRLS (``iterations`` steps, threshold ``huber`` x the MAD scale) instead of plain
        least squares.
    max_pixels : fit on an evenly strided subset of at most this many pixels (None: all); the reported
        statistics use every valid pixel.
    return_residual : also return the (H, W) residual phase map (NaN outside the fitted pixels).
    plane_pixels : (H, W) bool, the reference plane's own pixels (e.g. :func:`fppsim.phase.plane.phase_plane_masks`):
        the plane polynomial is fitted on these alone (``h`` not used), then ``a, b`` on every valid pixel with
        the plane held. An object covering much of the view then cannot bend the plane (the all-pixel fit's
        plane bows at its edge, which penalises a flat and a good prediction alike); the relief is the phase
        minus that plane. ValueError when fewer plane pixels than twice the plane's terms.

    Returns
    -------
    :class:`PhaseFit` (and the residual map when asked). ValueError when fewer valid pixels than
    unknowns remain.
    """
    phi = np.asarray(phase, dtype=np.float64)
    h = np.asarray(height_mm, dtype=np.float64)
    if phi.ndim != 2 or phi.shape != h.shape:
        raise InputError(f"phase {phi.shape} and height {h.shape} must be the same 2-D shape")
    ok = np.isfinite(phi) & np.isfinite(h)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    P, names = poly_basis(*phi.shape, degree), poly_terms(degree)  # (H*W, n_terms): the one plane basis
    n_unknown = len(names) + 2
    n = int(ok.sum())
    if n < 2 * n_unknown:
        raise InputError(f"only {n} valid pixels for {n_unknown} unknowns (degree {degree})")
    idx = np.flatnonzero(ok)
    fit_idx = idx if max_pixels is None or n <= max_pixels else idx[:: int(np.ceil(n / max_pixels))]
    Pf = P.T
    hv = h.ravel()
    b = phi.ravel()

    def design(sel):
        return np.concatenate([Pf[:, sel].T, hv[sel, None], hv[sel, None] ** 2], axis=1)

    A = design(fit_idx)
    if plane_pixels is None:
        coef_plane = _solve(A[:, :-2], b[fit_idx], robust, iterations, huber)
        coef = _solve(A, b[fit_idx], robust, iterations, huber)
    else:
        pidx = np.flatnonzero(ok & np.asarray(plane_pixels, bool))
        if pidx.size < 2 * len(names):
            raise InputError(f"only {pidx.size} plane pixels for {len(names)} plane terms (degree {degree})")
        if max_pixels is not None and pidx.size > max_pixels:
            pidx = pidx[:: int(np.ceil(pidx.size / max_pixels))]
        coef_plane = _solve(Pf[:, pidx].T, b[pidx], robust, iterations, huber)
        coef = np.r_[coef_plane, _solve(A[:, -2:], b[fit_idx] - A[:, :-2] @ coef_plane, robust, iterations, huber)]
    Aall = design(idx)
    relief = b[idx] - Aall[:, :-2] @ coef_plane
    resid = b[idx] - Aall @ coef
    ss_relief = float(np.sum(relief ** 2))
    ss_res = float(np.sum(resid ** 2))
    a = float(coef[-2])
    out = PhaseFit(
        rmse_rad=float(np.sqrt(ss_res / n)), relief_rms_rad=float(np.sqrt(ss_relief / n)),
        explained=float(1.0 - ss_res / ss_relief) if ss_relief > 0 else float("nan"),
        a_rad_per_mm=a, b_rad_per_mm2=float(coef[-1]),
        rmse_mm_equiv=float(np.sqrt(ss_res / n) / abs(a)) if a != 0 else float("nan"),
        plane_coefficients=[float(c) for c in coef[:-2]], plane_terms=names, pixels=n, degree=int(degree),
        robust=bool(robust), plane_pixels=None if plane_pixels is None else int((ok & np.asarray(plane_pixels, bool)).sum()))
    if not return_residual:
        return out
    res_map = np.full(phi.size, np.nan)
    res_map[idx] = resid
    return out, res_map.reshape(phi.shape)


def evaluate_phase(phase: np.ndarray, height_mm: np.ndarray, valid: np.ndarray | None = None,
                   plane_pixels: np.ndarray | None = None, **kw) -> dict:
    """:func:`fit_phase` for the prediction and for the flat (h = 0) baseline on the same pixels.

    Returns ``{"prediction": PhaseFit dict, "flat": PhaseFit dict, "residual": (H, W) map}``; with
    ``plane_pixels`` also ``"plane": {"prediction", "flat"}``, the same two fits with the plane fitted on
    those pixels alone (None when they are too few to fit it).
    """
    h = np.asarray(height_mm, dtype=np.float64)
    ok = np.isfinite(h) if valid is None else (np.asarray(valid, bool) & np.isfinite(h))
    pred, res = fit_phase(phase, h, ok, return_residual=True, **kw)
    flat = fit_phase(phase, np.zeros_like(h), ok, **kw)
    out = {"prediction": pred.to_dict(), "flat": flat.to_dict(), "residual": res}
    if plane_pixels is not None:
        try:
            out["plane"] = {"prediction": fit_phase(phase, h, ok, plane_pixels=plane_pixels, **kw).to_dict(),
                            "flat": fit_phase(phase, np.zeros_like(h), ok, plane_pixels=plane_pixels, **kw).to_dict()}
        except ValueError:  # too few plane pixels in view: the all-pixel score stands alone
            out["plane"] = None
    return out


# ------------------------------------------------------------------------------ a folder of real data
@dataclass
class PhaseEvalConfig:
    """What ``uhrnet evaluate-phase`` does; the fields are its flags (see :mod:`uhrnet.cli`)."""
    checkpoints: list
    phase_root: str | Path
    out: str | Path
    degree: int = 3
    robust: bool = False
    convention: str = "auto"
    negate_sin: bool = False
    mask_predicted_invalid: bool = False
    names: list | None = None
    ids: list | None = None
    limit: int | None = None
    figures: int = 3
    device: str = "auto"
    refine: str | None = None  # "phase": also score each model's heights refined by the image's phase (a row each)
    refine_method: str = "orders"
    rig: str | Path | None = None  # the rig --refine works through (default: the checkpoint's, else fppsim's)

    def __post_init__(self):  # an option value wrong on its own: a usage error (exit 2), before anything is read
        if self.degree < 0:
            raise UsageError(f"--degree must be >= 0, got {self.degree}")
        if self.limit is not None and self.limit < 1:
            raise UsageError(f"--limit must be >= 1, got {self.limit}")
        if self.figures < 0:
            raise UsageError(f"--figures must be >= 0, got {self.figures}")
        check_name_count(self.names, len(self.checkpoints))


def _mean(values) -> float:
    v = np.asarray([x for x in values if x is not None], dtype=float)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else float("nan")


def view_plane(phase: np.ndarray, pixels: np.ndarray, degree: int = 3) -> tuple[np.ndarray | None, list[float]]:
    """``(plane pixels, side shares)`` of a frame's reference plane for the plane-pixel score: the pixels
    :func:`fppsim.phase.plane.phase_plane_masks` finds among ``pixels``, None when they reach fewer than
    :data:`PLANE_SIDES` sides (:func:`plane_sides`): no plane in view. A first surface that does not is set aside and
    the rest searched once more (an object larger than the plane in view can win the consensus: FP147/109's face on 5
    of 12 draws, on black no second side); the side shares are the first surface's when neither reaches them."""
    pixels, sides = np.asarray(pixels, bool), None
    for _ in range(2):
        plane = phase_plane_masks(phase, pixels, degree=degree)[0]
        sides = sides or plane_sides(plane)
        if sides_reached(plane_sides(plane)) >= PLANE_SIDES:
            return plane, plane_sides(plane)
        pixels = pixels & ~plane
    return None, sides


def _fringe_input(image: np.ndarray):
    """The network input of a uint8 (H, W) fringe image: (1, 1, H, W) float32 in [-1, 1]."""
    import torch  # the module's plain-numpy fits load without torch

    return torch.from_numpy(image.astype(np.float32) / 127.5 - 1.0)[None, None]


def _scored_pixels(sample) -> np.ndarray:
    """The pixels a frame's fit uses: a valid phase and a lit (non-zero) image pixel."""
    return sample.valid & (sample.image > 0)


class PhaseValidation:
    """Real phase-shifting frames as an UNLABELLED validation set of a training run (``uhrnet train
    --val-phase``): :meth:`score` predicts every frame's height and returns the calibration-free phase
    residual (:func:`fit_phase`, as ``uhrnet evaluate-phase`` with its defaults) as a fraction of the flat
    prediction's on the same pixels, averaged over the frames.

    With two or more frames every second one (the 2nd, 4th, ...) is HELD OUT: ``val_phase_ratio`` (which
    picks ``best.pt``) is scored on the others, ``val_phase_heldout_ratio`` on these alone, so the run reports
    a real score the choice of epoch never saw (on FP147 an epoch picked on its own frame scored 0.47 of flat
    there and 0.64 on another frame). With one frame there is no held-out score, and a note says so.

    ``roots``: folders of the public layout (``PSin/ PCos/ Fringe/ iPattern/``); at most ``max_frames`` of
    their frames, evenly spaced over all of them in folder then id order. Frames are read and their flat
    fits done once, here. :class:`ConfigError` naming ``what`` (the flag) and the folder or file when one
    cannot be read, or when a frame is not ``shape`` (H, W) px (given: the training data's size; frames of
    another size are of another rig). ``convention`` / ``negate_sin``: how the frames' files make their phase
    (:func:`fppsim.dataio.readers.load_psp_folder_sample`).
    """

    def __init__(self, roots, max_frames: int, degree: int = 3, what: str = "--val-phase", shape=None,
                 convention: str = "auto", negate_sin: bool = False):
        frames = phase_frames(roots, what)
        if len(frames) > max_frames:
            frames = [frames[int(i)] for i in np.linspace(0, len(frames) - 1, max_frames).round()]
        self.degree = degree
        self.frames, self.notes, seen = [], [], {}  # notes: how frames read by --convention auto another way were read
        for root, sid in frames:
            try:
                s = open_source(root).scan(sid, convention=convention, negate_sin=negate_sin)
            except PSPMatError as exc:
                raise ConfigError(f"{what}: {exc}") from None
            note = reading_note(s.meta, (f"{what}-convention", f"{what}-negate-sin"))
            if note and not self.notes:  # the first frame read another way stands for the folders
                self.notes.append(note)
            if shape is not None and tuple(s.image.shape) != tuple(shape):
                raise ConfigError(f"{what}: {s.path}: the frame is {s.image.shape[1]} x {s.image.shape[0]} px but the "
                                  f"training images are {shape[1]} x {shape[0]}: give frames of the rig the data is of")
            digest = s.digest()
            if digest in seen:  # a copy of a frame already read (another folder holding the same scan)
                self.notes.append(f"{s.path} is the same frame as {seen[digest]}: read once")
                continue
            seen[digest] = s.path
            ok = _scored_pixels(s)
            try:
                flat = fit_phase(s.phase, np.zeros(s.phase.shape), ok, degree=degree).rmse_rad
            except ValueError as exc:
                raise ConfigError(f"{what}: {s.path}: {exc}") from None
            self.frames.append({"x": _fringe_input(s.image), "phase": s.phase, "pixels": ok, "flat_rad": flat,
                                "root": str(Path(root).resolve()), "id": sid, "digest": digest})
        for k, f in enumerate(self.frames):  # every second frame held out, once the frames are known distinct
            f["held_out"] = len(self.frames) > 1 and k % 2 == 1
        if len(self.frames) == 1:
            self.notes.insert(0, f"one frame ({frames[0][1]}): best.pt is chosen on the frame it is scored on; give two "
                                 "or more frames (not those the rig was fitted to) for a held-out score")

    def record(self) -> list[dict]:
        """``[{"root", "id", "held_out", "digest"}]`` of every frame scored: what a checkpoint keeps of them, so
        that :func:`uhrnet.scoring.chosen_frames.chosen_on` can tell evaluate-phase which frames (or copies of
        them: ``digest``, :meth:`fppsim.dataio.readers.PspMat.digest`) chose ``best.pt``."""
        return [{"root": f["root"], "id": f["id"], "held_out": bool(f["held_out"]), "digest": f["digest"]}
                for f in self.frames]

    def score(self, model, transform, size=None) -> dict:
        """``{"val_phase_ratio": mean residual / flat residual, "val_phase_rad": mean residual (rad)}`` of
        ``model`` (label units, as :func:`uhrnet.inference.prediction.predict_labels` takes it; put in
        eval mode) on the frames that choose the epoch, and ``val_phase_heldout_ratio`` /
        ``val_phase_heldout_rad`` on the held-out ones (NaN with one frame); ``transform`` turns its labels
        into mm; ``size``: the model's --resize."""
        import torch  # the module's plain-numpy fits load without torch

        ratios, rads = {False: [], True: []}, {False: [], True: []}
        with torch.no_grad():
            for f in self.frames:
                label = predict_labels(model, f["x"], size)[0, 0].cpu().numpy().astype(np.float64)
                try:
                    rad = fit_phase(f["phase"], transform.height_mm(label), f["pixels"], degree=self.degree).rmse_rad
                except ValueError:  # no finite prediction on the frame's pixels
                    rad = float("nan")
                rads[f["held_out"]].append(rad)
                ratios[f["held_out"]].append(rad / f["flat_rad"] if f["flat_rad"] > 0 else float("nan"))
        return {"val_phase_ratio": _mean(ratios[False]), "val_phase_rad": _mean(rads[False]),
                "val_phase_heldout_ratio": _mean(ratios[True]), "val_phase_heldout_rad": _mean(rads[True])}


def _own_report(out: Path) -> list[str]:
    """The report files of an ``--out`` written before evaluate-phase recorded its files: its
    ``phase_results.json`` (with this module's keys), the markdown beside it and the figures."""
    try:
        doc = json.loads((out / "phase_results.json").read_text())
    except (OSError, ValueError):
        return []
    if not (isinstance(doc, dict) and {"phase_root", "models", "per_image"} <= doc.keys()):
        return []
    rows = doc["per_image"] if isinstance(doc["per_image"], list) else []
    ids = {str(r.get("id")) for r in rows if isinstance(r, dict)}
    figs = [f"figures/{sid}.png" for sid in sorted(ids) if (out / "figures" / f"{sid}.png").is_file()]  # its frames'
    return ["phase_results.json", "phase_results.md", *figs]


def _phase_models(ckpts, args: PhaseEvalConfig) -> list:
    """``(model, transform, size, rig, rig_name)`` per checkpoint; ``rig``: what ``--refine phase`` refines through,
    else None; ``rig_name``: where it came from (the --rig file, the checkpoint's rig or fppsim's default rig)."""
    device = select_device(args.device)
    models = []
    for ck in ckpts:
        model, transform = model_from_checkpoint(ck, device)
        rig, rig_name = None, None
        if args.refine == "phase":
            try:
                rig, rig_name = refine_rig_for(ck, args.rig, args.rig)
            except (RigError, OSError) as exc:
                raise ConfigError(f"--rig {args.rig}: {exc}") from None
        models.append((model, transform, parse_size(ck.get("args", {}).get("resize")), rig, rig_name))
    return models


def _mm_equiv(rows) -> float:
    """The images' residual in mm: mean residual (rad) over mean ``|a|`` (rad/mm). The mean of each image's
    ``rmse_rad / |a|`` would let one image whose fit finds no height term (``a`` near 0) dominate it."""
    pairs = [(r["prediction"]["rmse_rad"], abs(r["prediction"]["a_rad_per_mm"])) for r in rows]
    pairs = [(e, a) for e, a in pairs if np.isfinite(e) and np.isfinite(a)]
    scale = float(np.mean([a for _, a in pairs])) if pairs else 0.0
    return float(np.mean([e for e, _ in pairs]) / scale) if scale > 0 else float("nan")


def _plane_means(planes: list) -> dict:
    """The plane-pixel columns over the frames with a plane in view; None (null in the JSON) with none."""
    if not planes:
        return {"plane_rmse_rad": None, "plane_flat_rmse_rad": None, "plane_ratio": None}
    return {"plane_rmse_rad": _mean(p["prediction"]["rmse_rad"] for p in planes),
            "plane_flat_rmse_rad": _mean(p["flat"]["rmse_rad"] for p in planes),
            "plane_ratio": _mean(p["prediction"]["rmse_rad"] / p["flat"]["rmse_rad"]
                                 for p in planes if p["flat"]["rmse_rad"] > 0)}


def _phase_summary(ckpts, names, per_image: list, args: PhaseEvalConfig) -> list[dict]:
    """One row per model (and per refined model): the per-image numbers averaged over the images."""
    summary = []
    refined = [(ck, f"{n} +{args.refine_method}") for ck, n in zip(ckpts, names)] if args.refine == "phase" else []
    for ck, name in list(zip(ckpts, names)) + refined:
        rows = [r["models"][name] for r in per_image]
        summary.append({
            "name": name, "checkpoint": ck["path"], "images": len(rows),
            **{key: _mean(r["prediction"][key] for r in rows)
               for key in ("rmse_rad", "explained", "a_rad_per_mm", "b_rad_per_mm2", "relief_rms_rad")},
            "rmse_mm_equiv": _mm_equiv(rows),
            "flat_rmse_rad": _mean(r["flat"]["rmse_rad"] for r in rows),
            "ratio": _mean(r["prediction"]["rmse_rad"] / r["flat"]["rmse_rad"] for r in rows if r["flat"]["rmse_rad"] > 0),
            **_plane_means([r["plane"] for r in rows if r["plane"]]),
            "flat_explained": _mean(r["flat"]["explained"] for r in rows),
            "pixel_fraction": _mean(r["pixel_fraction"] for r in rows),
            "predicted_invalid_fraction": _mean(r["predicted_invalid_fraction"] for r in rows),
        })
    return summary


def evaluate_phase_folder(args: PhaseEvalConfig, echo=print) -> dict:
    """Evaluate ``args.checkpoints`` on the folder layout at ``args.phase_root``; writes the report to
    ``args.out`` and returns ``{"summary", "per_image", "markdown", "figures"}``. ``echo`` gets one line
    per image (None: silent)."""
    echo = echo or (lambda line: None)
    src = open_source(args.phase_root)
    try:
        ids = src.scan_ids()
    except PSPMatError as exc:
        raise ConfigError(str(exc)) from None
    if args.ids:
        unknown = [i for i in args.ids if i not in ids]
        if unknown:
            raise ConfigError(f"{args.phase_root}: no such id(s): {', '.join(unknown[:10])}")
        ids = list(args.ids)
    if args.limit is not None:
        ids = ids[: max(0, args.limit)]
    if not ids:
        raise ConfigError(f"{args.phase_root}: nothing to evaluate")
    ckpts = [load_checkpoint(p) for p in args.checkpoints]
    names = model_names(ckpts, args.names)
    models = _phase_models(ckpts, args)
    # every frame's size through the rigs of --refine phase, before anything is written (its image is the scan's)
    for image in [src.ipattern_file(sid) for sid in ids] if any(m[3] is not None for m in models) else ():
        try:
            _rig_sees(args, models, load_ipattern(image).shape, image)
        except (PSPMatError, OSError):  # unreadable: the scoring says how
            pass
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: is a file, not a folder")
    # locked for the run; a failed run drops its claims on what it never wrote, and a folder it made and left empty
    with output_folder(out, EVALUATE_PHASE_TOOL, error=ConfigError):
        claim(out, EVALUATE_PHASE_TOOL, ["phase_results.md", "phase_results.json"]
              + [f"figures/{sid}.png" for sid in ids[: max(0, args.figures)]], legacy=lambda: _own_report(out))
        return _evaluate_frames(args, src, ids, ckpts, names, models, out, echo)


def _rig_sees(args: PhaseEvalConfig, models, shape, path) -> None:
    """:class:`ConfigError` when a rig of ``--refine phase`` does not see images of ``shape`` (frame ``path``): which
    rig, and, where none was given, what to give."""
    for _, _, _, rig, rig_name in models:
        if rig is not None:
            check_image_size(rig, shape, str(path), who=f"the rig used by --refine ({rig_name}) sees",
                             hint="" if args.rig else NO_RIG_HINT, error=ConfigError)


def _refined(args: PhaseEvalConfig, s, sid: str, name: str, net, transform, size, rig, rig_name: str, h, record: dict,
             echo):
    """``name``'s heights ``h`` after frame ``s``'s own phase, the network's where it cannot (said, in ``record``)."""
    fringe = s.image.astype(np.float32) / 127.5 - 1.0
    try:
        refined, stats = refine_with_phase(path_estimate(net, transform, fringe, size, rig, h), fringe, rig,
                                           args.refine_method, network_mm=h, name=str(s.path))
    except DataError as exc:  # as predict's default: an image whose phase cannot be read keeps them
        echo(f"{sid}: warning: no fringe phase to refine with ({exc}): {name}'s heights")
        refined, stats = h, {}
        record.setdefault("not_refined", {})[name] = str(exc)
    flipped = flipped_warning(stats.get("orientation"), str(rig_name))
    if flipped:  # said as predict says it, never acted on: the heights stay the path's
        record.setdefault("flipped", {})[name] = stats["orientation"]
        echo(f"{sid}: warning: {name}: {flipped}")
    leaning = lean_warning(stats, str(rig_name))
    if leaning:  # said as predict says it, never acted on
        record.setdefault("leaning", {})[name] = stats["plane_lean"]
        echo(f"{sid}: warning: {name}: {leaning}")
    if stats.get("undecided_regions"):  # said as predict says it: those pixels keep the network's heights
        undecided = {"regions": stats["undecided_regions"], "fraction": stats["undecided_fraction"]}
        record.setdefault("undecided", {})[name] = undecided
        echo(f"{sid}: warning: {name}: {undecided['regions']} phase region(s), {undecided['fraction']:.1%} of the "
             "pixels, have no fringe order the path can decide: the network's heights stay there")
    return refined


def _frame_plane(s, degree: int, rig_says_none: bool, record: dict) -> tuple[np.ndarray | None, str | None]:
    """Frame ``s``'s plane pixels for the plane-pixel score (:func:`view_plane`), or None and why there is no plane
    in view; ``record`` (the frame's) gets ``plane_in_view``, ``plane_sides`` and ``plane_pixel_fraction``."""
    if rig_says_none:
        plane, sides = None, None
        why = "the --rig records no reference plane in view (fit-rig found none)"
    else:
        plane, sides = view_plane(s.phase, _scored_pixels(s), degree)
        n = sides_reached(sides)
        why = None if plane is not None else (f"the 'plane' found reaches {n} of the image's 4 sides, a reference "
                                              f"plane reaching beyond the view {PLANE_SIDES} or more "
                                              f"({PLANE_SIDE_SHARE:.0%} of a side each)")
    record.update(plane_in_view=plane is not None, plane_sides=sides,
                  plane_pixel_fraction=0.0 if plane is None else float(plane.mean()))
    return plane, why


def _evaluate_frames(args: PhaseEvalConfig, src, ids, ckpts, names, models, out: Path, echo) -> dict:
    """The body of :func:`evaluate_phase_folder` once ``out`` is open: every frame scored, the report written."""
    fit_kw = dict(degree=args.degree, robust=args.robust)

    per_image, figures, skipped, digests = [], [], [], {}
    without = {}  # frame id -> why no plane is in view
    no_plane = any(rig is not None and not rig.plane_in_view for _, _, _, rig, _ in models)
    for k, sid in enumerate(ids):
        try:
            s = src.scan(sid, convention=args.convention, negate_sin=args.negate_sin)
        except NoPhaseError as exc:  # read right, nothing to fit: the others still count, as a black frame
            echo(f"{sid}: warning: {exc}: skipped")
            skipped.append(sid)
            continue
        except PSPMatError as exc:
            raise ConfigError(str(exc)) from None
        digests[sid] = s.digest()  # its content: a copy of a frame that chose a checkpoint is that frame
        note = reading_note(s.meta)
        if note:
            echo(f"{sid}: {note}")
        img = s.image
        unknowns, lit = len(poly_terms(args.degree)) + 2, int(_scored_pixels(s).sum())
        if lit <= unknowns:  # nothing to fit (a black or invalid frame): the others still count
            echo(f"{sid}: warning: {s.path}: {lit} pixels with a valid phase and light, "
                 f"{unknowns} unknowns to fit: skipped")
            skipped.append(sid)
            continue
        for ck, name in zip(ckpts, names):
            note = shape_note(ck, img.shape)
            if note:
                echo(f"{sid}: warning: {name}: {s.path}: {note}")
        x = _fringe_input(img)
        record = {"id": sid, "valid_phase_fraction": float(s.valid.mean()), "models": {}}
        try:
            _, relief = fit_phase(s.phase, np.zeros(img.shape), s.valid, return_residual=True, **fit_kw)
        except ValueError as exc:
            raise ConfigError(f"{s.path}: {exc}") from None
        slips, found = frame_slips(s, _scored_pixels(s))  # the reference's own order errors: said, still scored
        if found:
            record["reference_slips"] = found
        heights, residuals, scored = {}, {}, []
        for (model, transform, size, rig, rig_name), name in zip(models, names):
            label = predict_labels(model, x, size)[0, 0].cpu().numpy().astype(np.float64)
            h = transform.height_mm(label)
            pred_valid = np.asarray(transform.valid(label))
            ok = _scored_pixels(s)
            if args.mask_predicted_invalid:
                ok &= pred_valid
            scored.append((name, h, ok, pred_valid))
            if rig is not None:  # the same pixels, the heights after the image's own phase
                refined = _refined(args, s, sid, name, model, transform, size, rig, rig_name, h, record, echo)
                scored.append((f"{name} +{args.refine_method}", refined.astype(np.float64), ok, pred_valid))
        # no plane in view (the rig says so, or the plane found does not reach the border): no plane-pixel score,
        # whose "plane" would be the objects
        plane, why = _frame_plane(s, args.degree, no_plane, record)
        if why:
            without[sid] = why
        for name, h, ok, pred_valid in scored:
            try:
                res = evaluate_phase(s.phase, h, ok, plane_pixels=plane, **fit_kw)
            except ValueError as exc:
                raise ConfigError(f"{s.path}: {name}: {exc}") from None
            record["models"][name] = {"prediction": res["prediction"], "flat": res["flat"], "plane": res.get("plane"),
                                      "pixel_fraction": float(ok.mean()),
                                      "predicted_invalid_fraction": float((s.valid & ~pred_valid).mean())}
            if slips is not None:
                record["models"][name]["without_slips"] = slip_scores(fit_phase, s.phase, h, ok, slips, **fit_kw)
            heights[name] = np.where(ok, h, np.nan)
            residuals[name] = res["residual"]
        per_image.append(record)
        if k < args.figures:
            figures.append(plot_phase_residuals(img, relief, heights, residuals, out / "figures" / f"{sid}.png",
                                                title=f"{sid}: calibration-free phase fit (degree {args.degree})"))
        echo(frame_line(sid, record["models"], why))
        if found:
            echo(slip_line(sid, found, record["models"]))
    if not per_image:
        raise ConfigError(f"{args.phase_root}: no frame has pixels to fit (skipped {', '.join(skipped[:10])})")
    chosen = {name: on for ck, name in zip(ckpts, names) if (on := chosen_frames(ck, args.phase_root, ids, digests))}
    for name, on in chosen.items():
        echo(f"warning: {name}: its weights were chosen (train --val-phase, best epoch) on frame(s) "
             f"{chosen_words(args.phase_root, on)}: their score is not held out; score frames its run never saw")
    summary = _phase_summary(ckpts, names, per_image, args)
    md = _write_report(args, out, summary, per_image, skipped, without, chosen)
    return {"summary": summary, "per_image": per_image, "markdown": md, "figures": figures}


def _write_report(args: PhaseEvalConfig, out: Path, summary, per_image, skipped, without, chosen) -> str:
    """Write ``phase_results.md`` / ``.json`` of :func:`evaluate_phase_folder` into ``out``; returns the markdown."""
    md = markdown(summary, len(per_image), args.phase_root, args.degree, args.robust, without)
    md += slip_markdown(per_image)
    if skipped:
        md += f"\nSkipped (no pixel with a valid phase and light to fit): {', '.join(skipped)}.\n"
    for name, on in chosen.items():
        md += (f"\nNot held out: {name}'s weights were chosen (train --val-phase) on frame(s) "
               f"{chosen_words(args.phase_root, on)}.\n")
    atomic_write_text(out / "phase_results.md", md)
    atomic_write_text(out / "phase_results.json", json_text(
        {"phase_root": str(args.phase_root), "convention": args.convention, "negate_sin": args.negate_sin,
         "degree": args.degree, "robust": args.robust, "models": summary, "per_image": per_image,
         "skipped": skipped, "chosen_on": {name: [sid for sid, _ in on] for name, on in chosen.items()}},
        indent=1))
    return md

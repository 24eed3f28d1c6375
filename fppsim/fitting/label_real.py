"""Label real phase-shifting scans: absolute phase -> height through a rig -> figshare arrays.

A lab that owns a fringe projection rig measures its "ground truth" by phase shifting. This module
turns such scans into training samples in the figshare layout (``f1_80.npy`` + ``Z.npy``, see
:mod:`fppsim.dataio.formats`) that ``uhrnet train --real`` reads:

1. read each scan's absolute phase (rad) and single-shot image (uint8):

   * ``public``: the folder layout of the public phase-shifting benchmarks, ``ROOT/PSin/<id>.mat``,
     ``PCos/``, ``Fringe/`` (fringe order), ``iPattern/`` (single-shot image), read by
     :func:`fppsim.dataio.readers.load_psp_folder_sample` in either convention (:data:`fppsim.dataio.readers.CONVENTIONS`)
     and either sine sign;
   * ``native``: fppsim's own output with its phase-shifting images (``ROOT/<id>/psp/f{f}_s{n}.png``):
     the images are decoded here, like a lab would, by :func:`fppsim.phase.psp.decode_stacks` (N-step phase
     per frequency, quality mask, temporal unwrapping over the recorded ladder, order check). The
     exact arrays of ``arrays.npz`` are never read;

2. add a constant phase offset (the scan's phase origin need not be the rig's projector column 0:
   the public frames count fringe orders from the first fringe the camera sees), chosen by the
   policy: ``auto`` fits it on the reference plane (:func:`fppsim.fitting.reference_plane.fit_phase_offset`),
   ``none`` adds 0, a number adds that many radians;
3. triangulate through the rig (:func:`fppsim.phase.triangulation.height_from_phase`): height = world z (mm) above the
   reference plane z = 0;
4. measure the reference plane (:func:`fppsim.fitting.reference_plane.plane_flatness`): its level (median height
   of the plane pixels, which must come out at 0 mm), its flatness about 0 and about a fitted tilted
   plane, and its tilt. A wrong rig shows there first: a scan whose plane is not flat (or whose phase is read in a
   convention its files are not written in) does not fit, and the run is refused naming it, nothing written
   (``keep_unfit``: written, reported, and the run warns "the rig does not fit these scans");
5. write ``f1_80.npy`` (float32 (N, H, W, 1), ``I/127.5 - 1``, -1 where invalid), ``Z.npy`` (float32
   (N, H, W, 1), ``label = mm * units_per_mm + plane_offset`` of the label preset, the invalid marker
   where the phase or the triangulation is missing), ``label_real.json`` (the report) and
   ``previews/<id>.png`` (single-shot image, height map, plane residual), all atomically.

Output files fppsim did not write are never replaced: the folder's ownership record
(:mod:`fppsim.owned`) names the files label-real wrote, and a later run replaces only those. A run
replaces the arrays, the previews and then the report only once every scan is labelled: a run that
stops half-way leaves an earlier result (arrays, previews and ``label_real.json``) as it was.

Units: millimetres for heights, radians for phases, pixels for images.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from fppsim.dataio.encoding import encode_fringe, json_default
from fppsim.errors import ConfigError, DatasetError, UsageError
from fppsim.files import atomic_write_text, json_text, tmp_path
from fppsim.dataio.formats import FIGSHARE_PAIRS, LabelTransform
from fppsim.owned import claim, output_folder, owners, same_folder
from fppsim.phase import wrap
from fppsim.phase.psp import decode_stacks
from fppsim.phase.reference_check import order_slips, slips_words
from fppsim.dataio.readers import check_read_convention, plain_images_note, reading_note, open_source, scan_folders_note
from fppsim.fitting.reference_plane import PlaneFit, fit_phase_offset, plane_flatness, reference_plane_phase
from fppsim.geometry.rig import Rig, RigError, check_image_size, usable_rig
from fppsim.dataio.rig_choice import resolve_rig
from fppsim.phase.triangulation import height_from_phase
from fppsim.dataio.writers import NpyRowStream
from fppsim.plots import pyplot, save_figure
from fppsim import __version__

__all__ = ["LabelRealConfig", "LabelRealReport", "PlaneFit", "Scan", "label_real", "reference_plane_phase",
           "fit_phase_offset", "plane_flatness", "detect_layout", "iter_scans", "LAYOUTS", "REPORT_NAME",
           "PREVIEW_DIR"]

LAYOUTS = ("public", "native")  # label-real's two sources of scans, as its report names them
PUBLIC, NATIVE = LAYOUTS
REPORT_NAME = "label_real.json"
PREVIEW_DIR = "previews"
FRINGE_NAME, LABEL_NAME = FIGSHARE_PAIRS[0]
TOOL = "fppsim label-real"


# ============================================================================================ config
def _parse_offset(value) -> str | float | None:
    """``None`` (the layout's default), ``"auto"``, ``"none"`` or a finite float (rad)."""
    if value is None:
        return None
    if isinstance(value, str):
        text = value.strip().lower()
        if text in ("auto", "none"):
            return text
        try:
            value = float(text)
        except ValueError:
            raise UsageError(f"--phase-offset must be auto, none or a number of radians, got {value!r}") from None
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise UsageError(f"--phase-offset must be auto, none or a number of radians, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise UsageError(f"--phase-offset must be finite, got {value}")
    return value


@dataclass
class LabelRealConfig:
    """What ``fppsim label-real`` does; the fields are its flags.

    Attributes
    ----------
    root : folder of scans: the public layout (``PSin/ PCos/ Fringe/ iPattern/`` of ``<id>.mat``) or a
        native fppsim dataset generated with phase-shifting images (``manifest.jsonl``, ``<id>/psp/``).
    out : output folder (created): ``f1_80.npy``, ``Z.npy``, ``label_real.json``, ``previews/``.
    rig : :class:`fppsim.geometry.rig.Rig`, a rig file fppsim reads, or None: the default rig
        (``assets/default_rig.json``) for the public layout, each sample's recorded rig
        (``meta.json``) for the native layout.
    phase_offset : constant added to the absolute phase before triangulation: ``"auto"`` (fit per scan
        so the reference plane lies at 0 mm), ``"none"`` (0), or a number (rad); None: ``auto`` for the
        public layout, ``none`` for native scans (whose phase is absolute in rig terms; the fitted
        offset is still reported, to verify that).
    periods : fringe periods across the projector of the scans' absolute phase (public layout only;
        default the rig's ``periods``, 80). Native scans use the top of their recorded ladder.
    convention, negate_sin : how the public layout's wrapped phase and fringe order combine and the
        sign of its PSin (see :data:`fppsim.dataio.readers.CONVENTIONS`); default ``auto``: as published
        (``benchmark``) unless a scan is clearly written another way (:data:`fppsim.dataio.readers.AUTO`).
    ids : scan ids to label, in this order (default: every id, numeric names in numeric order).
    label : label preset or transform (default ``figshare``: 6 units per mm, plane at -97, invalid -105).
    plane_window_mm : a pixel belongs to the reference plane when its height lies within this many mm
        of the plane (default 3 mm, about half a fringe period of the default rig).
    max_plane_rms_mm, max_plane_tilt_mm : a scan's plane fits when the RMS of its plane pixels about
        0 mm is at most ``max_plane_rms_mm`` (default 1.5) and the fitted plane rises by at most
        ``max_plane_tilt_mm`` (default 3) across the image width or height; otherwise the run warns.
    min_modulation : native decoding: modulation threshold B in gray levels (default 3, as generated).
    neighbour_check : native decoding: reject pixels whose fringe order disagrees with their neighbours.
    previews : write ``previews/<id>.png`` per scan (default True).
    progress : show a progress bar over the scans (stderr).
    """
    root: str | os.PathLike
    out: str | os.PathLike
    rig: Rig | str | os.PathLike | None = None
    phase_offset: str | float | None = None
    periods: float | None = None
    convention: str = "auto"
    negate_sin: bool = False
    ids: Sequence[str] | None = None
    label: LabelTransform | str | dict | None = "figshare"
    plane_window_mm: float = 3.0
    max_plane_rms_mm: float = 1.5
    max_plane_tilt_mm: float = 3.0
    min_modulation: float = 3.0
    neighbour_check: bool = True
    previews: bool = True
    progress: bool = False
    keep_unfit: bool = False  # write the labels also when a scan does not fit (else refused, nothing written)

    def __post_init__(self):
        self.phase_offset = _parse_offset(self.phase_offset)
        check_read_convention(self.convention)
        for name, flag in (("plane_window_mm", "--plane-window"), ("max_plane_rms_mm", "--max-plane-rms"),
                           ("max_plane_tilt_mm", "--max-plane-tilt")):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise UsageError(f"{flag} must be a positive number of mm, got {v!r}")
        if self.periods is not None and not (math.isfinite(self.periods) and self.periods > 0):
            raise UsageError(f"--periods must be > 0, got {self.periods!r}")
        if not (math.isfinite(self.min_modulation) and self.min_modulation >= 0):
            raise UsageError(f"--min-modulation must be >= 0, got {self.min_modulation!r}")
        self.label = LabelTransform.resolve(self.label).check()
        if self.ids is not None:
            self.ids = [str(i) for i in self.ids]
            if not self.ids:
                raise UsageError("--ids: give at least one id")
            twice = sorted({i for i in self.ids if self.ids.count(i) > 1})
            if twice:
                raise UsageError(f"--ids: {', '.join(twice)} given more than once (each scan is one row)")


# ============================================================================================ scans
@dataclass
class Scan:
    """One scan, read and decoded (arrays of the camera shape (H, W)).

    id : scan id (file stem of the public layout, sample id of the native one).
    image : uint8 (or uint16) single-shot image.
    phase : float64 absolute phase (rad), NaN where invalid.
    valid : bool pixels with a phase.
    periods : fringe periods across the projector of ``phase``.
    rig : the rig to triangulate with.
    source : the file or folder it came from (for messages and the report).
    note : how the phase was read when ``--convention auto`` read it another way than given, else None.
    """
    id: str
    image: np.ndarray
    phase: np.ndarray
    valid: np.ndarray
    periods: float
    rig: Rig
    source: str
    note: str | None = None
    misread: bool = False  # read in a --convention its files are clearly not written in (note says so)


def detect_layout(root: str | os.PathLike) -> str:
    """:data:`LAYOUTS` ``[0]`` (``"public"``: the scans' absolute phase is on disk, as the reader's
    :meth:`~fppsim.dataio.readers.Source.scan` reads it: any of PSin/ PCos/ Fringe/ iPattern/ present, or a
    registered layout with :meth:`~fppsim.dataio.readers.Source.phase_ids`) or ``[1]`` (``"native"``: fppsim's
    samples, whose phase-shifting images are decoded here), as the folder's reader tells.

    Raises :class:`DatasetError` (one line naming ``root``) for anything else.
    """
    src = open_source(root)
    root = src.path
    if not src.path.exists():
        raise DatasetError(f"{root}: no such folder")
    if not root.is_dir():
        raise DatasetError(f"{root}: not a folder")
    if src.is_psp or src.phase_ids():  # a scan folder (whole or damaged: scan_ids names what it lacks), or scans
        return PUBLIC
    if src.has_manifest:
        return NATIVE
    # a folder of scan folders is named (their ids may repeat: one ROOT at a time), never read as one
    raise DatasetError(f"{root}: no scans found (expected PSin/ PCos/ Fringe/ iPattern/ folders of <id>.mat, or an "
                       "fppsim dataset generated with phase-shifting images: manifest.jsonl + <id>/psp/)"
                       + scan_folders_note(root, src.scan_folders()) + plain_images_note(root))


def _scan_ids(cfg: LabelRealConfig, layout: str) -> list[str]:
    src = open_source(cfg.root)
    if layout == PUBLIC:
        ids = src.scan_ids()
    else:
        ids = src.ids()
        if not ids:
            raise DatasetError(f"{cfg.root}: manifest.jsonl lists no sample")
    if cfg.ids is not None:
        unknown = [i for i in cfg.ids if i not in set(ids)]
        if unknown:
            raise DatasetError(f"{cfg.root}: no scan with id {', '.join(unknown[:8])}"
                               + (f" (and {len(unknown) - 8} more)" if len(unknown) > 8 else ""))
        ids = list(cfg.ids)
    return ids


MISREAD = "phase read in a convention its files are not written in (see read_as)"


def _check_camera(rig: Rig, shape: tuple, where: str) -> None:
    check_image_size(rig, shape, where, who="rig camera is", hint="; pass the rig of these scans with --rig",
                     error=ConfigError, template="{who} {camera} but images are {got} ({what}){hint}")


def _public_scan(cfg: LabelRealConfig, sid: str, rig: Rig) -> Scan:
    src = open_source(cfg.root)
    s = src.scan(sid, convention=cfg.convention, negate_sin=cfg.negate_sin)
    _check_camera(rig, s.image.shape, str(src.ipattern_file(sid)))
    return Scan(id=sid, image=s.image, phase=s.phase, valid=s.valid & np.isfinite(s.phase),
                periods=float(cfg.periods if cfg.periods is not None else rig.periods), rig=rig, source=s.path,
                note=reading_note(s.meta), misread=bool(s.meta.get("misread")))


def _native_scan(cfg: LabelRealConfig, sid: str, rig: Rig | None) -> Scan:
    folder = Path(cfg.root) / sid
    image, stacks, shifts, meta = open_source(cfg.root).psp_images(sid)
    freqs = tuple(stacks)
    if rig is None:
        try:
            rig = usable_rig(Rig.from_dict(meta["rig"]), f"{folder / 'meta.json'}: its rig")
        except RigError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            raise DatasetError(f"{folder / 'meta.json'}: no usable rig ({exc}); pass --rig") from None
    _check_camera(rig, image.shape, f"{folder}/fringe.png")
    dec = decode_stacks(stacks, None, freqs, min_modulation=cfg.min_modulation, neighbour_check=cfg.neighbour_check,
                        shifts=shifts)
    valid = dec.valid & np.isfinite(dec.phase)
    return Scan(id=sid, image=image, phase=np.where(valid, dec.phase, np.nan), valid=valid,
                periods=float(freqs[-1]), rig=rig, source=str(folder))


def iter_scans(cfg: LabelRealConfig, layout: str | None = None, ids: Sequence[str] | None = None,
               rig: Rig | None = None) -> Iterator[Scan]:
    """Yield the :class:`Scan` of every id (``ids``, else the config's or all) of ``cfg.root`` in order.

    ``rig``: the rig to triangulate with (None: the config's, else the layout's default).
    """
    layout = layout or detect_layout(cfg.root)
    ids = _scan_ids(cfg, layout) if ids is None else list(ids)
    rig = rig if rig is not None else _config_rig(cfg, layout)[0]
    for sid in ids:
        yield _public_scan(cfg, sid, rig) if layout == PUBLIC else _native_scan(cfg, sid, rig)


def _config_rig(cfg: LabelRealConfig, layout: str) -> tuple[Rig | None, str]:
    """``(rig, source)``; rig None = each native sample's recorded rig."""
    return resolve_rig(cfg.rig, per_sample=layout == NATIVE)


# ============================================================================================ labelling
def _finite(x):
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    return x


def _label_scan(cfg: LabelRealConfig, scan: Scan, policy: str | float, cache: dict) -> tuple[np.ndarray, dict]:
    """``(height mm float64 (H, W) NaN where invalid, record)`` of one scan."""
    key = json.dumps(scan.rig.to_dict(), sort_keys=True, default=json_default), scan.periods
    if cache.get("key") != key:
        cache.update(key=key, plane_phase=reference_plane_phase(scan.rig, scan.periods))
    fitted = fit_phase_offset(scan.phase, scan.valid, scan.rig, scan.periods, cfg.plane_window_mm,
                              plane_phase=cache["plane_phase"])
    if policy == "auto":
        offset, source = fitted, "auto"
        if not math.isfinite(offset):
            raise DatasetError(f"{scan.source}: no valid phase pixel to fit the phase offset on")
    elif policy == "none":
        offset, source = 0.0, "none"
    else:
        offset, source = float(policy), "given"
    height = height_from_phase(scan.rig, scan.phase + offset, periods=scan.periods, mask=scan.valid)
    slips = order_slips(wrap(scan.phase), scan.phase, scan.valid)  # an order in doubt gets no label, not a guess
    valid = scan.valid & np.isfinite(height) & ~slips.mask
    if not valid.any():
        raise DatasetError(f"{scan.source}: none of its {int(scan.valid.sum())} phase pixels triangulates through "
                           "the rig (the phase lies outside the projector's columns): check --rig, --periods and "
                           "--phase-offset")
    height = np.where(valid, height, np.nan)
    plane = plane_flatness(height, valid, cfg.plane_window_mm)
    n_valid = int(valid.sum())
    w = cfg.plane_window_mm
    above = valid & (height > w)
    hv = height[valid]
    label = cfg.label
    read_invalid = valid & ~(label.label_from_height_mm(np.nan_to_num(height), valid) > label.invalid_threshold)
    rec = {
        "id": scan.id,
        "source": scan.source,
        "shape": list(height.shape),
        "valid_share": n_valid / height.size,
        "phase_offset_rad": offset,
        "phase_offset_source": source,
        "phase_offset_fit_rad": fitted,
        "plane": plane.to_dict(),
        "object": {"share": float(above.sum() / max(n_valid, 1)),
                   "p99_mm": float(np.percentile(hv[hv > w], 99)) if above.any() else None,
                   "max_mm": float(hv.max()) if n_valid else None},
        "below_plane_share": float((valid & (height < -w)).sum() / max(n_valid, 1)),
        "read_as_invalid_share": float(read_invalid.sum() / max(n_valid, 1)),
        "order_slips": {"pixels": slips.pixels, "patches": slips.patches},
    }
    problems = []
    if plane.share == 0 or not math.isfinite(plane.rms_mm):
        problems.append("no reference plane found")
    else:
        if abs(plane.level_mm) > cfg.max_plane_rms_mm:
            problems.append(f"plane at {plane.level_mm:+.2f} mm")
        if plane.rms_mm > cfg.max_plane_rms_mm:
            problems.append(f"plane RMS {plane.rms_mm:.2f} mm")
        tilt = max(abs(plane.tilt_x_mm), abs(plane.tilt_y_mm))
        if tilt > cfg.max_plane_tilt_mm:
            problems.append(f"plane tilts {tilt:.2f} mm across the image")
    rec["fits"] = not problems
    rec["problems"] = problems
    return height, (rec, plane)


def _preview(path: Path, scan: Scan, height: np.ndarray, plane: PlaneFit, rec: dict) -> Path:

    plt = pyplot()
    fig, ax = plt.subplots(1, 3, figsize=(16, 3.6))
    ax[0].imshow(scan.image, cmap="gray", vmin=0, vmax=255 if scan.image.dtype == np.uint8 else 65535)
    ax[0].set_title(f"{scan.id}: single-shot image")
    im = ax[1].imshow(height, cmap="viridis")
    ax[1].set_title(f"height (mm)\nphase offset {rec['phase_offset_rad']:+.3f} rad ({rec['phase_offset_source']})")
    fig.colorbar(im, ax=ax[1], fraction=0.03)
    lim = max(0.5, float(np.nanpercentile(np.abs(plane.residual), 99))) if plane.pixels.any() else 1.0
    im = ax[2].imshow(plane.residual, cmap="coolwarm", vmin=-lim, vmax=lim)
    ax[2].set_title(f"plane residual (mm) about the fitted plane\nlevel {plane.level_mm:+.2f} mm, RMS {plane.rms_mm:.2f} "
                    f"mm, tilt x {plane.tilt_x_mm:+.2f} y {plane.tilt_y_mm:+.2f} mm")
    fig.colorbar(im, ax=ax[2], fraction=0.03)
    for a in ax:
        a.set_axis_off()
    fig.tight_layout()
    save_figure(fig, path, dpi=70)
    plt.close(fig)
    return path


# ============================================================================================ outputs
def _legacy_files(out: Path) -> set[str]:
    """A folder labelled before the ownership record: the files its ``label_real.json`` listed (plus that
    report) when label-real wrote it, else nothing."""
    try:
        doc = json.loads((out / REPORT_NAME).read_text())
        if not isinstance(doc, dict) or doc.get("tool") != TOOL:
            return set()
        files = doc.get("files", {})
        own = {REPORT_NAME, str(files.get("fringe", FRINGE_NAME)), str(files.get("label", LABEL_NAME))}
        own.update(str(p) for p in files.get("previews", []))
        own.update(str(p) for p in files.get("earlier", []))
        return own
    except (OSError, ValueError, TypeError, AttributeError):
        return set()


def _check_targets(out: Path, targets: list[str]) -> list[str]:
    """Claim ``targets`` (:func:`fppsim.owned.claim`: refused when one exists that label-real did not
    write); returns the files earlier runs wrote that are still there and are not targets now (so a
    later run may still replace them)."""

    claim(out, TOOL, targets, legacy=lambda: _legacy_files(out), hint="move it away, or use another --out")
    own = {n for n, tool in (owners(out) or {}).items() if tool == TOOL}
    return sorted(p for p in own - set(targets) if (out / p).is_file())


# ============================================================================================ report
@dataclass
class LabelRealReport:
    """What :func:`label_real` did (also written as ``out/label_real.json``).

    out : the output folder. root, layout : the scans read. rig : ``{"name", "source"}``.
    policy : phase-offset policy applied (``auto``, ``none`` or ``given``).
    label : the label transform (dict). ids : scan ids in the order of the rows of the arrays.
    scans : one record per scan: ``id``, ``source``, ``valid_share`` (labelled pixels / image),
        ``phase_offset_rad`` (applied), ``phase_offset_source``, ``phase_offset_fit_rad`` (the auto fit,
        also when not applied), ``plane`` (``level_mm``, ``rms_mm`` about 0, ``rms_fit_mm`` about the
        fitted plane, ``tilt_x_mm``, ``tilt_y_mm``, ``share`` of valid pixels), ``object`` (``share`` of
        valid pixels above the plane window, ``p99_mm``, ``max_mm``), ``below_plane_share``,
        ``read_as_invalid_share`` (valid pixels whose label the reference rule ``Z <= threshold``
        masks), ``fits`` and ``problems``; ``preview`` when written.
    warnings : one-line warnings (e.g. "the rig does not fit these scans").
    files : relative paths written (``fringe``, ``label``, ``previews``; ``earlier``: files an earlier run
        wrote that are still there, e.g. previews of other ids, which a later run may replace).
    """
    out: Path
    root: str
    layout: str
    rig: dict
    policy: str
    label: dict
    ids: list[str]
    scans: list[dict]
    warnings: list[str]
    files: dict

    def summary(self) -> dict:
        def col(*keys):
            vals = []
            for s in self.scans:
                v = s
                for k in keys:
                    v = v.get(k) if isinstance(v, dict) else None
                vals.append(np.nan if v is None else float(v))
            return np.asarray(vals, dtype=np.float64)

        off = col("phase_offset_rad")
        fit = col("phase_offset_fit_rad")
        level = col("plane", "level_mm")
        return _finite({
            "scans": len(self.scans),
            "scans_not_fitting": int(sum(not s["fits"] for s in self.scans)),
            "phase_offset_rad_median": float(np.nanmedian(off)) if np.isfinite(off).any() else None,
            "phase_offset_rad_range": [float(np.nanmin(off)), float(np.nanmax(off))] if np.isfinite(off).any() else None,
            "phase_offset_fit_rad_median": float(np.nanmedian(fit)) if np.isfinite(fit).any() else None,
            "plane_level_mm_median": float(np.nanmedian(level)) if np.isfinite(level).any() else None,
            "plane_level_mm_max_abs": float(np.nanmax(np.abs(level))) if np.isfinite(level).any() else None,
            "plane_rms_mm_max": float(np.nanmax(col("plane", "rms_mm"))) if np.isfinite(col("plane", "rms_mm")).any() else None,
            "valid_share_mean": float(np.mean(col("valid_share"))),
            "object_share_mean": float(np.mean(col("object", "share"))),
        })

    def to_dict(self, status: str = "done") -> dict:
        return _finite({"tool": TOOL, "version": __version__, "status": status, "root": self.root,
                        "layout": self.layout, "out": str(self.out), "rig": self.rig,
                        "phase_offset_policy": self.policy, "label": self.label, "ids": self.ids,
                        "files": self.files, "summary": self.summary() if self.scans else {},
                        "warnings": self.warnings, "scans": self.scans})

    def lines(self) -> list[str]:
        """Human-readable summary lines (the CLI prints them)."""
        s = self.summary()
        rig = self.rig.get("file") or f"{self.rig['name']} ({self.rig['source']})"  # a user's file by its path
        out = [f"{self.root}: {s['scans']} scan(s), layout {self.layout}, rig {rig}, phase offset {self.policy}"]
        for r in self.scans:
            p = r["plane"]
            lvl = "n/a" if p["level_mm"] is None else f"{p['level_mm']:+.2f}"
            rms = "n/a" if p["rms_mm"] is None else f"{p['rms_mm']:.2f}"
            mx = r["object"]["max_mm"]
            fit = r["phase_offset_fit_rad"]
            out.append(f"  {r['id']}: offset {r['phase_offset_rad']:+.3f} rad ({r['phase_offset_source']}; fit "
                       f"{'n/a' if fit is None else f'{fit:+.3f}'}), plane {lvl} mm RMS {rms} mm tilt "
                       f"{(p['tilt_x_mm'] or 0):+.2f}/{(p['tilt_y_mm'] or 0):+.2f} mm ({100 * p['share']:.0f}% of "
                       f"valid), objects {100 * r['object']['share']:.0f}% up to "
                       f"{'n/a' if mx is None else f'{mx:.1f}'} mm, valid {100 * r['valid_share']:.1f}%"
                       + ("" if r["fits"] else "  <- " + "; ".join(r["problems"])))
        out.append(f"wrote {self.out / self.files['fringe']} and {self.out / self.files['label']} "
                   f"({len(self.ids)} x {' x '.join(map(str, self.scans[0]['shape']))} x 1, float32; labels "
                   f"{self.label['units_per_mm']:g}/mm + {self.label['plane_offset']:g}, invalid "
                   f"{self.label['invalid_value']:g})" if self.scans else "nothing written")
        out.append(f"report: {self.out / REPORT_NAME}"
                   + (f"; previews: {self.out / PREVIEW_DIR}/" if self.files.get("previews") else ""))
        return out


def _rig_warning(report: LabelRealReport, cfg: LabelRealConfig) -> str | None:
    bad = [s for s in report.scans if not s["fits"] and s["problems"] != [MISREAD]]
    if not bad:
        return None
    worst = max(bad, key=lambda s: (s["plane"]["rms_mm"] or math.inf))
    hint = ""
    if report.policy != "auto" and any(any(p.startswith("plane at") for p in s["problems"]) for s in bad):
        hint = " (the phase origin differs from the rig's: try --phase-offset auto)"
    return (f"{len(bad)} of {len(report.scans)} scan(s) have no flat reference plane at 0 mm (e.g. {worst['id']}: "
            f"{'; '.join(worst['problems'])}; limits RMS {cfg.max_plane_rms_mm:g} mm, tilt {cfg.max_plane_tilt_mm:g} mm): "
            f"the rig does not fit these scans{hint}")


def _refuse_unfit(report: LabelRealReport, cfg: LabelRealConfig) -> None:
    """:class:`fppsim.errors.DatasetError` (one line naming the first scan that does not fit and why) when a scan's
    reference plane is not flat at 0 mm or its phase was read in a convention its files are not written in: its
    labels are wrong by the run's own check, and a pipeline would train on them. ``cfg.keep_unfit`` writes them."""
    bad = [s for s in report.scans if not s["fits"]]
    if not bad or cfg.keep_unfit:
        return
    first = bad[0]
    more = f" (and {len(bad) - 1} more of the {len(report.scans)} scans)" if len(bad) > 1 else ""
    problems = [p for p in first["problems"] if p != MISREAD]
    what = "; ".join(problems) + (f"; limits RMS {cfg.max_plane_rms_mm:g} mm, tilt {cfg.max_plane_tilt_mm:g} mm"
                                  if problems else "")
    hints = []
    if MISREAD in first["problems"]:
        what = "phase read in a convention its files are not written in" + (f"; {what}" if what else "")
        hints.append("try --convention auto")
    if report.policy != "auto" and any(p.startswith("plane at") for p in problems):
        hints.append("try --phase-offset auto")
    raise DatasetError(f"{first['source']}: scan {first['id']} does not fit ({what}){more}: its labels would be "
                       f"wrong, nothing written{''.join('; ' + h for h in hints)} (--keep-unfit writes them anyway)")


# ============================================================================================ main
def label_real(cfg: LabelRealConfig) -> LabelRealReport:
    """Label the scans of ``cfg.root`` (see the module docstring); returns the report.

    Raises :class:`fppsim.errors.DatasetError` / :class:`fppsim.errors.PSPMatError` (one line naming
    the file) for unreadable or inconsistent scans, :class:`fppsim.errors.ConfigError` when the rig's
    camera size differs from the images, and :class:`fppsim.errors.DatasetError` when an output file
    exists that label-real did not write. Nothing is replaced until every scan is labelled.
    """
    from tqdm import tqdm

    layout = detect_layout(cfg.root)
    if layout == NATIVE and cfg.periods is not None:
        raise UsageError("--periods applies to the public layout only (native scans record their ladder)")
    ids = _scan_ids(cfg, layout)
    rig, rig_source = _config_rig(cfg, layout)
    policy = cfg.phase_offset if cfg.phase_offset is not None else ("auto" if layout == PUBLIC else "none")
    if policy == "auto" and rig is not None and not rig.plane_in_view:
        named = cfg.rig if isinstance(cfg.rig, (str, os.PathLike)) else rig.name
        raise ConfigError(f"--phase-offset auto (the public layout's default) fits the offset on the reference plane, "
                          f"and the rig ({named}) was "
                          "fitted to frames with no plane in view: give --phase-offset RAD (or none)")
    out = Path(cfg.out)
    if out.exists() and not out.is_dir():
        raise DatasetError(f"--out {out} is a file, not a folder")
    if same_folder(out, cfg.root):
        # the labels beside the scans would make one folder of two layouts, each reader picking one
        raise UsageError(f"--out {out} is the scans' own folder; give another (e.g. {out / 'labels'})")
    previews = [f"{PREVIEW_DIR}/{sid}.png" for sid in ids] if cfg.previews else []
    scans = iter_scans(cfg, layout, ids, rig)
    first = next(scans)  # read (and check) the first scan before anything is created
    H, W = first.image.shape
    report = LabelRealReport(out=out, root=str(cfg.root), layout=layout,
                             rig={"name": (rig or first.rig).name, "source": rig_source,
                                  **({"file": str(cfg.rig)} if isinstance(cfg.rig, (str, os.PathLike)) else {})},
                             policy=policy if isinstance(policy, str) else "given", label=cfg.label.to_dict(),
                             ids=ids, scans=[], warnings=[],
                             files={"fringe": FRINGE_NAME, "label": LABEL_NAME, "previews": previews})
    with output_folder(out, TOOL, error=DatasetError):
        earlier = _check_targets(out, [FRINGE_NAME, LABEL_NAME, REPORT_NAME] + previews)
        if earlier:
            report.files["earlier"] = earlier
        # the previews wait in a folder of our own temp name (removed if we are killed) until the arrays are in
        staging = tmp_path(out / PREVIEW_DIR)
        streams = []
        try:
            if previews:
                staging.mkdir()
            for name in (FRINGE_NAME, LABEL_NAME):
                streams.append(NpyRowStream(out / name, (len(ids), H, W, 1)))
            cache: dict = {}
            bar = tqdm(total=len(ids), desc="label-real", unit="scan", disable=not cfg.progress, dynamic_ncols=True)
            with bar:
                for k in range(len(ids)):
                    scan = first if k == 0 else next(scans)
                    if scan.image.shape != (H, W):
                        raise DatasetError(f"{scan.source}: image size {scan.image.shape} differs from the first "
                                           f"scan's {(H, W)}")
                    height, (rec, plane) = _label_scan(cfg, scan, policy, cache)
                    if rec["order_slips"]["pixels"]:
                        report.warnings.append(f"{scan.source}: its phase-shifting order slips "
                                               f"{slips_words(rec['order_slips']['patches'])} where its wrapped phase "
                                               "and gradient run on (temporal unwrapping wrong there, likely): "
                                               "left unlabelled")
                    if scan.note:  # every scan's in the report, the first one's as the run's warning
                        if not any("read_as" in r for r in report.scans):
                            report.warnings.append(scan.note)
                        rec["read_as"] = scan.note
                        if scan.misread:  # a scan read in a convention it is not written in does not fit
                            rec["fits"] = False
                            rec["problems"].append(MISREAD)
                    valid = np.isfinite(height)
                    streams[0].write(encode_fringe(scan.image, valid))
                    streams[1].write(cfg.label.label_from_height_mm(np.nan_to_num(height), valid))
                    if cfg.previews:
                        rec["preview"] = previews[k]
                        _preview(staging / Path(previews[k]).name, scan, height, plane, rec)
                    report.scans.append(_finite(rec))
                    bar.update(1)
            _refuse_unfit(report, cfg)
            for s in streams:
                s.close()
            for s in streams:
                s.commit()
            if previews:
                (out / PREVIEW_DIR).mkdir(exist_ok=True)
                for name in previews:
                    os.replace(staging / Path(name).name, out / name)
        except BaseException:
            for s in streams:
                s.discard()
            raise
        finally:
            shutil.rmtree(staging, ignore_errors=True)
        warning = _rig_warning(report, cfg)
        if warning:
            report.warnings.append(warning)
        atomic_write_text(out / REPORT_NAME, json_text(report.to_dict("done"), indent=1, default=json_default))
    return report

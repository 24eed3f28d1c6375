"""`fppsim validate-psp`: how far is phase-shifting (PSP) "ground truth" from the exact geometry?

This package is split by job: :mod:`.sample` evaluates one sample (pixel classes, height errors),
:mod:`.report` reads a dataset, pools the samples and writes the report, tables and error maps,
:mod:`.sweep` builds the optics grid of ``--sweep``; :class:`ValidateConfig` + :func:`validate_psp`
here run the whole command (``fppsim.validate_psp``).

Real FPP datasets label their images with the height a multi-frequency PSP measurement gives. The
simulator knows the exact height, so it can measure the error of that PSP ground truth: for every
sample the PSP height (``height_psp``, decoded from the rendered 8-bit phase-shifted images, see
:func:`fppsim.rendering.synth.psp_decode`) is compared with the exact height on the pixels the exact mask calls
valid (seen and lit by the projector).

Pixel classes (all over the exact-valid pixels ``V``; fractions are relative to ``|V|``)
-----------------------------------------------------------------------------------------
* accepted: ``V`` and PSP kept the pixel (``mask_psp`` = 1 and a finite ``height_psp``).
* rejected: ``V`` and PSP did not keep it; split by reason when the PSP images are there
  (re-decoded from ``psp/f{f}_s{n}.png``): low modulation (``B`` below the decoder's
  ``min_modulation``), fringe order flagged unreliable by the unwrapper, other (triangulation).
* order error: ``|phase_psp - phase_true| > pi`` (absolute phase of the highest frequency vs the
  exact projector phase), i.e. a wrong fringe order or an equally gross phase error. Counted on all
  of ``V`` (what the unwrapper got wrong) and on the accepted pixels (what silently ends up in the
  ground truth). The unwrapper flags conservatively, so "rejected" and "wrong" differ: the report
  gives both and their overlap.

Height error statistics (``height_psp - height``, mm) are computed on the accepted pixels, once
including and once excluding the order-error pixels (keys ``*_incl_order_errors`` /
``*_excl_order_errors``), and, excluding order errors, separately for pixels near edges (within
``edge_px`` pixels of an invalid pixel, of a depth discontinuity or of the image border) and for
the interior. A depth discontinuity is a jump between 4-neighbours larger than 4 pixel footprints
(``4 * depth / fx``; surfaces steeper than about 76 degrees to the view count as edges too).

Aggregates pool the pixels of all samples (RMSE = sqrt(sum of squares / count)); the pooled 99th
percentile comes from a log-spaced histogram (0.6 % relative resolution, upper bin edge), per-sample
percentiles are exact. The tool reports numbers only: it has no pass/fail thresholds.

Sweeps
------
``--sweep noise=0,0.5,1,2 gamma=1,2.2`` renders the same scenes (same seed and sample indices; the
scene draws do not depend on the optics) once per combination of the given values -- the full grid,
here 4 x 2 = 8 settings -- with the swept parameters fixed and everything else drawn from the usual
ranges, and tabulates the aggregate error per setting. Names: ``noise`` = ``noise_sigma`` (gray
levels; ``shot_noise`` is then fixed to 0 unless it is swept or given with ``--optics``), ``gamma`` =
``projector_gamma``, ``blur`` = ``projector_blur`` (projector pixels), or any
:class:`fppsim.rendering.optics.OpticsRanges` field (``camera_blur``, ``camera_gamma``, ``gain``, ...). Each
setting renders into its own subfolder ``<out>/sweep/<name>/`` so an interrupted sweep resumes.
Within one sweep the other optics draws are identical across settings (a fixed parameter consumes no
random draw in every setting alike), and so is the noise realisation (scaled by the setting).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

from fppsim.errors import ConfigError, ValidateError, ValidateUsageError, check_seed
from fppsim.dataio.formats import SETTINGS_FILE, sample_id
from fppsim.dataio.encoding import json_default
from fppsim.files import atomic_write_text, json_text
from fppsim.owned import claim, forget, output_folder
from fppsim.validate.report import (VALIDATE_TOOL, format_sweep_table, format_table, own_report_files, read_dataset_settings,
                                    read_records, report_files, resolve_dataset, validate_dataset, write_error_map)
from fppsim.validate.sample import ORDER_ERROR_RAD, evaluate_sample
from fppsim.validate.sweep import DEFAULT_SWEEP, SWEEP_ALIASES, config_from_settings, parse_sweep, ranges_with, sweep_settings
from fppsim.generation import GenerateConfig, generate_dataset

__all__ = [
    "SWEEP_ALIASES", "DEFAULT_SWEEP", "ORDER_ERROR_RAD", "ValidateError", "ValidateUsageError", "VALIDATE_TOOL", "resolve_dataset", "evaluate_sample",
    "validate_dataset", "parse_sweep", "sweep_settings", "format_table", "format_sweep_table", "write_error_map",
    "ValidateConfig", "validate_psp",
]


# ====================================================================== the whole command as a function
@dataclass
class ValidateConfig:
    """What ``fppsim validate-psp`` does, checked on construction (:class:`ValidateError`).

    Either ``dataset`` (a generated native folder, or a figshare output with ``native/``) or ``meshes``
    + ``count`` to render a fresh set into ``out/samples`` (the scene fields then apply as in
    :class:`fppsim.generation.GenerateConfig`). ``sweep``: None (no sweep), [] (:data:`DEFAULT_SWEEP`)
    or ``["noise=0,1", ...]``: the full grid of the given optics values, rendered into
    ``out/sweep/<setting>/``. ``edge_px``: width of the edge region for the edge/interior split (0: off).
    """
    out: str | os.PathLike
    dataset: str | os.PathLike | None = None
    meshes: Sequence[str] | None = None
    count: int | None = None
    seed: int = 0
    rig: object = None
    objects: tuple[int, int] = (1, 3)
    optics: dict = field(default_factory=dict)
    noise_free: bool = False
    supersample: int = 1
    psp_steps: int = 4
    psp_freqs: tuple[int, ...] = (1, 8, 80)
    workers: int = 1
    tmp_samples: bool = False
    sweep: Sequence[str] | None = None
    edge_px: int = 3
    maps: bool = True
    progress: bool = True

    def __post_init__(self):  # flags wrong on their own or together: usage errors (exit 2) before anything is read
        if self.dataset and self.meshes:
            raise ValidateUsageError("give either a DATASET folder or --meshes, not both")
        if not self.dataset and not self.meshes:
            raise ValidateUsageError("nothing to validate: give a DATASET folder or --meshes PATH... --count N")
        if self.meshes and not self.count:
            raise ValidateUsageError("--meshes needs --count N")
        if self.dataset and (self.count or self.optics or self.noise_free):
            raise ValidateUsageError("--count/--optics/--noise-free only apply with --meshes")
        if self.psp_steps < 3:
            raise ValidateUsageError(f"--psp-steps must be >= 3, got {self.psp_steps}")
        if self.edge_px < 0:
            raise ValidateUsageError(f"--edge-px must be >= 0 (0: no edge split), got {self.edge_px}")
        check_seed(self.seed, error=ValidateUsageError)
        grid = self.grid()  # a bad --sweep value is refused here
        if grid is not None and self.noise_free and any(n in ("noise_sigma", "shot_noise") for n, _ in grid):
            raise ValidateUsageError("a noise sweep needs noise: --noise-free renders every setting alike")

    def grid(self) -> list[tuple[str, list]] | None:
        return parse_sweep(self.sweep) if self.sweep is not None else None


def _render(meshes, folder: Path, count: int, seed: int, config, noise_free: bool, workers: int, progress: bool,
            echo) -> None:
    summary = generate_dataset(meshes, folder, count, seed=seed, config=config, workers=workers,
                               noise_free=noise_free, progress=progress)
    for line in summary.lines():
        echo(line)


def validate_psp(config: ValidateConfig, echo=None) -> dict:
    """Run ``fppsim validate-psp``: validate a dataset, render and validate a fresh set, or a sweep.

    Writes ``out/report.json`` (and maps, samples, sweep folders) and returns the report: the
    :func:`validate_dataset` report, or for a sweep ``{"grid", "rows": [{"name", "setting", "folder",
    "aggregate"}], ...}``. ``echo`` receives progress lines of the rendering runs (None: silent).
    """
    echo = echo or (lambda line: None)
    grid = config.grid()
    out = Path(config.out)
    if config.dataset:
        root = resolve_dataset(config.dataset)
        read_records(root)  # fail early on an empty dataset
        settings = read_dataset_settings(root)
        if grid is None:
            return validate_dataset(root, out, maps=config.maps, progress=config.progress, edge_px=config.edge_px)
        if settings is None:
            raise ValidateError(f"{root}: no dataset.json, so its scenes cannot be re-rendered for --sweep")
        synth, meshes, seed, noise_free = config_from_settings(settings, root / SETTINGS_FILE)
        if not synth.psp_freqs:
            raise ValidateError(f"{root}: no PSP data (generated with --no-psp): re-generate without --no-psp")
        missing = [m for m in meshes if not Path(m).exists()]
        if missing:
            raise ValidateError(f"cannot re-render the dataset's scenes for --sweep: mesh not found: {missing[0]}")
        count = max(int(r["index"]) for r in read_records(root)) + 1
        base = {}
    else:
        try:
            synth = GenerateConfig(meshes=list(config.meshes), out=out, count=config.count, seed=config.seed,
                                   rig=config.rig, objects=tuple(config.objects), optics=dict(config.optics),
                                   supersample=config.supersample, psp_steps=config.psp_steps,
                                   psp_freqs=tuple(config.psp_freqs)).synth_config()
        except ConfigError as exc:
            raise ValidateError(str(exc)) from None
        base = dict(config.optics)
        meshes, seed, noise_free, count = list(config.meshes), config.seed, config.noise_free, config.count

    if grid is not None and noise_free and any(n in ("noise_sigma", "shot_noise") for n, _ in grid):
        raise ValidateError("a noise sweep needs noise: the dataset/run is noise-free (--noise-free), so every "
                            "setting would render the same images")
    settings = sweep_settings(grid, base) if grid is not None else None
    ids = [sample_id(i) for i in range(count)]  # every sample the run can render (a failed one is skipped)
    names = report_files(ids, config.maps) if settings is None else ["report.json", *[
        n for name, _ in settings for n in report_files(ids, config.maps, prefix=f"sweep/{name}/")]]
    # locked, and every report and map name claimed before anything is rendered or written: never a user's file
    with output_folder(out, VALIDATE_TOOL, error=ValidateError):
        claim(out, VALIDATE_TOOL, names, legacy=lambda: own_report_files(out))
        try:
            return _render_and_validate(config, out, settings, synth, meshes, seed, noise_free, count, echo)
        finally:  # claims of samples that were never rendered go again
            forget(out, [n for n in names if not (out / n).exists()])


def _render_and_validate(config: ValidateConfig, out: Path, settings, synth, meshes, seed, noise_free, count,
                         echo) -> dict:
    kw = dict(maps=config.maps, progress=config.progress, edge_px=config.edge_px, claimed=True)
    tmp = Path(tempfile.mkdtemp(prefix="fppsim-validate-")) if config.tmp_samples else None
    render = dict(workers=config.workers, progress=config.progress, echo=echo)
    try:
        if settings is None:
            samples = (tmp or out) / "samples"
            _render(meshes, samples, count, seed, synth, noise_free, **render)
            return validate_dataset(samples, out, extra={"samples_folder": None if tmp else str(samples)}, **kw)
        rows = []
        for i, (name, fixed) in enumerate(settings, 1):
            if config.progress:
                echo(f"sweep {i}/{len(settings)}: {name}")
            cfg = replace(synth, optics=ranges_with(synth.optics, fixed))
            sub = out / "sweep" / name
            samples = ((tmp / name) if tmp else sub) / "samples"
            _render(meshes, samples, count, seed, cfg, noise_free, **render)
            rep = validate_dataset(samples, sub, extra={"sweep_setting": fixed}, **kw)
            rows.append({"name": name, "setting": fixed, "folder": f"sweep/{name}", "aggregate": rep["aggregate"]})
        grid = config.grid()
        sweep_report = {
            "tool": "fppsim validate-psp --sweep",
            "grid": {n: v for n, v in grid},
            "combination": "full grid (every combination of the given values)",
            "seed": seed, "count": count, "meshes": [str(Path(m).resolve()) for m in meshes],
            "noise_free": noise_free, "base_optics_ranges": synth.optics.to_dict(),
            "config": synth.to_dict(), "rig": synth.rig.to_dict(),
            "rows": rows,
        }
        atomic_write_text(out / "report.json", json_text(sweep_report, indent=1, default=json_default))
        return sweep_report
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)

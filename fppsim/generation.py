"""Dataset generation run: mesh loading, sharding, worker pool, resumable writing, summary.

``fppsim.generate(GenerateConfig(meshes=[...], out=..., count=N))`` is the whole run as the command
line does it (rig file, optics overrides, label preset, preview); :func:`generate_dataset` is the
same run over an already-built :class:`fppsim.rendering.synth.SynthConfig`.

A run owns an output folder. ``dataset.json`` records the settings; re-running the same command on
the same folder first reconciles it (temporary folders removed, manifest rebuilt from the complete
sample folders) and then produces only the missing samples, so an interrupted run completes without
duplicates. Samples are independent of the worker count (see :mod:`fppsim.rendering.synth`). The folder's
fixed files are claimed in its ownership record before anything is written (:mod:`fppsim.dataio.dataset_folder`):
a file of those names that fppsim did not write, a dataset of the other format, or (figshare) samples beyond
``count`` are refused, and a run that fails before its first sample leaves nothing behind.
"""

from __future__ import annotations

import shutil
import json
import logging
import math
import multiprocessing as mp
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence


from fppsim import __version__
from fppsim.errors import ConfigError, DatasetError, GenerateError, MeshError, SampleError, UsageError, InputError, check_seed
from fppsim.threads import check_cores
from fppsim.files import atomic_write_text, die_with_parent, json_text, ignore_sigint, signals_raise, tmp_path
from fppsim.owned import claim, output_folder
from fppsim.dataio.formats import (psp_freq, FIGSHARE_PAIRS, SETTINGS_FILE, LabelTransform, append_manifest, finished_indices,
                                   foreign_sample_folders, manifest_record, read_settings, reconcile, sample_id)
from fppsim.dataio.dataset_folder import (DATASET_TOOL, PREVIEW_NAME, check_format, check_no_frames, check_shards,
                                          dataset_files, discard_empty_dataset, legacy_files)
from fppsim.rendering.scene import MeshAsset, SceneRanges, find_meshes, load_mesh, unread_mesh_files
from fppsim.rendering.synth import SynthConfig, synthesize
from fppsim.dataio.writers import (BackgroundWriter, FigshareRows, export_figshare, figshare_rows, samples_folder,
                                   write_sample_folder)
from fppsim.dataio.readers import open_source
from fppsim.rendering.optics import OpticsRanges
from fppsim.geometry.jitter import RigJitter
from fppsim.geometry.rig import Rig, load_rig
from fppsim.rendering.render import DepthRenderer, select_backend
from fppsim.rendering.preview import write_preview
from fppsim.settings_files import SCENE_FIELDS, read_optics_file, resolve_scenes

log = logging.getLogger("fppsim")

__all__ = ["GenerateConfig", "GenerateError", "RunSummary", "load_assets", "generate", "generate_dataset",
           "shard_indices", "merge", "read_optics_file", "resolve_scenes", "SCENE_FIELDS", "FORMATS", "SUPERSAMPLE", "PROCEDURAL"]

MAX_COUNT = 10_000_000  # samples of one run: more is a typo (at 3 MB a sample, 30 TB)
FORMATS = ("native", "figshare")  # on-disk layouts generate writes
SUPERSAMPLE = (1, 3, 5)  # odd sub-pixel factors (ground truth stays at pixel centres)


@dataclass
class RunSummary:
    out: str
    requested: int
    existing: int = 0
    written: int = 0
    failed: list = field(default_factory=list)      # (index, reason)
    skipped_meshes: list = field(default_factory=list)  # (path, reason)
    seconds: float = 0.0
    figshare: str | None = None
    preview: str | None = None
    scenes: str | None = None
    background: str | None = None

    def lines(self) -> list[str]:
        out = [f"samples: {self.written} written, {self.existing} already there, {len(self.failed)} failed "
               f"(of {self.requested} in this shard) in {self.seconds:.1f} s -> {self.out}"]
        if self.scenes:
            out.append(f"scenes: {self.scenes}")
        if self.background:
            out.append(f"background: {self.background}")
        for path, reason in self.skipped_meshes:
            out.append(f"skipped mesh: {reason}")
        for index, reason in self.failed[:10]:
            out.append(f"failed sample {index}: {reason}")
        if len(self.failed) > 10:
            out.append(f"... and {len(self.failed) - 10} more failed samples")
        if self.figshare:
            out.append(f"figshare arrays: {self.figshare}")
        if self.preview:
            out.append(f"preview: {self.preview}")
        return out


PROCEDURAL = "procedural"  # a --meshes entry that stands for fppsim.rendering.shapes.procedural sculptures


@dataclass
class GenerateConfig:
    """Everything ``fppsim generate`` needs; checks itself on construction.

    meshes : mesh files or folders (the entry ``"procedural"`` alone: procedural sculptures only).
    out : output folder (re-running resumes it). count : samples in the whole dataset; sample i
    depends only on (seed, i). rig : calibration file, a :class:`Rig`, or None for the packaged
    default rig. objects : (lo, hi) objects per scene. format : one of :data:`FORMATS`. shard : (i, n)
    to generate only every n-th sample from i. supersample : one of :data:`SUPERSAMPLE`. optics :
    optics range overrides ``{name: value or [lo, hi]}`` (names of :class:`fppsim.rendering.optics.OpticsRanges`;
    :func:`read_optics_file` reads them from a file). psp_freqs : unwrapping ladder starting at 1 and
    ending at the rig's frequency; () skips the phase-shifting images. label : figshare label
    transform. procedural_share : chance that an object is a procedural sculpture (None: 1 when
    ``meshes`` is just ``"procedural"``, else 0); procedural_pool : distinct sculptures. rig_jitter :
    per-sample projector (yaw rad, relative focal) jitter, (0, 0) = off. pedestal : chance that an
    object stands on a prism pedestal (None: ``SceneRanges.pedestal_probability``). scenes : the objects'
    sizes, relief caps and pedestal heights (:data:`SCENE_FIELDS` of :class:`SceneRanges`): ``"auto"`` (the
    rig file's ``scenes``, written by ``fppsim fit-rig`` to follow the frames, else the defaults),
    ``"default"``, a JSON/YAML file (a rig file with ``scenes``, or such a mapping) or the mapping itself
    (:func:`resolve_scenes`). preview : also write
    ``out/preview.png``. backend : GL platform ``osmesa``/``egl`` (None: ``$PYOPENGL_PLATFORM``).

    A value that is wrong on its own raises :class:`UsageError` (the command line exits 2, before
    anything is written); settings that do not fit the rig raise :class:`ConfigError` in
    :meth:`synth_config`.
    """
    meshes: Sequence[str]
    out: str | os.PathLike
    count: int
    seed: int = 0
    rig: "str | os.PathLike | Rig | None" = None
    objects: tuple[int, int] = (1, 3)
    workers: int = 1
    format: str = "native"
    shard: tuple[int, int] | None = None
    supersample: int = 1
    optics: dict = field(default_factory=dict)
    noise_free: bool = False
    psp_steps: int = 4
    psp_freqs: tuple[int, ...] = (1, 8, 80)
    label: LabelTransform = field(default_factory=LabelTransform)
    procedural_share: float | None = None
    procedural_pool: int = 96
    rig_jitter: tuple[float, float] = (0.0, 0.0)
    pedestal: float | None = None
    preview: bool = False
    backend: str | None = None
    progress: bool = True
    scenes: "str | dict" = "auto"

    def __post_init__(self):
        if isinstance(self.meshes, (str, os.PathLike)):
            self.meshes = [self.meshes]
        self.meshes = [str(m) for m in self.meshes]
        if not self.meshes:
            raise UsageError("no meshes given (--meshes)")
        if not 1 <= int(self.count) <= MAX_COUNT:
            raise UsageError(f"--count must be from 1 to {MAX_COUNT:,} samples, got {self.count}")
        check_seed(self.seed, error=UsageError)
        if self.format not in FORMATS:
            raise UsageError(f"unknown format '{self.format}' ({' or '.join(FORMATS)})")
        if self.supersample not in SUPERSAMPLE:
            raise UsageError(f"supersample must be one of {SUPERSAMPLE}, got {self.supersample}")
        if int(self.workers) < 1:
            raise UsageError(f"workers must be >= 1, got {self.workers}")
        check_cores(int(self.workers), "--workers", "worker processes", UsageError)
        lo, hi = self.objects
        if not 1 <= lo <= hi:
            raise UsageError(f"objects must be LO-HI with 1 <= LO <= HI, got {lo}-{hi}")
        if self.shard is not None:
            try:
                shard_indices(1, self.shard)
            except ValueError as exc:
                raise UsageError(str(exc)) from None
        if self.psp_freqs:
            try:
                f = tuple(float(v) for v in self.psp_freqs)
            except (TypeError, ValueError):
                raise UsageError(f"--psp-freqs must be numbers, got {list(self.psp_freqs)}") from None
            if not all(math.isfinite(v) for v in f) or f[0] != 1 or any(b <= a for a, b in zip(f, f[1:])):
                raise UsageError(f"--psp-freqs ladder must start at 1 and increase, got {list(f)}")
            if self.psp_steps < 3:
                raise UsageError(f"--psp-steps must be >= 3, got {self.psp_steps}")

        try:
            OpticsRanges.from_dict(dict(self.optics))
        except ValueError as exc:
            raise UsageError(f"--optics: {exc}") from None
        if self.procedural_share is not None and not 0.0 <= float(self.procedural_share) <= 1.0:
            raise UsageError(f"--procedural-share must be in [0, 1], got {self.procedural_share}")
        if int(self.procedural_pool) < 1:
            raise UsageError(f"--procedural-pool must be >= 1, got {self.procedural_pool}")
        if self.pedestal is not None and not 0.0 <= float(self.pedestal) <= 1.0:
            raise UsageError(f"--pedestal must be in [0, 1], got {self.pedestal}")
        if not self.mesh_paths and self.share < 1.0:
            raise UsageError("--meshes procedural alone needs --procedural-share 1 (or give mesh files too)")
        self.rig_jitter = tuple(float(v) for v in self.rig_jitter)
        try:
            self.jitter()
        except ValueError as exc:
            raise UsageError(f"--rig-jitter: {exc}") from None
        try:
            self.label.check()
        except DatasetError as exc:
            raise UsageError(f"--label-*: {exc}") from None
        self.scene_fields()  # a bad --scenes file is named before anything is written

    @property
    def mesh_paths(self) -> list[str]:
        """The mesh files and folders, without the ``"procedural"`` entry."""
        return [m for m in self.meshes if m != PROCEDURAL]

    @property
    def share(self) -> float:
        """The procedural share in effect (``procedural_share``, or its default)."""
        if self.procedural_share is not None:
            return float(self.procedural_share)
        return 1.0 if not self.mesh_paths else 0.0

    def jitter(self):
        return RigJitter(*self.rig_jitter)

    def scene_fields(self) -> tuple[dict, str]:
        """The :data:`SCENE_FIELDS` the scenes take (``{}``: the defaults) and where from, in words."""
        return resolve_scenes(self.scenes, None if isinstance(self.rig, Rig) else self.rig)

    def synth_config(self) -> SynthConfig:
        """The renderer's configuration: loads the rig and checks the ladder against it
        (:class:`RigError` / :class:`ConfigError`)."""

        rig = self.rig if isinstance(self.rig, Rig) else load_rig(self.rig)
        optics = OpticsRanges.from_dict(dict(self.optics))
        freqs = tuple(psp_freq(f) for f in self.psp_freqs)
        if freqs and not math.isclose(float(freqs[-1]), float(rig.periods), rel_tol=1e-6, abs_tol=1e-9):
            top = psp_freq(rig.periods)
            raise ConfigError(f"--psp-freqs must end at the rig's single-shot frequency {top!r}, got {freqs[-1]!r} "
                              f"(e.g. --psp-freqs 1,{max(2, round(float(top) ** 0.5))},{top!r})")
        if freqs:  # a ladder that ends within rounding of the rig's frequency ends exactly there
            freqs = freqs[:-1] + (psp_freq(rig.periods),)
        extra = {} if self.pedestal is None else {"pedestal_probability": float(self.pedestal)}
        extra.update(self.scene_fields()[0])
        scene = SceneRanges(objects=tuple(self.objects), procedural_share=self.share,
                            procedural_pool=int(self.procedural_pool), **extra)
        return SynthConfig(rig=rig, optics=optics, scene=scene, supersample=self.supersample, psp_freqs=freqs,
                           psp_steps=self.psp_steps, rig_jitter=self.jitter())


def generate(config: GenerateConfig) -> RunSummary:
    """Generate (or complete) the dataset ``config`` describes; returns a :class:`RunSummary`."""
    summary = generate_dataset(config.mesh_paths, config.out, config.count, seed=config.seed,
                               config=config.synth_config(), workers=config.workers, fmt=config.format,
                               shard=config.shard, label=config.label, noise_free=config.noise_free,
                               progress=config.progress, backend=config.backend, preview=config.preview)
    fields, source = config.scene_fields()
    sc = SceneRanges(**fields)
    summary.scenes = (f"objects {sc.footprint[0]:.0f}-{sc.footprint[1]:.0f} mm across, relief capped at "
                      f"{sc.max_relief[0]:.0f}-{sc.max_relief[1]:.0f} mm, pedestals {sc.pedestal_height[0]:.0f}-"
                      f"{sc.pedestal_height[1]:.0f} mm: {source}")
    if OpticsRanges.from_dict(dict(config.optics)).albedo_plane[1] == 0:
        summary.background = ("black (albedo_plane 0, no plane in view): only the objects return fringes and carry "
                              "labels")
    return summary


def load_assets(paths) -> tuple[list[MeshAsset], list[tuple[str, str]]]:
    """Load every mesh under ``paths``; return the usable ones and (path, reason) for the others."""
    assets, skipped = [], []
    for p in find_meshes(paths):
        try:
            assets.append(load_mesh(p))
        except MeshError as exc:
            skipped.append((p, str(exc)))
            log.warning("skipping mesh: %s", exc)
    for p, reason in unread_mesh_files(paths):
        skipped.append((p, reason))
        log.warning("skipping mesh: %s", reason)
    return assets, skipped


def shard_indices(count: int, shard: tuple[int, int] | None) -> list[int]:
    """Global sample indices of shard ``(i, n)`` (round robin), or all of ``range(count)``."""
    if shard is None:
        return list(range(count))
    i, n = shard
    if not (n >= 1 and 0 <= i < n):
        raise InputError(f"shard must be I/N with 0 <= I < N, got {i}/{n}")
    return list(range(i, count, n))


# --------------------------------------------------------------------------- worker side
_WORKER: dict = {}


def _worker_init(assets, config, seed, out, noise_free, label=None, backend=None, pool_worker=False):

    if pool_worker:  # only the parent reacts to Ctrl-C/SIGTERM (it terminates the pool); no orphans
        ignore_sigint()
        die_with_parent()
    _WORKER.update(assets=assets, config=config, seed=seed, out=Path(out), noise_free=noise_free,
                   renderer=DepthRenderer(backend), label=label, writer=BackgroundWriter())


def _worker_run_chunk(indices: list[int]) -> list[tuple]:
    """Produce ``indices``, writing each sample on the background thread while the next one renders.

    Returns ``(index, record, error, figshare rows or None)`` per index once every folder of the
    chunk is complete on disk, so the manifest never lists a sample still being written.
    """
    w = _WORKER
    out = []
    for index in indices:
        sid = sample_id(index)
        try:
            images, arrays, meta = synthesize(index, w["seed"], w["assets"], w["config"], w["renderer"],
                                              noise_free=w["noise_free"])
        except SampleError as exc:
            out.append((index, None, str(exc), None))
            continue
        w["writer"].submit(write_sample_folder, w["out"], sid, images, arrays, meta)
        rows = figshare_rows(images["fringe.png"], arrays, w["label"]) if w["label"] is not None else None
        out.append((index, manifest_record(sid, meta), None, rows))
    w["writer"].flush()
    return out


def _chunks(todo: list[int], workers: int, size: int = 8) -> list[list[int]]:
    """Consecutive chunks of at most ``size`` indices, small enough to keep every worker busy."""
    size = max(1, min(size, len(todo) // (4 * max(1, workers)) or 1))
    return [todo[i:i + size] for i in range(0, len(todo), size)]


# --------------------------------------------------------------------------- run
def _settings(config: SynthConfig, seed: int, mesh_paths: list[str], fmt: str, label: LabelTransform,
              noise_free: bool) -> dict:
    return {
        "generator": "fppsim", "version": __version__, "seed": int(seed), "format": fmt,
        "meshes": [os.path.abspath(p) for p in mesh_paths], "rig": config.rig.to_dict(),
        "config": config.to_dict(), "label": label.to_dict(), "noise_free": bool(noise_free),
    }


def _settings_diff(folder: Path, settings: dict) -> list[str]:
    """The settings in which ``folder``'s ``dataset.json`` differs from ``settings`` (the version aside); []
    when it has none."""
    if not (folder / SETTINGS_FILE).is_file():
        return []
    try:
        old = read_settings(folder)
    except DatasetError:
        raise GenerateError(f"{folder / SETTINGS_FILE} is corrupt: remove it or use a new --out") from None
    return [k for k in settings if k != "version" and not _same_setting(k, old.get(k), json.loads(json_text(settings[k])))]


def _same_setting(key: str, old, new) -> bool:
    """The meshes by real path, in order (a folder given through a link is the same folder, as sim2real compares
    them: :func:`fppsim.rendering.scene.changed_meshes`); every other setting as written."""
    if key == "meshes" and isinstance(old, list) and all(isinstance(p, str) for p in old):
        return [os.path.realpath(p) for p in old] == [os.path.realpath(p) for p in new]
    return old == new


def _claim_dataset(out: Path, native: Path, has_samples: bool, settings: dict, names, what: str) -> list[str]:
    """Claim a dataset's fixed ``names`` in ``out``'s record and return where ``native``'s ``dataset.json`` differs
    from ``settings``. Beside fppsim's finished samples (``has_samples``) that file is fppsim's and is compared
    first: a difference is returned unclaimed, so the refusal that follows writes nothing, not even the record."""
    diff = _settings_diff(native, settings) if has_samples else []
    if not diff:
        claim(out, DATASET_TOOL, names, legacy=lambda: legacy_files(out), hint=f"move it away, or use another {what}")
        diff = _settings_diff(native, settings)  # claimed: ours, or none
    return diff


def _open_dataset(out: Path, fmt: str, count: int, shard, settings: dict, preview: bool) -> tuple[list[int], set[int], bool]:
    """Check ``out`` for this run, then claim its fixed files and write its settings: ``(wanted indices,
    finished ones, whether this run wrote dataset.json)``. Every refusal comes before anything is written."""
    check_format(out, fmt)
    check_no_frames(out, dataset_files(fmt, preview))  # the user's own frames: never a dataset beside them
    native = samples_folder(out, fmt)
    wanted = shard_indices(count, shard)
    done = finished_indices(native)
    foreign = foreign_sample_folders(native, set(wanted) - done)
    if foreign:  # fppsim never replaces (nor counts) a folder it did not write
        raise GenerateError(f"{foreign[0]} exists but is not a finished fppsim sample"
                            + (f" (and {len(foreign) - 1} more)" if len(foreign) > 1 else "")
                            + ": move it away, or use another --out")
    extra = sorted(done - set(wanted))
    if fmt == "figshare" and extra:  # the arrays would hold fewer samples than native/ beside them
        raise GenerateError(f"{native} holds {len(done)} samples, {len(extra)} of them outside --count {count}"
                            + (f" --shard {shard[0]}/{shard[1]}" if shard else "")
                            + f" (sample {sample_id(extra[0])}), so f1_80.npy and Z.npy would leave them out: "
                            f"give --count {max(done) + 1} or more, or use another --out")
    diff = _claim_dataset(out, native, bool(done), settings, dataset_files(fmt, preview), "--out")
    if diff and done:
        raise GenerateError(f"{native} holds a dataset made with different {', '.join(diff)}: "
                            "use a new --out (or the same options) to resume")
    # new, or settings beside no finished sample (a run that failed before its first): ours to (re)write
    created = bool(diff) or not (native / SETTINGS_FILE).is_file()
    if created:
        native.mkdir(parents=True, exist_ok=True)
        atomic_write_text(native / SETTINGS_FILE, json_text(settings, indent=1))
    return wanted, done, created


def generate_dataset(mesh_paths, out, count: int, seed: int = 0, config: SynthConfig | None = None,
                     workers: int = 1, fmt: str = "native", shard: tuple[int, int] | None = None,
                     label: LabelTransform | None = None, noise_free: bool = False, progress: bool = True,
                     backend: str | None = None, preview: bool = False) -> RunSummary:
    """Generate (or complete) a dataset from an already-built :class:`SynthConfig` (what
    :func:`generate` calls). See the module docstring; returns a :class:`RunSummary`.

    ``backend``: GL platform ``osmesa`` or ``egl`` (None: ``$PYOPENGL_PLATFORM``, else osmesa); it does
    not change the samples beyond rasteriser rounding (depth within about 1e-3 mm).

    ``fmt="figshare"`` keeps the native samples in ``out/native`` and writes ``out/f1_80.npy`` and
    ``out/Z.npy`` at the end. ``preview``: also write ``out/preview.png``.

    Every check (meshes, seed, the folder's format, settings and files) comes before anything is written;
    the fixed files are claimed in ``out``'s ownership record (:mod:`fppsim.dataio.dataset_folder`), so a
    file someone else put there is refused, never replaced. A run that fails before its first sample
    leaves nothing behind.
    """
    t0 = time.perf_counter()
    if count < 1:
        raise GenerateError(f"--count must be >= 1, got {count}")
    if fmt not in FORMATS:
        raise GenerateError(f"unknown format '{fmt}' (native or figshare)")
    check_seed(seed)  # numpy refused a negative seed only inside the first sample, after dataset.json was written
    backend = select_backend(backend)  # before the workers spawn: they inherit the platform
    config = config or SynthConfig(rig=Rig.default())
    label = label or LabelTransform()
    label.check()
    config.rig.check_usable()  # before any sample is written
    # the meshes are read before --out is touched: a bad --meshes leaves no folder behind
    assets, skipped = load_assets(mesh_paths) if mesh_paths else ([], [])
    if not assets and not (config.scene.procedural_share >= 1.0 and not skipped):
        reasons = "; ".join(r for _, r in skipped) or "no mesh files found"
        raise GenerateError(f"no usable mesh ({reasons})")
    settings = _settings(config, seed, [a.path for a in assets], fmt, label, noise_free)
    with signals_raise():  # SIGTERM (e.g. a Slurm timeout) stops like Ctrl-C: pool terminated, exit 143
        with output_folder(out, "fppsim generate", error=GenerateError) as out_path:
            native = samples_folder(out_path, fmt)
            native_made = not native.exists()
            wanted, done, created = _open_dataset(out_path, fmt, count, shard, settings, preview)
            summary = RunSummary(out=str(out), requested=len(wanted), existing=len(set(wanted) & done),
                                 skipped_meshes=skipped)
            try:
                _generate(summary, assets, out_path, wanted, seed, config, workers, fmt, label, noise_free,
                          progress, backend)
            except BaseException:
                if created and not finished_indices(native):  # this run's settings, and no sample beside them
                    discard_empty_dataset(native, folder_too=native_made and native != out_path)
                raise
            if preview:
                summary.preview = str(write_preview(native, out_path / PREVIEW_NAME))
            summary.seconds = time.perf_counter() - t0
            return summary


def _generate(summary, assets, out, wanted, seed, config, workers, fmt, label, noise_free, progress, backend):
    from tqdm import tqdm

    native = samples_folder(out, fmt)
    done = {r["index"] for r in reconcile(native)}
    todo = [i for i in wanted if i not in done]
    # figshare rows come back with the samples when this run produces all of them (else: read back)
    rows = None
    if fmt == "figshare" and todo and not summary.existing:
        rows = FigshareRows(out, len(wanted), config.rig.camera.height, config.rig.camera.width)
    position = {index: k for k, index in enumerate(wanted)}
    init_args = (assets, config, seed, str(native), noise_free, label if rows is not None else None, backend)
    bar = tqdm(total=len(wanted), initial=summary.existing, unit="sample", desc="generate",
               disable=not progress, dynamic_ncols=True)

    def consume(chunks):
        for chunk in chunks:
            for index, record, error, row in chunk:
                if error is None:
                    append_manifest(native, record)
                    summary.written += 1
                    if rows is not None:
                        rows.put(position[index], *row)
                else:
                    summary.failed.append((index, error))
                    log.warning("%s", error)
                bar.update(1)

    try:
        if workers <= 1 or len(todo) <= 1:
            _worker_init(*init_args)
            try:
                consume(map(_worker_run_chunk, _chunks(todo, 1)))
            finally:
                _WORKER["writer"].close()
        else:
            # spawn, not fork: a GL (OSMesa/llvmpipe) context and its threads do not survive fork()
            ctx = mp.get_context("spawn")
            with ctx.Pool(min(workers, len(todo)), initializer=_worker_init, initargs=(*init_args, True)) as pool:
                consume(pool.imap_unordered(_worker_run_chunk, _chunks(todo, workers)))
    except BaseException:
        if rows is not None:
            rows.discard()
        raise
    finally:
        bar.close()
    reconcile(native)  # manifest sorted by index
    if summary.written + summary.existing == 0:
        if rows is not None:  # its temp arrays too: a failed run leaves nothing
            rows.discard()
        raise GenerateError("nothing could be generated: " + (summary.failed[0][1] if summary.failed else "no samples"))
    if fmt == "figshare":  # this run's samples, in index order: native/ holds no others (checked up front)
        if rows is not None and rows.complete:
            n = rows.commit()
        else:
            if rows is not None:
                rows.discard()
            folders = [native / sample_id(i) for i in wanted if (native / sample_id(i) / "meta.json").is_file()]
            n = export_figshare(native, out, label, folders=folders)
        summary.figshare = f"{out / FIGSHARE_PAIRS[0][0]} + {out / FIGSHARE_PAIRS[0][1]} ({n} samples)"


def merge(out, shard_dirs, link: bool = True) -> tuple[int, str | None, list[int]]:
    """Join native shard folders into ``out`` (hard links when possible) with one manifest.

    Shards must come from the same settings (``dataset.json``, ignoring nothing but the version).
    Figshare-format shards (a ``native`` subfolder) also get one ``f1_80.npy``/``Z.npy`` pair.
    ``out``'s fixed files are claimed as :func:`generate_dataset` claims them (a merged folder resumes with
    ``generate``). Returns (samples in out, figshare path or None, missing indices below the largest one).
    """
    out = Path(out)
    natives, settings, fmt = [], None, None
    for d in map(Path, shard_dirs):
        samples = open_source(d).fppsim_samples()
        nd = samples.path if samples is not None else d
        s = read_settings(nd)
        if s is None:
            raise DatasetError(f"{d}: not an fppsim dataset folder (no dataset.json)")
        s.pop("version", None)
        if settings is None:
            settings, fmt = s, s.get("format", "native")
        elif s != settings:
            raise DatasetError(f"{d}: made with different settings than {shard_dirs[0]}; cannot merge")
        natives.append(nd)
    if not natives:
        raise DatasetError("no shard folders given")
    check_shards(out, shard_dirs, natives)  # OUT none of them, no damaged sample: before anything is written
    with output_folder(out, "fppsim merge", error=DatasetError):
        check_format(out, fmt)
        check_no_frames(out, dataset_files(fmt), "OUT", DatasetError)
        target = samples_folder(out, fmt)
        diff = _claim_dataset(out, target, bool(finished_indices(target)), settings, dataset_files(fmt),
                              "output folder")
        if diff:
            raise DatasetError(f"{target} holds a dataset made with different {', '.join(diff)}: cannot merge "
                               "these shards into it")
        target.mkdir(parents=True, exist_ok=True)
        if not (target / SETTINGS_FILE).is_file():
            atomic_write_text(target / SETTINGS_FILE, json_text({**settings, "version": __version__}, indent=1))
        return _merge(out, target, natives, settings, fmt, link)


def _merge(out, target, natives, settings, fmt, link):
    reconcile(target)
    for nd in natives:
        for rec in reconcile(nd):
            src, dst = nd / rec["id"], target / rec["id"]
            if dst.exists():
                if foreign_sample_folders(target, {int(rec["index"])}):
                    raise DatasetError(f"{dst} exists but is not a finished fppsim sample: move it away")
                continue
            tmp = tmp_path(dst)
            shutil.rmtree(tmp, ignore_errors=True)
            if link:
                try:
                    shutil.copytree(src, tmp, copy_function=os.link)
                except OSError:
                    shutil.rmtree(tmp, ignore_errors=True)
                    shutil.copytree(src, tmp)
            else:
                shutil.copytree(src, tmp)
            os.replace(tmp, dst)
    records = reconcile(target)
    have = {int(r["index"]) for r in records}
    missing = sorted(set(range(max(have) + 1)) - have) if have else []
    fig = None
    if fmt == "figshare":
        export_figshare(target, out, LabelTransform.from_dict(settings["label"]))
        fig = str(out)
    return len(records), fig, missing

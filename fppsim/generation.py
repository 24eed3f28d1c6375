"""Dataset generation run: mesh loading, sharding, worker pool, resumable writing, summary.

``fppsim.generate(GenerateConfig(meshes=[...], out=..., count=N))`` is the whole run as the command
line does it (rig file, optics overrides, label preset, preview); :func:`generate_dataset` is the
same run over an already-built :class:`fppsim.synth.SynthConfig`.

A run owns an output folder. ``dataset.json`` records the settings; re-running the same command on
the same folder first reconciles it (temporary folders removed, manifest rebuilt from the complete
sample folders) and then produces only the missing samples, so an interrupted run completes without
duplicates. Samples are independent of the worker count (see :mod:`fppsim.synth`).
"""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence


from . import __version__
from .errors import ConfigError, DatasetError, GenerateError, MeshError, SampleError
from .formats import (LabelTransform, append_manifest, atomic_write_text, export_figshare, manifest_record,
                      read_settings, reconcile, sample_id, write_sample_folder)
from .scene import MeshAsset, find_meshes, load_mesh
from .synth import SynthConfig, synthesize

log = logging.getLogger("fppsim")

__all__ = ["GenerateConfig", "GenerateError", "RunSummary", "load_assets", "generate", "generate_dataset",
           "shard_indices", "merge", "read_optics_file", "FORMATS", "SUPERSAMPLE"]

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

    def lines(self) -> list[str]:
        out = [f"samples: {self.written} written, {self.existing} already there, {len(self.failed)} failed "
               f"(of {self.requested} in this shard) in {self.seconds:.1f} s -> {self.out}"]
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


@dataclass
class GenerateConfig:
    """Everything ``fppsim generate`` needs; checks itself on construction (:class:`ConfigError`).

    meshes : mesh files or folders. out : output folder (re-running resumes it). count : samples in
    the whole dataset; sample i depends only on (seed, i). rig : calibration file, a :class:`Rig`, or
    None for the packaged default rig. objects : (lo, hi) objects per scene. format : one of
    :data:`FORMATS`. shard : (i, n) to generate only every n-th sample from i. supersample : one of
    :data:`SUPERSAMPLE`. optics : optics range overrides ``{name: value or [lo, hi]}`` (names of
    :class:`fppsim.optics.OpticsRanges`). psp_freqs : unwrapping ladder starting at 1 and ending at
    the rig's frequency; () skips the phase-shifting images. label : figshare label transform.
    preview : also write ``out/preview.png``.
    """

    meshes: Sequence[str]
    out: str | os.PathLike
    count: int
    seed: int = 0
    rig: "str | os.PathLike | Rig | None" = None  # noqa: F821
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
    preview: bool = False
    progress: bool = True

    def __post_init__(self):
        if isinstance(self.meshes, (str, os.PathLike)):
            self.meshes = [self.meshes]
        if not self.meshes:
            raise ConfigError("no meshes given")
        if int(self.count) < 1:
            raise ConfigError(f"--count must be >= 1, got {self.count}")
        if self.format not in FORMATS:
            raise ConfigError(f"unknown format '{self.format}' ({' or '.join(FORMATS)})")
        if self.supersample not in SUPERSAMPLE:
            raise ConfigError(f"supersample must be one of {SUPERSAMPLE}, got {self.supersample}")
        if int(self.workers) < 1:
            raise ConfigError(f"workers must be >= 1, got {self.workers}")
        lo, hi = self.objects
        if not 1 <= lo <= hi:
            raise ConfigError(f"objects must be LO-HI with 1 <= LO <= HI, got {lo}-{hi}")
        if self.shard is not None:
            shard_indices(1, self.shard)  # raises on a bad shard
        if self.psp_freqs:
            f = tuple(int(v) for v in self.psp_freqs)
            if f[0] != 1 or any(b <= a for a, b in zip(f, f[1:])):
                raise ConfigError(f"--psp-freqs ladder must start at 1 and increase, got {list(f)}")
            if self.psp_steps < 3:
                raise ConfigError(f"--psp-steps must be >= 3, got {self.psp_steps}")
        try:
            self.label.check()
        except DatasetError as exc:
            raise ConfigError(str(exc)) from None

    def synth_config(self) -> SynthConfig:
        """The renderer's configuration: loads the rig and checks the ladder against it."""
        from .optics import OpticsRanges
        from .rig import Rig, load_rig
        from .scene import SceneRanges

        rig = self.rig if isinstance(self.rig, Rig) else load_rig(self.rig)
        optics = OpticsRanges.from_dict(dict(self.optics))
        freqs = tuple(int(f) for f in self.psp_freqs)
        if freqs and freqs[-1] != rig.periods:
            raise ConfigError(f"--psp-freqs must end at the rig's single-shot frequency {rig.periods:g}, got {freqs[-1]}")
        return SynthConfig(rig=rig, optics=optics, scene=SceneRanges(objects=tuple(self.objects)),
                           supersample=self.supersample, psp_freqs=freqs, psp_steps=self.psp_steps)


def read_optics_file(path: str | os.PathLike) -> dict:
    """Optics range overrides from a JSON/YAML mapping ``{name: value or [lo, hi]}``."""
    import yaml

    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"file not found: {p}")
    try:
        doc = yaml.safe_load(p.read_text()) if p.suffix.lower() in (".yaml", ".yml") else json.loads(p.read_text())
    except Exception as exc:
        raise ConfigError(f"{p}: not valid JSON/YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"{p}: expected a mapping of name -> value or [lo, hi]")
    return doc


def generate(config: GenerateConfig) -> RunSummary:
    """Generate (or complete) the dataset ``config`` describes; returns a :class:`RunSummary`."""
    summary = generate_dataset(config.meshes, config.out, config.count, seed=config.seed,
                               config=config.synth_config(), workers=config.workers, fmt=config.format,
                               shard=config.shard, label=config.label, noise_free=config.noise_free,
                               progress=config.progress)
    if config.preview:
        from .preview import write_preview

        root = Path(config.out) / ("native" if config.format == "figshare" else "")
        summary.preview = str(write_preview(root, Path(config.out) / "preview.png"))
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
    return assets, skipped


def shard_indices(count: int, shard: tuple[int, int] | None) -> list[int]:
    """Global sample indices of shard ``(i, n)`` (round robin), or all of ``range(count)``."""
    if shard is None:
        return list(range(count))
    i, n = shard
    if not (n >= 1 and 0 <= i < n):
        raise ValueError(f"shard must be I/N with 0 <= I < N, got {i}/{n}")
    return list(range(i, count, n))


# --------------------------------------------------------------------------- worker side
_WORKER: dict = {}


def _worker_init(assets, config, seed, out, noise_free):
    from .render import DepthRenderer

    _WORKER.update(assets=assets, config=config, seed=seed, out=Path(out), noise_free=noise_free,
                   renderer=DepthRenderer())


def _worker_run(index: int):
    w = _WORKER
    sid = sample_id(index)
    try:
        images, arrays, meta = synthesize(index, w["seed"], w["assets"], w["config"], w["renderer"],
                                          noise_free=w["noise_free"])
    except SampleError as exc:
        return index, None, str(exc)
    write_sample_folder(w["out"], sid, images, arrays, meta)
    return index, manifest_record(sid, meta), None


# --------------------------------------------------------------------------- run
def _settings(config: SynthConfig, seed: int, mesh_paths: list[str], fmt: str, label: LabelTransform,
              noise_free: bool) -> dict:
    return {
        "generator": "fppsim", "version": __version__, "seed": int(seed), "format": fmt,
        "meshes": [os.path.abspath(p) for p in mesh_paths], "rig": config.rig.to_dict(),
        "config": config.to_dict(), "label": label.to_dict(), "noise_free": bool(noise_free),
    }


def _check_settings(path: Path, settings: dict) -> None:
    if not path.is_file():
        atomic_write_text(path, json.dumps(settings, indent=1))
        return
    try:
        old = read_settings(path.parent)
    except DatasetError:
        raise GenerateError(f"{path} is corrupt: remove it or use a new --out") from None
    diff = [k for k in settings if k != "version" and old.get(k) != json.loads(json.dumps(settings[k]))]
    if diff:
        raise GenerateError(f"{path.parent} holds a dataset made with different {', '.join(diff)}: "
                            "use a new --out (or the same options) to resume")


def generate_dataset(mesh_paths, out, count: int, seed: int = 0, config: SynthConfig | None = None,
             workers: int = 1, fmt: str = "native", shard: tuple[int, int] | None = None,
             label: LabelTransform | None = None, noise_free: bool = False, progress: bool = True) -> RunSummary:
    """Generate (or complete) a dataset. See the module docstring; returns a :class:`RunSummary`.

    ``fmt="figshare"`` keeps the native samples in ``out/native`` and writes ``out/f1_80.npy`` and
    ``out/Z.npy`` at the end.
    """
    from tqdm import tqdm

    from .rig import Rig

    t0 = time.perf_counter()
    if count < 1:
        raise GenerateError(f"--count must be >= 1, got {count}")
    if fmt not in ("native", "figshare"):
        raise GenerateError(f"unknown format '{fmt}' (native or figshare)")
    config = config or SynthConfig(rig=Rig.default())
    label = label or LabelTransform()
    label.check()
    assets, skipped = load_assets(mesh_paths)
    summary = RunSummary(out=str(out), requested=0, skipped_meshes=skipped)
    if not assets:
        reasons = "; ".join(r for _, r in skipped) or "no mesh files found"
        raise GenerateError(f"no usable mesh ({reasons})")
    out = Path(out)
    native = out / "native" if fmt == "figshare" else out
    try:
        native.mkdir(parents=True, exist_ok=True)
        probe = native / f".write-test.{os.getpid()}.tmp"
        probe.write_text("ok")
        probe.unlink()
    except OSError as exc:
        raise GenerateError(f"cannot write to output folder {out}: {exc.strerror or exc}") from None

    _check_settings(native / "dataset.json", _settings(config, seed, [a.path for a in assets], fmt, label, noise_free))

    wanted = shard_indices(count, shard)
    summary.requested = len(wanted)
    done = {r["index"] for r in reconcile(native)}
    todo = [i for i in wanted if i not in done]
    summary.existing = len(wanted) - len(todo)

    init_args = (assets, config, seed, str(native), noise_free)
    bar = tqdm(total=len(wanted), initial=summary.existing, unit="sample", desc="generate",
               disable=not progress, dynamic_ncols=True)

    def consume(results):
        for index, record, error in results:
            if error is None:
                append_manifest(native, record)
                summary.written += 1
            else:
                summary.failed.append((index, error))
                log.warning("%s", error)
            bar.update(1)

    try:
        if workers <= 1 or len(todo) <= 1:
            _worker_init(*init_args)
            consume(map(_worker_run, todo))
        else:
            # spawn, not fork: a GL (OSMesa/llvmpipe) context and its threads do not survive fork()
            ctx = mp.get_context("spawn")
            with ctx.Pool(min(workers, len(todo)), initializer=_worker_init, initargs=init_args) as pool:
                consume(pool.imap_unordered(_worker_run, todo))
    finally:
        bar.close()
    reconcile(native)  # manifest sorted by index
    summary.seconds = time.perf_counter() - t0
    if summary.written + summary.existing == 0:
        raise GenerateError("nothing could be generated: " + (summary.failed[0][1] if summary.failed else "no samples"))
    if fmt == "figshare":  # exactly this run's samples, in index order (a folder may hold more)
        folders = [native / sample_id(i) for i in wanted if (native / sample_id(i) / "meta.json").is_file()]
        n = export_figshare(native, out, label, folders=folders)
        summary.figshare = f"{out / 'f1_80.npy'} + {out / 'Z.npy'} ({n} samples)"
    return summary


def merge(out, shard_dirs, link: bool = True) -> tuple[int, str | None, list[int]]:
    """Join native shard folders into ``out`` (hard links when possible) with one manifest.

    Shards must come from the same settings (``dataset.json``, ignoring nothing but the version).
    Figshare-format shards (a ``native`` subfolder) also get one ``f1_80.npy``/``Z.npy`` pair.
    Returns (samples in out, figshare path or None, missing indices below the largest one).
    """
    import shutil

    out = Path(out)
    natives, settings, fmt = [], None, None
    for d in map(Path, shard_dirs):
        nd = d / "native" if (d / "native" / "dataset.json").is_file() else d
        if not (nd / "dataset.json").is_file():
            raise DatasetError(f"{d}: not an fppsim dataset folder (no dataset.json)")
        s = read_settings(nd)
        s.pop("version", None)
        if settings is None:
            settings, fmt = s, s.get("format", "native")
        elif s != settings:
            raise DatasetError(f"{d}: made with different settings than {shard_dirs[0]}; cannot merge")
        natives.append(nd)
    if not natives:
        raise DatasetError("no shard folders given")
    target = out / "native" if fmt == "figshare" else out
    target.mkdir(parents=True, exist_ok=True)
    _check_settings(target / "dataset.json", {**settings, "version": __version__})
    reconcile(target)
    for nd in natives:
        for rec in reconcile(nd):
            src, dst = nd / rec["id"], target / rec["id"]
            if dst.exists():
                continue
            tmp = target / ".tmp" / rec["id"]
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.parent.mkdir(parents=True, exist_ok=True)
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

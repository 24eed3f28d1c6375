"""Dataset generation run: mesh loading, sharding, worker pool, resumable writing, summary.

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


from . import __version__
from ._fs import clean_stale_tmp, die_with_parent, folder_lock, ignore_sigint, signals_raise, tmp_path
from .errors import DatasetError, GenerateError, MeshError, SampleError
from .formats import (LabelTransform, append_manifest, atomic_write_text, export_figshare, foreign_sample_folders,
                      manifest_record, read_settings, reconcile, sample_id, write_sample_folder)
from .scene import MeshAsset, find_meshes, load_mesh
from .synth import SynthConfig, synthesize

log = logging.getLogger("fppsim")

__all__ = ["GenerateError", "RunSummary", "load_assets", "generate", "shard_indices", "merge"]


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
        return out


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


def _worker_init(assets, config, seed, out, noise_free, label=None, backend=None, pool_worker=False):
    from .pipeline import BackgroundWriter
    from .render import DepthRenderer

    if pool_worker:  # only the parent reacts to Ctrl-C/SIGTERM (it terminates the pool); no orphans
        ignore_sigint()
        die_with_parent()
    _WORKER.update(assets=assets, config=config, seed=seed, out=Path(out), noise_free=noise_free,
                   renderer=DepthRenderer(backend), label=label, writer=BackgroundWriter())


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


def _worker_run_chunk(indices: list[int]) -> list[tuple]:
    """Produce ``indices``, writing each sample on the background thread while the next one renders.

    Returns ``(index, record, error, figshare rows or None)`` per index once every folder of the
    chunk is complete on disk, so the manifest never lists a sample still being written.
    """
    from .pipeline import figshare_rows

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


def generate(mesh_paths, out, count: int, seed: int = 0, config: SynthConfig | None = None,
             workers: int = 1, fmt: str = "native", shard: tuple[int, int] | None = None,
             label: LabelTransform | None = None, noise_free: bool = False, progress: bool = True,
             backend: str | None = None) -> RunSummary:
    """Generate (or complete) a dataset. See the module docstring; returns a :class:`RunSummary`.

    ``backend``: GL platform ``osmesa`` or ``egl`` (None: ``$PYOPENGL_PLATFORM``, else osmesa); it does
    not change the samples beyond rasteriser rounding (depth within about 1e-3 mm).

    ``fmt="figshare"`` keeps the native samples in ``out/native`` and writes ``out/f1_80.npy`` and
    ``out/Z.npy`` at the end.
    """
    from .rig import Rig

    t0 = time.perf_counter()
    if count < 1:
        raise GenerateError(f"--count must be >= 1, got {count}")
    if fmt not in ("native", "figshare"):
        raise GenerateError(f"unknown format '{fmt}' (native or figshare)")
    from .render import select_backend

    backend = select_backend(backend)  # before the workers spawn: they inherit the platform
    config = config or SynthConfig(rig=Rig.default())
    label = label or LabelTransform()
    label.check()
    config.rig.check_usable()  # before any sample is written
    with signals_raise():  # SIGTERM (e.g. a Slurm timeout) stops like Ctrl-C: pool terminated, exit 143
        out_path = Path(out)
        try:
            out_path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise GenerateError(f"cannot write to output folder {out}: {exc.strerror or exc}") from None
        with folder_lock(out_path, "fppsim generate"):
            return _generate(mesh_paths, out, count, seed, config, workers, fmt, shard, label, noise_free,
                             progress, t0, backend)


def _generate(mesh_paths, out, count, seed, config, workers, fmt, shard, label, noise_free, progress, t0, backend):
    from tqdm import tqdm

    assets, skipped = load_assets(mesh_paths) if mesh_paths else ([], [])
    summary = RunSummary(out=str(out), requested=0, skipped_meshes=skipped)
    if not assets and not (config.scene.procedural_share >= 1.0 and not skipped):
        reasons = "; ".join(r for _, r in skipped) or "no mesh files found"
        raise GenerateError(f"no usable mesh ({reasons})")
    out = Path(out)
    native = out / "native" if fmt == "figshare" else out
    try:
        native.mkdir(parents=True, exist_ok=True)
        probe = tmp_path(native / "write-test")
        probe.write_text("ok")
        probe.unlink()
    except OSError as exc:
        raise GenerateError(f"cannot write to output folder {out}: {exc.strerror or exc}") from None

    _check_settings(native / "dataset.json", _settings(config, seed, [a.path for a in assets], fmt, label, noise_free))

    wanted = shard_indices(count, shard)
    summary.requested = len(wanted)
    clean_stale_tmp(out)
    done = {r["index"] for r in reconcile(native)}
    todo = [i for i in wanted if i not in done]
    summary.existing = len(wanted) - len(todo)
    foreign = foreign_sample_folders(native, set(todo))
    if foreign:  # fppsim never replaces (nor counts) a folder it did not write
        raise GenerateError(f"{foreign[0]} exists but is not a finished fppsim sample"
                            + (f" (and {len(foreign) - 1} more)" if len(foreign) > 1 else "")
                            + ": move it away, or use another --out")

    # figshare rows come back with the samples when this run produces all of them (else: read back)
    rows = None
    if fmt == "figshare" and todo and not summary.existing:
        from .pipeline import FigshareRows

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
    summary.seconds = time.perf_counter() - t0
    if summary.written + summary.existing == 0:
        raise GenerateError("nothing could be generated: " + (summary.failed[0][1] if summary.failed else "no samples"))
    if fmt == "figshare":  # exactly this run's samples, in index order (a folder may hold more)
        if rows is not None and rows.complete:
            n = rows.commit()
        else:
            if rows is not None:
                rows.discard()
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
    with folder_lock(out, "fppsim merge"):
        return _merge(out, target, natives, settings, fmt, link)


def _merge(out, target, natives, settings, fmt, link):
    import shutil

    _check_settings(target / "dataset.json", {**settings, "version": __version__})
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

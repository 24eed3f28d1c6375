#!/usr/bin/env python
"""Few real scans: does one labelled real pair help a synthetic-pretrained network on real frames it never saw?

Arms (all the same architecture as the synthetic-only run; every trained arm b-d takes the same number of
draws per epoch, ``--samples-per-epoch`` or 1 + the synthetic training samples, so they take the same steps):

  syn-only         (a) the sim-to-real recipe: synthetic data only (``--syn-run DIR`` reuses one, read only;
                   otherwise ``fppsim generate`` + ``uhrnet train`` here, see --count / --pretrain-epochs)
  real-only        (b) from scratch on the one labelled real pair (``--real-split train``), --scratch-lr
  ft-real          (c) --init-from the synthetic-only run, fine-tuned on the pair alone, --lr
  ft-mixed         (c) the same with synthetic batches mixed in (``--synthetic-ratio 0.5``): the issue's recipe
  ft-mixed-freeze  (c) ft-mixed with ``--freeze encoder``
  mixed-scratch    (d) from scratch on the pair + synthetic (ratio 0.5), --scratch-lr, --scratch-epochs

Judged on real frames no arm trained on (the pair is training data for b-d and is NOT scored for them):

  * ``uhrnet evaluate-phase`` on --phase-root (default ../shared/real-phase/FP1523): the calibration-free
    phase residual (rad) of each arm's height map (lower is better; the plane-only fit is the floor to beat);
  * millimetres: ``fppsim label-real`` of the same frame through --rig (default: the packaged default rig,
    fitted to this data; phase offset fitted on the plane) gives a height label; each arm's RMSE against it
    over the object pixels (valid, more than 1 mm above the plane) and over all valid pixels
    (:func:`uhrnet.workflows.sim2real.evaluate_real`); a second mm column labels the frame through --check-rig
    (default assets/figshare_depth_rig.json: the default rig reads real heights about 8 % low at 40 mm,
    docs/experiments/physics.md section 3, so arms that learn the pair's own scale are also scored on it).

The pair is scored for syn-only only (as in DESIGN.md section 9); for b-d its RMSE is shown as the fit of
the training data. Writes OUT/report.json, OUT/report.md and OUT/few_scans.png; OUT/runs/<arm>/ (training
runs), OUT/eval/<arm>/, OUT/labels/heldout/, OUT/logs/<stage>.log. Re-running the same command resumes: finished
datasets, runs and evaluations are reused; an interrupted training run continues from its last.pt.

    # the issue's judged setting (U-Net base 16 pretrained 4 epochs on 160 recipe samples, fine-tuned 2 epochs)
    python pipelines/few_scans.py --out runs/few_scans
    # reuse an existing synthetic-only run (its synthetic data is mixed into the fine-tunes)
    python pipelines/few_scans.py --out runs/few_scans_base --syn-run runs/recipe --samples-per-epoch 129
    # a tiny smoke run
    python pipelines/few_scans.py --out runs/few_scans_smoke --count 6 --pretrain-epochs 1 --epochs 1 --samples-per-epoch 2 \\
        --base-channels 4 --workers 1

Cost on 2 CPU cores (U-Net base 16, batch 2, 352 x 640): about 3.5 s a step. The default setting: 160
samples, 4 x 64 pretraining steps, 129 steps per arm b-c and 6 x 129 / 2 = 387 for mixed-scratch: a bit over
an hour. With ``--syn-run`` on the 400-sample recipe the default epoch is 321 draws (19 minutes an arm) and
mixed-scratch gets 10 + 2 such epochs (about 2 hours): bound it with --samples-per-epoch / --scratch-epochs.

Units: heights in mm, phases in rad. Labels: the figshare preset (label = 6 mm - 97, invalid -105).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from uhrnet.errors import Sim2RealError  # noqa: E402 (after the path)
from uhrnet.run_folder import (CHECKPOINTS, CONFIG_JSON, LAST_PT, default_meshes, fresh, read_history,  # noqa: E402
                               run_epochs)
from uhrnet.workflows.stages import dataset_count, run_stage  # noqa: E402

SHARED = ROOT.parent / "shared"
ARMS = ("syn-only", "real-only", "ft-real", "ft-mixed", "ft-mixed-freeze", "mixed-scratch")
DESCRIPTION = {
    "syn-only": "(a) synthetic only",
    "real-only": "(b) real pair only, from scratch",
    "ft-real": "(c) synthetic-pretrained, fine-tuned on the pair alone",
    "ft-mixed": "(c) synthetic-pretrained, fine-tuned on the pair + synthetic (ratio 0.5)",
    "ft-mixed-freeze": "(c) as ft-mixed, encoder frozen",
    "mixed-scratch": "(d) pair + synthetic (ratio 0.5) from scratch",
}
OBJECT_MM = 1.0


class PipelineError(Exception):
    """A stage failed or the inputs do not fit; one line naming the culprit."""


# ============================================================================================ arguments
def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="few_scans.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="experiment folder (created; re-running resumes it)")
    g = p.add_argument_group("real data")
    g.add_argument("--real-pair", default=str(SHARED / "real-sample"),
                   help="the ONE labelled real pair the arms b-d train on (figshare layout) [%(default)s]")
    g.add_argument("--phase-root", default=str(SHARED / "real-phase" / "FP1523"),
                   help="held-out real phase-shifting frame(s) (PSin/ PCos/ Fringe/ iPattern/) [%(default)s]")
    g.add_argument("--rig", default=None,
                   help="rig of the real frames for label-real's mm labels [assets/default_rig.json]")
    depth_rig = ROOT / "assets" / "figshare_depth_rig.json"
    g.add_argument("--check-rig", default=str(depth_rig) if depth_rig.is_file() else None,
                   help="a second rig whose label-real labels give a second mm column ('none': skip); the "
                        "default reads real heights about 8 %% low at 40 mm (docs/experiments/physics.md), "
                        "the depth-fitted rig was fitted on the real pair [%(default)s]")
    g = p.add_argument_group("synthetic-only arm (a)")
    g.add_argument("--syn-run", default=None,
                   help="reuse this synthetic-only run folder (read only; best.pt is the start of the fine-tunes) "
                        "instead of generating and training one here")
    g.add_argument("--syn-data", default=None,
                   help="synthetic data mixed into the fine-tunes [the --syn-run's first --synthetic folder, "
                        "else OUT/syn]")
    g.add_argument("--meshes", nargs="+", default=None,
                   help="meshes of the generated data [../shared/meshes (when present) and assets/meshes]")
    g.add_argument("--count", type=int, default=160, help="synthetic samples generated [%(default)s]")
    g.add_argument("--seed", type=int, default=100, help="generation seed (the recipe's) [%(default)s]")
    g.add_argument("--workers", type=int, default=2, help="generation worker processes [%(default)s]")
    g.add_argument("--pretrain-epochs", type=int, default=4, help="epochs of the synthetic-only run [%(default)s]")
    g.add_argument("--pretrain-lr", type=float, default=5e-4, help="its learning rate (the recipe's) [%(default)s]")
    g.add_argument("--model", default="unet", help="architecture of a run trained here [%(default)s]")
    g.add_argument("--base-channels", type=int, default=16, help="its width [%(default)s]")
    g.add_argument("--loss", default="compound", help="its loss (the fine-tunes use the same) [%(default)s]")
    g.add_argument("--batch-size", type=int, default=2, help="batch size of every run trained here [%(default)s]")
    g = p.add_argument_group("arms b-d")
    g.add_argument("--arms", default=",".join(ARMS), help=f"comma-separated subset of {', '.join(ARMS)} [all]")
    g.add_argument("--epochs", type=int, default=2, help="fine-tuning epochs (also real-only) [%(default)s]")
    g.add_argument("--samples-per-epoch", type=int, default=None,
                   help="draws per epoch of every arm b-d [1 + the synthetic training samples]")
    g.add_argument("--lr", type=float, default=1e-4, help="fine-tuning learning rate [%(default)s]")
    g.add_argument("--synthetic-ratio", type=float, default=0.5, help="synthetic share of the mixed arms [%(default)s]")
    g.add_argument("--scratch-lr", type=float, default=5e-4, help="learning rate of the from-scratch arms [%(default)s]")
    g.add_argument("--scratch-epochs", type=int, default=None,
                   help="epochs of mixed-scratch [the synthetic-only run's epochs + --epochs: the draws of (a) + (c)]")
    g.add_argument("--train-seed", type=int, default=0, help="seed of weights and data order of every run [%(default)s]")
    g.add_argument("--device", default="cpu", choices=("cpu", "cuda", "auto"), help="[%(default)s]")
    args = p.parse_args(argv)
    arms = [a.strip() for a in args.arms.split(",") if a.strip()]
    unknown = [a for a in arms if a not in ARMS]
    if unknown or not arms:
        p.error(f"--arms: unknown {', '.join(unknown) or '(none given)'}; choose from {', '.join(ARMS)}")
    args.arms = [a for a in ARMS if a in arms]  # canonical order
    if args.check_rig is not None and args.check_rig.lower() == "none":
        args.check_rig = None
    for name in ("count", "workers", "pretrain_epochs", "epochs", "batch_size", "base_channels"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1")
    for name in ("samples_per_epoch", "scratch_epochs"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1")
    if not 0 < args.synthetic_ratio < 1:
        p.error("--synthetic-ratio must be in (0, 1)")
    return args


# ============================================================================================ stages
def stage(out: Path, name: str, fn, echo=print) -> float:
    """Run ``fn()`` with its printed output in ``OUT/logs/<name>.log`` (the workflow layer's
    :func:`~uhrnet.workflows.stages.run_stage`); returns the seconds taken."""
    log = out / "logs" / f"{name}.log"
    echo(f"[{time.strftime('%H:%M:%S')}] {name} ... (log {log})")
    return run_stage(name, fn, log, f"==== {time.strftime('%Y-%m-%d %H:%M:%S')} {name}")


def generate_synthetic(args, out: Path) -> Path:
    """Recipe (a)'s data: ``fppsim generate --meshes M --count N --seed S --workers W --no-psp --format figshare``."""
    from fppsim.dataio.formats import PRESETS
    from fppsim.generation import GenerateConfig, generate

    data = out / "syn"
    if dataset_count(data) == args.count:
        print(f"synthetic data: {data} ({args.count} samples, done)")
        return data
    cfg = GenerateConfig(meshes=args.meshes or default_meshes(SHARED), out=data, count=args.count, seed=args.seed,
                         workers=args.workers, format="figshare", psp_freqs=(), label=PRESETS["figshare"],
                         preview=True, progress=False)
    stage(out, "generate", lambda: generate(cfg))
    if dataset_count(data) != args.count:
        raise PipelineError(f"{data}: generation wrote {dataset_count(data)} of {args.count} samples (log "
                            f"{out / 'logs' / 'generate.log'})")
    return data


def check_settings(run: Path, options: dict) -> None:
    """Refuse to reuse or resume ``run`` when it was trained with other settings than ``options``."""
    config = run / CONFIG_JSON
    if not config.is_file():
        return
    have = json.loads(config.read_text())
    differ = []
    for key, want in options.items():
        if key in ("device",) or key not in have:
            continue
        got = have[key]
        if key in ("real", "synthetic"):
            same = [str(Path(p).resolve()) for p in got or []] == [str(Path(p).resolve()) for p in want or []]
        elif key == "init_from":
            same = got is not None and want is not None and Path(got).resolve() == Path(want).resolve()
        elif isinstance(want, float) and isinstance(got, (int, float)):
            same = math.isclose(got, want, rel_tol=1e-9)
        else:
            same = (got or None) == (want or None)
        if not same:
            differ.append(f"{key} {got!r} (now {want!r})")
    if differ:
        raise PipelineError(f"{run} was trained with other settings: {'; '.join(differ)}: use another --out, or "
                            "move that run away")


def train_run(out: Path, name: str, run: Path, epochs: int, **options) -> dict:
    """Train ``run`` to ``epochs`` epochs (``uhrnet.train(TrainConfig(...))``), resuming its last.pt."""
    from uhrnet.training.train_config import TrainConfig
    from uhrnet.training.trainer import train

    check_settings(run, options)
    done = run_epochs(run)
    if done >= epochs:
        print(f"{name}: {run} ({done} epochs, done)")
        return {"run": str(run), "epochs": done, "reused": True}
    if done:
        cfg = TrainConfig(out=run, resume="auto", epochs=epochs, progress=False)
    else:
        cfg = TrainConfig(out=run, epochs=epochs, progress=False, overwrite=run.exists(), **options)
    seconds = stage(out, f"train-{name}", lambda: train(cfg))
    return {"run": str(run), "epochs": run_epochs(run), "seconds": seconds}


def arm_options(args, arm: str, syn_cfg: dict, syn_ckpt: Path, syn_data: Path, draws: int) -> tuple[int, dict]:
    """(epochs, TrainConfig options) of a trained arm b-d."""
    model = dict(model=syn_cfg["model"], base_channels=syn_cfg.get("base_channels"),
                 model_option=syn_cfg.get("model_option") or None, raw_output=bool(syn_cfg.get("raw_output")),
                 loss=syn_cfg.get("loss", "compound"), batch_size=syn_cfg.get("batch_size", 2),
                 device=args.device, seed=args.train_seed, samples_per_epoch=draws)
    real = dict(real=[args.real_pair], real_split="train")
    mixed = dict(synthetic=[str(syn_data)], synthetic_ratio=args.synthetic_ratio)
    scratch_epochs = args.scratch_epochs or (int(syn_cfg.get("epochs") or args.pretrain_epochs) + args.epochs)
    table = {
        "real-only": (args.epochs, dict(real, lr=args.scratch_lr)),
        "ft-real": (args.epochs, dict(real, lr=args.lr, init_from=str(syn_ckpt))),
        "ft-mixed": (args.epochs, dict(real, **mixed, lr=args.lr, init_from=str(syn_ckpt))),
        "ft-mixed-freeze": (args.epochs, dict(real, **mixed, lr=args.lr, init_from=str(syn_ckpt), freeze="encoder")),
        "mixed-scratch": (scratch_epochs, dict(real, **mixed, lr=args.scratch_lr)),
    }
    epochs, opts = table[arm]
    return epochs, {**model, **opts}


def evaluate_arm(args, out: Path, arm: str, ckpt: Path, labelled: dict) -> dict:
    """Phase residual on --phase-root, mm on its label-real labels (``labelled``: key -> folder, one per rig)
    and on the pair (see the docstring)."""
    from uhrnet.scoring.phase_residual import PhaseEvalConfig, evaluate_phase_folder
    from uhrnet.workflows.sim2real import evaluate_real

    ev = out / "eval" / arm
    res = {}
    phase_json = ev / "phase" / "phase_results.json"
    if not fresh(phase_json, ckpt):
        stage(out, f"evaluate-phase-{arm}", lambda: evaluate_phase_folder(PhaseEvalConfig(
            checkpoints=[str(ckpt)], phase_root=args.phase_root, out=ev / "phase", names=[arm], figures=3,
            device=args.device)))
    res["phase"] = json.loads(phase_json.read_text())["models"][0]
    for key, folder in (*labelled.items(), ("pair", Path(args.real_pair))):
        doc = ev / key / "real_metrics.json"
        if not fresh(doc, ckpt):
            stage(out, f"evaluate-{key}-{arm}", lambda: evaluate_real(
                ckpt, [str(folder)], ev / key, object_mm=OBJECT_MM, device=args.device, figures=True,
                title=f"{arm}: {DESCRIPTION[arm]}"))
        res[key] = json.loads(doc.read_text())
    return res


def label_heldout(args, out: Path, rig: str | None, name: str) -> tuple[Path, dict]:
    """``fppsim label-real PHASE_ROOT --out OUT/labels/NAME [--rig RIG]`` (phase offset auto)."""
    from fppsim.fitting.label_real import LabelRealConfig, label_real

    dest = out / "labels" / name
    report = dest / "label_real.json"
    if report.is_file():
        doc = json.loads(report.read_text())
        if doc.get("status") == "done" and doc.get("root") == str(args.phase_root) and \
                doc.get("rig", {}).get("source") == (str(rig) if rig else "default (assets/default_rig.json)"):
            return dest, doc
    cfg = LabelRealConfig(root=args.phase_root, out=dest, rig=rig, keep_unfit=True)  # an unfit rig: DOES NOT FIT
    stage(out, f"label-real-{name}", lambda: label_real(cfg))
    return dest, json.loads(report.read_text())


# ============================================================================================ report
def fmt(x, digits=2) -> str:
    return "n/a" if x is None or not isinstance(x, (int, float)) or not math.isfinite(x) else f"{x:.{digits}f}"


def markdown(doc: dict) -> str:
    c = doc["config"]
    h = doc["heldout"]
    lines = [
        "# Few real scans: one labelled real pair on top of synthetic pretraining", "",
        f"Judged on {h['phase_root']} (frames no arm trained on): the calibration-free phase residual "
        f"(`uhrnet evaluate-phase`, degree-3 plane + a h + b h^2, rad; lower is better) and the mm RMSE against "
        f"`fppsim label-real` heights of the same frame through {h['rig']} (phase offset fitted on the plane: "
        f"{fmt(h['phase_offset_rad'], 1)} rad; plane {fmt(h['plane_level_mm'])} mm, RMS {fmt(h['plane_rms_mm'])} mm"
        f"{'' if h['fits'] else ', DOES NOT FIT: ' + '; '.join(h['problems'])}); object pixels are valid and more "
        f"than {OBJECT_MM:g} mm above the plane (input: label-real's f1_80.npy, the iPattern image with -1 where "
        f"the phase is missing, as in the figshare layout; evaluate-phase feeds the raw iPattern). The real pair "
        f"({c['real_pair']}) is training data for b-d: its column is a fit there, not a score.", "",
        f"Synthetic-only run: {doc['syn_run']['run']} ({doc['syn_run']['epochs']} epochs on "
        f"{doc['syn_run']['synthetic']}); fine-tunes start from its best.pt; arms b-d: "
        f"{doc['draws_per_epoch']} draws per epoch, batch {doc['batch_size']}, their last.pt is scored.", "",
    ]
    ck = h.get("check")
    if ck:
        lines += [f"Second mm column: the same frame labelled through {ck['rig']} (objects' 99th percentile "
                  f"{fmt(ck['object_p99_mm'], 1)} mm there, {fmt(h.get('object_p99_mm'), 1)} mm through the first rig).", ""]
    lines += [
        "| arm | what | epochs x draws | lr | phase residual (rad) | explained | object RMSE (mm) | valid RMSE (mm) "
        "| object bias (mm) |" + (" object RMSE, second rig (mm) |" if ck else "") + " pair object RMSE (mm) | minutes |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|" + ("---:|" if ck else "") + "---:|---:|",
    ]
    for a in doc["arms"]:
        r = a["results"]
        held = r["heldout"]["mean"]
        pair = r["pair"]["mean"]["object_rmse_mm"]
        pair_cell = fmt(pair) if a["name"] == "syn-only" else f"({fmt(pair)}, trained on)"
        check_cell = f" {fmt(r['heldout_check']['mean']['object_rmse_mm'])} |" if ck else ""
        lines.append(
            f"| {a['name']} | {DESCRIPTION[a['name']]} | {a['epochs']} x {a['draws'] or 'all'} | {a['lr']:g} | "
            f"{fmt(r['phase']['rmse_rad'], 3)} | {fmt(r['phase']['explained'], 3)} | {fmt(held['object_rmse_mm'])} | "
            f"{fmt(held['valid_rmse_mm'])} | {fmt(held['object_bias_mm'])} |{check_cell} {pair_cell} | "
            f"{fmt((a.get('seconds') or 0) / 60, 1)} |")
    flat = doc["arms"][0]["results"] if doc["arms"] else None
    if flat:
        check_cell = f" {fmt(flat['heldout_check']['mean']['flat_object_rmse_mm'])} |" if ck else ""
        lines.append(f"| plane | predicts the reference plane everywhere | | | "
                     f"{fmt(flat['phase']['flat_rmse_rad'], 3)} | 0 | "
                     f"{fmt(flat['heldout']['mean']['flat_object_rmse_mm'])} | "
                     f"{fmt(flat['heldout']['mean']['flat_valid_rmse_mm'])} | |{check_cell} "
                     f"{fmt(flat['pair']['mean']['flat_object_rmse_mm'])} | |")
    lines += ["", f"![few scans]({doc['figure']})", "",
              "Command: `" + " ".join(doc["argv"]) + "`", ""]
    return "\n".join(lines)


def figure(doc: dict, out: Path, heldout_labels: Path) -> Path:
    """Bars of the two held-out scores per arm, and the held-out frame's label and predictions (mm)."""
    import numpy as np

    from fppsim.dataio.formats import PRESETS
    from fppsim.plots import pyplot, save_figure

    fig_t = PRESETS["figshare"]
    plt = pyplot()
    arms = doc["arms"]
    n = len(arms)
    cols = max(n + 1, 2)
    fig = plt.figure(figsize=(max(12, 3.2 * cols), 7.5))
    gs = fig.add_gridspec(2, cols)
    names = [a["name"] for a in arms]
    half = cols // 2
    for k, (key, title, flat_key) in enumerate((("phase", "phase residual on the held-out frame (rad)", "flat_rmse_rad"),
                                                ("heldout", "object RMSE on the held-out frame (mm)",
                                                 "flat_object_rmse_mm"))):
        ax = fig.add_subplot(gs[0, :half] if k == 0 else gs[0, half:])
        vals = [a["results"]["phase"]["rmse_rad"] if key == "phase" else a["results"]["heldout"]["mean"]["object_rmse_mm"]
                for a in arms]
        vals = [np.nan if v is None else v for v in vals]  # None: null in the JSON read back, not measured
        ax.bar(range(n), vals, color=[f"C{i}" for i in range(n)])
        flat = arms[0]["results"]["phase"][flat_key] if key == "phase" else arms[0]["results"]["heldout"]["mean"][flat_key]
        ax.axhline(np.nan if flat is None else flat, color="k", ls="--", lw=1, label="plane predictor")
        ax.set_xticks(range(n), names, rotation=20, fontsize=8)
        ax.set_title(title)
        ax.legend(fontsize=8)
        ax.grid(axis="y", alpha=0.3)
    z = np.load(heldout_labels / "Z.npy", mmap_mode="r")[0, ..., 0].astype(np.float64)
    valid = z > fig_t.invalid_threshold
    truth = np.where(valid, fig_t.height_mm(z), np.nan)
    hi = float(np.nanpercentile(truth, 99.5)) if np.isfinite(truth).any() else 10.0
    bottom = [fig.add_subplot(gs[1, i]) for i in range(n + 1)]
    ax = bottom[0]
    im = ax.imshow(truth, cmap="viridis", vmin=-5, vmax=max(hi, 1.0))
    ax.set_title("held-out frame: label-real (mm)", fontsize=9)
    ax.set_axis_off()
    for i, a in enumerate(arms, start=1):
        pred = np.load(Path(a["eval"]) / "heldout" / "predictions.npz")["0_000000"].astype(np.float64)
        ax = bottom[i]
        im = ax.imshow(np.where(valid, fig_t.height_mm(pred), np.nan), cmap="viridis", vmin=-5, vmax=max(hi, 1.0))
        ax.set_title(f"{a['name']}: {fmt(a['results']['heldout']['mean']['object_rmse_mm'])} mm", fontsize=9)
        ax.set_axis_off()
    fig.tight_layout()
    fig.colorbar(im, ax=bottom, fraction=0.015, pad=0.01, label="mm above the plane")
    path = save_figure(fig, out / "few_scans.png", dpi=80)
    plt.close(fig)
    return path


# ============================================================================================ main
def run(args, argv: list[str]) -> dict:
    from fppsim.files import atomic_write_text, folder_lock, json_text
    from uhrnet.checkpoint import checkpoint_file
    from uhrnet.data.datasets import load_sources

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for path, what in ((args.real_pair, "--real-pair"), (args.phase_root, "--phase-root")):
        if not Path(path).is_dir():
            raise PipelineError(f"{what} {path}: no such folder")
    with folder_lock(out, "few_scans.py"):
        # (a) the synthetic-only run: reused read-only, or generated + trained here
        if args.syn_run:
            syn_run = Path(args.syn_run)
            if not (syn_run / CONFIG_JSON).is_file() or not any((syn_run / n).is_file() for n in CHECKPOINTS):
                raise PipelineError(f"--syn-run {syn_run}: not a finished uhrnet run (config.json + best.pt)")
            syn_cfg = json.loads((syn_run / CONFIG_JSON).read_text())
            syn_data = args.syn_data or (syn_cfg.get("synthetic") or [None])[0]
            syn_info = {"run": str(syn_run), "reused": True, "epochs": run_epochs(syn_run),
                        "seconds": sum(r.get("seconds") or 0 for r in read_history(syn_run))}
        else:
            syn_data = Path(args.syn_data) if args.syn_data else generate_synthetic(args, out)
            syn_run = out / "runs" / "syn-only"
            syn_info = train_run(out, "syn-only", syn_run, args.pretrain_epochs, synthetic=[str(syn_data)],
                                 model=args.model, base_channels=args.base_channels, loss=args.loss,
                                 batch_size=args.batch_size, lr=args.pretrain_lr, device=args.device,
                                 seed=args.train_seed)
            syn_info["seconds"] = sum(r.get("seconds") or 0 for r in read_history(syn_run))
            syn_cfg = json.loads((syn_run / CONFIG_JSON).read_text())
        if not syn_data or not Path(syn_data).is_dir():
            raise PipelineError(f"synthetic data {syn_data or '(none recorded)'}: no such folder (give --syn-data)")
        syn_data = Path(syn_data)
        syn_info["synthetic"] = str(syn_data)
        syn_ckpt = checkpoint_file(syn_run)

        sources = load_sources(real=[args.real_pair], synthetic=[str(syn_data)], real_split="train",
                               synthetic_split="reference")
        n_real, n_syn = sources.train.n_real, sources.train.n_synthetic
        draws = args.samples_per_epoch or (n_real + n_syn)
        print(f"real pair: {n_real} training sample(s); synthetic: {n_syn} training samples; arms b-d: {draws} "
              f"draws per epoch, batch {syn_cfg.get('batch_size', 2)}")

        heldout_labels, label_doc = label_heldout(args, out, args.rig, "heldout")
        labelled = {"heldout": heldout_labels}
        check = None
        if args.check_rig:
            check_labels, check_doc = label_heldout(args, out, args.check_rig, "heldout_check")
            labelled["heldout_check"] = check_labels
            check = {"rig": check_doc["rig"]["source"], "labels": str(check_labels),
                     "plane_level_mm": check_doc["scans"][0]["plane"]["level_mm"],
                     "object_p99_mm": check_doc["scans"][0]["object"]["p99_mm"]}
        scan = label_doc["scans"][0]
        heldout = {"phase_root": str(args.phase_root), "labels": str(heldout_labels),
                   "rig": label_doc["rig"]["source"], "ids": label_doc["ids"],
                   "phase_offset_rad": scan["phase_offset_rad"], "plane_level_mm": scan["plane"]["level_mm"],
                   "plane_rms_mm": scan["plane"]["rms_mm"], "fits": all(s["fits"] for s in label_doc["scans"]),
                   "problems": [p for s in label_doc["scans"] for p in s["problems"]],
                   "warnings": label_doc["warnings"], "object_p99_mm": scan["object"]["p99_mm"], "check": check}

        arms = []
        for arm in args.arms:
            if arm == "syn-only":
                entry = {"name": arm, "run": str(syn_run), "checkpoint": str(syn_ckpt), "epochs": syn_info["epochs"],
                         "draws": None, "lr": float(syn_cfg.get("lr") or args.pretrain_lr),
                         "seconds": syn_info.get("seconds"), "options": {"synthetic": [str(syn_data)]}}
            else:
                epochs, options = arm_options(args, arm, syn_cfg, syn_ckpt, syn_data, draws)
                run_dir = out / "runs" / arm
                info = train_run(out, arm, run_dir, epochs, **options)
                entry = {"name": arm, "run": str(run_dir), "checkpoint": str(run_dir / LAST_PT), "epochs": epochs,
                         "draws": draws, "lr": options["lr"],
                         "seconds": sum(r.get("seconds") or 0 for r in read_history(run_dir)),
                         "options": {k: v for k, v in options.items() if v is not None}, "reused": info.get("reused")}
            entry["eval"] = str(out / "eval" / arm)
            entry["results"] = evaluate_arm(args, out, arm, Path(entry["checkpoint"]), labelled)
            r = entry["results"]
            print(f"{arm}: phase residual {fmt(r['phase']['rmse_rad'], 3)} rad, held-out object RMSE "
                  f"{fmt(r['heldout']['mean']['object_rmse_mm'])} mm (valid {fmt(r['heldout']['mean']['valid_rmse_mm'])}),"
                  f" pair {fmt(r['pair']['mean']['object_rmse_mm'])} mm" + ("" if arm == "syn-only" else " (trained on)"))
            arms.append(entry)

        doc = {"tool": "pipelines/few_scans.py", "argv": ["python", "pipelines/few_scans.py", *argv],
               "config": {k: v for k, v in vars(args).items()}, "syn_run": syn_info,
               "draws_per_epoch": draws, "batch_size": syn_cfg.get("batch_size", 2),
               "n_train": {"real": n_real, "synthetic": n_syn}, "heldout": heldout, "arms": arms,
               "figure": "few_scans.png"}
        for a in arms:  # the per-image rows are in eval/<arm>/; keep the report short
            for key in (*labelled, "pair"):
                a["results"][key] = {"mean": a["results"][key]["mean"], "images": a["results"][key]["images"],
                                     "file": str(Path(a["eval"]) / key / "real_metrics.json")}
        figure(doc, out, heldout_labels)
        atomic_write_text(out / "report.json", json_text(doc, indent=1, default=str))
        atomic_write_text(out / "report.md", markdown(doc))
    return doc


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_args(argv)
    try:
        run(args, argv)
    except (PipelineError, Sim2RealError) as exc:  # Sim2RealError: a stage failed (uhrnet.workflows.stages)
        print(f"few_scans.py: error: {exc}", file=sys.stderr)
        return 1
    print(f"report: {Path(args.out) / 'report.md'} (also report.json, few_scans.png)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

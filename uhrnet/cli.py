"""`uhrnet` command line: git-style subcommands over the library (the only module that parses flags).

Same design as ``fppsim`` (:func:`fppsim.commands.run_commands`): every command turns its flags into a
config of the library, which validates itself, and calls one plain function a Python user can call:

    train           -> uhrnet.train(TrainConfig)
    evaluate        -> uhrnet.evaluate(checkpoints, EvalData, ...) -> Report
    evaluate-phase  -> uhrnet.scoring.phase_residual.evaluate_phase_folder(PhaseEvalConfig)
    predict         -> uhrnet.predict(PredictConfig)
    bench           -> uhrnet.scoring.bench.bench(BenchConfig)
    export          -> uhrnet.inference.export.export_checkpoint(ExportConfig)
    import-weights  -> uhrnet.inference.reference_weights.import_weights(ImportWeightsConfig)
    sim2real        -> uhrnet.workflows.sim2real.run_sim2real(Sim2RealConfig)

Choices (models, losses, label presets, split modes) are listed from the library's registries. Only
the chosen command's flags are declared (its library module imported), so ``uhrnet --help`` stays fast.
Library errors (:mod:`uhrnet.errors`) and I/O errors print one line and exit 1; usage errors exit 2;
SIGTERM/Ctrl-C exit 128 + signum (``train`` says how to resume).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fppsim.commands import Command, build_command_parser, one_line, run_commands  # noqa: F401 (one_line re-exported)

__all__ = ["main", "build_parser", "COMMANDS", "one_line"]

DEVICES = ("auto", "cpu", "cuda")


# ============================================================================ train
def add_train(p: argparse.ArgumentParser) -> None:
    """train's flags, in the three groups its help shows."""
    # defaults are applied by the library (None = not given), so --resume can tell what the user set
    _add_train_data(p.add_argument_group("data (at least one of --real / --synthetic)"))
    _add_train_model(p.add_argument_group("model and optimisation"))
    _add_train_run(p.add_argument_group("run"))


def _add_train_data(d) -> None:
    """train's data flags: folders, splits, labels, the --val-phase frames, label transform, sizes, loading and
    augmentation."""
    from fppsim.dataio.formats import PRESETS
    from uhrnet.data.augment import AUGMENTS
    from fppsim.dataio.readers import LABEL_SOURCES
    from uhrnet.data.splits import SPLIT_MODES
    from uhrnet.training.train_config import HALVE_FROM_PERIOD_PX, HALVE_FROM_SIDE_PX, VAL_PHASE_FRAMES

    d.add_argument("--real", nargs="+", metavar="DIR", help="figshare-layout folder(s) (f1_80.npy + Z.npy)")
    d.add_argument("--synthetic", nargs="+", metavar="DIR",
                   help="fppsim folder(s): native (manifest.jsonl) or figshare-format exports")
    d.add_argument("--synthetic-ratio", type=float, metavar="R",
                   help="share of synthetic samples per batch in expectation when both kinds are given "
                        "(default: proportional to the dataset sizes)")
    d.add_argument("--real-split", choices=SPLIT_MODES,
                   help="reference = the paper's 80/10/10 split; train/val/test = every real sample in that "
                        "split (e.g. a single sample) [reference]")
    d.add_argument("--synthetic-split", choices=SPLIT_MODES, help="same for synthetic folders [reference]")
    d.add_argument("--synthetic-label", choices=LABEL_SOURCES,
                   help="train on the exact rendered height or the phase-shifting height [true]")
    d.add_argument("--val-phase", nargs="+", metavar="DIR",
                   help="folder(s) of REAL phase-shifting frames of your rig (PSin/ PCos/ Fringe/ iPattern/, the "
                        "public layout; no labels, never trained on): after every epoch, the calibration-free phase "
                        "residual of the predictions as a fraction of the flat prediction's (as uhrnet evaluate-phase "
                        f"reports it), on at most {VAL_PHASE_FRAMES} of their frames; best.pt is then the epoch with the "
                        "lowest, not the best on synthetic validation, which cannot tell which epoch carries over to "
                        "real images (about 1 s per frame and epoch on CPU) [off]")
    d.add_argument("--val-phase-convention", choices=("auto", "benchmark", "fppsim"),
                   help="how the --val-phase frames make their phase: benchmark = atan2(-PSin,-PCos) + pi + 2 pi Order "
                        "(the public data), fppsim = atan2(PSin,PCos) + 2 pi Order, auto = benchmark unless a frame is "
                        "clearly written another way (as evaluate-phase --convention auto) [auto]")
    d.add_argument("--val-phase-negate-sin", action="store_const", const=True,
                   help="the --val-phase frames' PSin holds +sum I_n sin(delta_n)")
    d.add_argument("--preset", choices=sorted(PRESETS), help="label transform preset [figshare]")
    d.add_argument("--label-transform", nargs="+", metavar="KEY=VALUE",
                   help="override preset fields: units_per_mm, invalid_value, invalid_threshold, plane_offset, "
                        "data_range")
    d.add_argument("--crop", metavar="HxW", help="random HxW crop per training sample (centre crop for validation)")
    d.add_argument("--resize", metavar="HxW",
                   help="resize every sample to HxW first (area averaging); predict, evaluate and adapt run the model "
                        "at that size and resample its heights back. 'auto': half the images' size when the "
                        f"synthetic data's fringes are at least {HALVE_FROM_PERIOD_PX:g} px apart (its rig's period at the "
                        f"image centre) and their shorter side is at least {HALVE_FROM_SIDE_PX} px, else full size; the "
                        "size chosen is printed and recorded [full size]")
    d.add_argument("--samples-per-epoch", type=int, metavar="N", help="draws per epoch, at least 1 [all training samples]")
    d.add_argument("--workers", type=int, metavar="N", help="data-loader processes [0 on CPU, 4 on GPU]")
    d.add_argument("--threads", type=int, metavar="N",
                   help="CPU threads torch computes with; a seeded run repeats bit for bit only at the same count "
                        "[torch's default: the cores]")
    d.add_argument("--augment", dest="augment", nargs="?", const="shading", choices=tuple(AUGMENTS),
                   metavar="KIND",
                   help="augmentation of synthetic samples (uhrnet.data.augment; real samples never): 'photometric' "
                        "jitters gain, gamma, contrast, blur and noise; 'shading' adds random smooth fields on "
                        "the fringe background and modulation so that shading cannot stand in for the phase; 'off' [shading]")
    d.add_argument("--no-augment", dest="augment", action="store_const", const="off",
                   help="no augmentation (same as --augment off)")
    d.add_argument("--augment-probability", type=float, metavar="P",
                   help="chance that a synthetic training sample is augmented; the rest are shown as rendered [0.8]")


def _add_train_model(m) -> None:
    """train's model and optimisation flags: architecture, loss, schedule, initialisation, transfer, head."""
    from uhrnet.training.losses import LOSSES, loss_help
    from uhrnet.models import HEADS, list_models
    from uhrnet.training.train_config import LR_FLOOR, LR_SCHEDULES
    from uhrnet.models.init import INITS
    from uhrnet.models.freeze import FREEZE_CHOICES

    m.add_argument("--model", choices=list_models(), help="architecture [uhrnet]")
    m.add_argument("--base-channels", type=int, metavar="N", help="width of the first level [model default]")
    m.add_argument("--model-option", nargs="+", metavar="KEY=VALUE", help="extra model constructor options")
    m.add_argument("--loss", choices=list(LOSSES), help=loss_help("compound"))
    m.add_argument("--epochs", type=int, help="total epochs (the paper: 200) [200]")
    m.add_argument("--batch-size", type=int, help="images per step (per process under torchrun) [1]")
    m.add_argument("--lr", type=float, help="Adam learning rate [1e-4]")
    m.add_argument("--lr-schedule", choices=LR_SCHEDULES,
                   help="learning rate over the run: cosine decays it per step from --lr to "
                        f"{LR_FLOOR:g} x --lr at the last step of --epochs, so the last epoch is the settled one; "
                        "constant keeps --lr [cosine]")
    m.add_argument("--weight-decay", type=float, help="Adam weight decay [0]")
    m.add_argument("--grad-clip", type=float, metavar="NORM", help="clip the gradient norm [off]")
    m.add_argument("--ema", type=float, metavar="DECAY",
                   help="keep an exponential moving average of the weights, updated after every optimizer step "
                        "with this decay (ramped up as min(DECAY, (1+n)/(10+n)) over the first steps); validation, "
                        "best.pt and the checkpoints' weights use the average; e.g. 0.998 (about 500 steps); 0: off [0]")
    m.add_argument("--init", choices=INITS,
                   help="weight initialisation of a fresh run: he draws the convolutions' weights from N(0, 2/fan_in) "
                        "with zero biases, as the U-Net paper (the coarse levels of a network without batch norm then "
                        "start contributing); torch is PyTorch's default, what runs used before this option; auto is "
                        "he for models without batch norm (unet, model_a, hnet) and torch for the others [auto]")
    m.add_argument("--init-from", metavar="CKPT",
                   help="transfer learning: start a new run from the weights of a checkpoint (a .pt file, or a run "
                        "folder: its best.pt, else last.pt, as predict and evaluate read it) instead of --init, with a "
                        "fresh optimizer, learning-rate schedule and epoch count; e.g. pretrain on synthetic data, then "
                        "fine-tune on a few real scans: --init-from SYN_RUN --real DIR --real-split train --synthetic "
                        "DIR --synthetic-ratio 0.5 --lr 1e-4. --model, --base-channels, --model-option and --raw-output "
                        "must match the checkpoint's; of a checkpoint trained with --ema its averaged weights are used. "
                        "Recorded in config.json and the checkpoints (path, sha256, epoch); --resume continues such a "
                        "run without re-initialising it")
    m.add_argument("--freeze", choices=FREEZE_CHOICES,
                   help="with --init-from, keep a part of the initial weights fixed: encoder = the contracting path "
                        "and the bottleneck, decoder = everything after it (up path, fusion blocks, heads); frozen "
                        "weights are left out of the optimizer and their batch norms stay in eval mode (they keep "
                        "the checkpoint's running statistics) [none]")
    m.add_argument("--head", choices=list(HEADS),
                   help="what the network predicts: height (the papers' networks) or phase, the physics head: the "
                        "network predicts the fringe phase (its cosine and sine) and a coarse height, and the calibrated "
                        "rig turns them into height (fringe order from the coarse height, height from the phase through "
                        "the rig's triangulation; one phase origin per image). Needs fppsim native samples (phase_true; "
                        "a figshare export's native/ folder is used) and whole camera images; the checkpoint carries "
                        "the rig, so predict, evaluate, export and bench need nothing more [height]")
    m.add_argument("--rig", metavar="FILE",
                   help="with --head phase: the rig (fppsim JSON/YAML or OpenCV stereo calibration) [the rig in the first "
                        "synthetic sample's meta.json, else fppsim's default rig]")
    m.add_argument("--amp", action="store_const", const=True,
                   help="mixed precision (CUDA: --amp-dtype; CPU: bf16)")
    m.add_argument("--amp-dtype", choices=("auto", "fp16", "bf16"),
                   help="--amp's type on CUDA: bf16 needs no gradient scaler [auto: bf16 where the GPU has it]")
    m.add_argument("--channels-last", choices=("auto", "on", "off"), help="NHWC network and input [auto: on on CUDA]")
    m.add_argument("--device-data", choices=("auto", "on", "off"),
                   help="samples decoded once onto the device and augmented there, no DataLoader [auto: on CUDA "
                        "when they fit in a quarter of its free memory]")
    m.add_argument("--host-sync", choices=("auto", "step", "epoch"),
                   help="when the loss check and metrics reach the host [auto: epoch on CUDA, step on CPU]")
    m.add_argument("--fused-adam", choices=("auto", "on", "off"), help="fused Adam kernel [auto: on on CUDA]")
    m.add_argument("--compile", action="store_const", const=True, help="torch.compile the network [off]")
    m.add_argument("--raw-output", action="store_const", const=True,
                   help="the network outputs raw labels (as the reference code) instead of height/10 mm "
                        "above the plane")
    m.add_argument("--seed", type=int, help="seed of weights, data order, crops and dropout, 0 to 2^32 - 1 [0]")


def _add_train_run(r) -> None:
    """train's run flags: the run folder, resuming or replacing it, device and logging."""
    r.add_argument("--out", required=True, metavar="RUN_DIR", help="run folder (history, checkpoints, plots)")
    r.add_argument("--resume", nargs="?", const="auto", metavar="CKPT",
                   help="continue from RUN_DIR/last.pt (or CKPT) with the same settings")
    r.add_argument("--overwrite", action="store_true",
                   help="start afresh in a RUN_DIR that already holds a run (its best.pt, last.pt, history and "
                        "config are replaced); without it such a folder is refused; not with --resume")
    r.add_argument("--device", choices=DEVICES, help="[auto: cuda when available]")
    r.add_argument("--no-progress", action="store_true", help="no progress bar")
    r.add_argument("--tensorboard", action="store_true",
                   help="also log losses, learning rate, validation RMSE/SSIM and a prediction image per epoch to "
                        "RUN_DIR/tensorboard/ (needs the optional tensorboard package)")


def train_options(args) -> dict:
    """The ``TrainConfig`` fields the ``train`` flags ``args`` give (None: not given)."""
    from dataclasses import fields

    from uhrnet.training.train_config import TrainConfig

    return {f.name: getattr(args, f.name) for f in fields(TrainConfig) if hasattr(args, f.name)}


def run_train(args) -> int:
    from uhrnet.training.trainer import TrainConfig, train

    train(TrainConfig(**train_options(args), progress=not args.no_progress))
    return 0


# ============================================================================ evaluate
def add_evaluate(p: argparse.ArgumentParser) -> None:
    from fppsim.dataio.readers import LABEL_SOURCES
    from uhrnet.data.splits import SPLIT_MODES
    from uhrnet.scoring.evaluation import SPLITS

    p.add_argument("checkpoints", nargs="+", metavar="CKPT", help="checkpoint files or run folders (best.pt)")
    p.add_argument("--real", nargs="*", metavar="DIR",
                   help="real figshare-layout folder(s); bare --real: none [the first checkpoint's]")
    p.add_argument("--synthetic", nargs="*", metavar="DIR",
                   help="fppsim folder(s); bare --synthetic: none [the first checkpoint's]")
    p.add_argument("--out", required=True, metavar="DIR", help="report folder")
    p.add_argument("--split", choices=SPLITS, default="test", help="which split to evaluate [test]")
    p.add_argument("--real-split", choices=SPLIT_MODES, help="how real folders are split [the checkpoint's]")
    p.add_argument("--synthetic-split", choices=SPLIT_MODES, help="how synthetic folders are split [the checkpoint's]")
    p.add_argument("--synthetic-label", choices=LABEL_SOURCES, help="ground truth of native folders [the checkpoint's]")
    p.add_argument("--names", nargs="+", metavar="NAME", help="model names in the table (one per checkpoint)")
    p.add_argument("--crop", metavar="HxW", help="evaluate the centre HxW pixels of every image [the whole image]")
    p.add_argument("--limit", type=int, metavar="N", help="evaluate only the first N images of the split")
    p.add_argument("--figures", type=int, default=3, metavar="N", help="comparison figures for N evenly spaced images [3]")
    p.add_argument("--samples", nargs="+", metavar="ID", help="figures for these sample ids (or split positions #K)")
    p.add_argument("--row", type=int, help="cross-section row [the row crossing most object pixels]")
    p.add_argument("--batch-size", type=int, default=1, metavar="N",
                   help="images per forward pass while scoring (the timing is at batch 1 whatever this is) [1]")
    p.add_argument("--device", choices=DEVICES, default="auto", help="where the models run [auto: cuda when available]")
    p.add_argument("--timing-repeats", type=int, default=5, metavar="N",
                   help="timed forward passes per model at batch 1 (0: skip timing) [5]")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run_evaluate(args) -> int:
    from uhrnet.scoring.evaluation import EvalData, evaluate

    data = EvalData(real=args.real, synthetic=args.synthetic, split=args.split, real_split=args.real_split,
                    synthetic_split=args.synthetic_split, synthetic_label=args.synthetic_label, crop=args.crop,
                    limit=args.limit)
    report = evaluate(args.checkpoints, data, out=args.out, names=args.names, figures=args.figures,
                      samples=args.samples, row=args.row, batch_size=args.batch_size, device=args.device,
                      timing_repeats=args.timing_repeats, progress=not args.no_progress)
    out = Path(args.out)
    print(report.table, end="")
    print(f"report: {out / 'results.md'} (also results.csv, results.json, per_sample.csv)")
    if report.figures:
        print(f"figures: {out / 'figures'} ({len(report.figures)} image{'s' if len(report.figures) > 1 else ''})")
    return 0


# ============================================================================ predict
def add_predict(p: argparse.ArgumentParser) -> None:
    from uhrnet.physics.refine import REFINE_METHODS

    p.add_argument("checkpoint", metavar="CKPT", help="checkpoint file or run folder (best.pt)")
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="fringe images, .npy arrays, or folders of them; figshare folders (their fringes only) and "
                        "phase-shifting folders (PSin/ PCos/ Fringe/ iPattern/: their iPattern images)")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output folder: per image NAME_height.npy/.tif (float32 height above the reference plane in "
                        "mm, NaN where invalid), NAME_height.png (colour preview) and NAME.ply (points in mm)")
    p.add_argument("--rig", metavar="FILE", help="rig calibration (fppsim JSON/YAML or OpenCV stereo YAML) for "
                                                 "metric x, y in the point cloud and, by default (--refine auto), "
                                                 "heights from the image's own fringe phase through it "
                                                 "[--refine phase without it: the checkpoint's rig, else fppsim's "
                                                 "default rig]")
    p.add_argument("--refine", choices=("auto", "phase", "none"), default="auto",
                   help="phase: move the heights to agree with the image's own fringe phase (single-shot phase, "
                        "rad) through the rig; writes NAME_height_network.npy (the network's map) and refine.json "
                        "(per image: pixels moved; per phase region: order, confidence, decided); auto: phase when "
                        "--rig is given (an image without readable fringes then keeps the network's heights, with a "
                        "warning); none: the network's heights [auto]")
    p.add_argument("--refine-method", choices=REFINE_METHODS, default="orders",
                   help="orders: every region of continuous phase at one whole fringe order, chosen for the image at "
                        "once from the network's level, projector-shadow bridges and seams of unreliable phase; "
                        "level and relief from the phase through the rig (exact as far as the rig's depth scale is); "
                        "a region it cannot decide keeps the network's heights and is named in a warning; relief: "
                        "each region's relief from the phase, its level from the network [orders]")
    p.add_argument("--pixel-size", type=float, default=1.0, metavar="MM",
                   help="x, y spacing of the point cloud without --rig [1.0]")
    p.add_argument("--keep-all", action="store_true", help="keep every pixel (no invalid masking)")
    p.add_argument("--range", nargs=2, type=float, metavar=("LO", "HI"),
                   help="colour range of the PNG in mm [1st-99th percentile]")
    p.add_argument("--colormap", default="viridis", help="matplotlib colour map of the PNG [viridis]")
    p.add_argument("--no-ply", action="store_true", help="skip the point clouds")
    p.add_argument("--device", choices=DEVICES, default="auto", help="where the model runs [auto: cuda when available]")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run_predict(args) -> int:
    from uhrnet.inference.prediction import PredictConfig, predict

    config = PredictConfig(checkpoint=args.checkpoint, inputs=list(args.inputs), out=args.out, rig=args.rig,
                           pixel_size=args.pixel_size, keep_all=args.keep_all,
                           range=tuple(args.range) if args.range is not None else None, colormap=args.colormap,
                           ply=not args.no_ply, device=args.device, progress=not args.no_progress,
                           refine=None if args.refine == "none" else args.refine, refine_method=args.refine_method)
    if args.refine_method != "orders" and (args.refine == "none" or (args.refine == "auto" and not args.rig)):
        print("uhrnet predict: warning: --refine-method has no effect without --refine phase or --rig", file=sys.stderr)
    result = predict(config)
    for line in result.warnings:
        print(f"uhrnet predict: warning: {line}", file=sys.stderr)
    for name, st in result.refine.items():
        print(refine_line(name, st))
    print(f"predict: {len(result.names)} height map(s) from {len(result.files)} input file(s) -> {args.out} "
          f"(NAME_height.npy/.tif in mm, NAME_height.png{'' if args.no_ply else ', NAME.ply'}"
          f"{', x/y from rig ' + str(args.rig) if args.rig else ''})")
    return 0


def refine_line(name: str, st: dict) -> str:
    """predict's one line on the refinement of image ``name`` from its refine.json entry ``st``."""
    links = st.get("links") or {}
    taken = ", ".join(f"{n} {what}{'s' if n != 1 else ''}" for what, n in
                      (("shadow bridge", links.get("bridge", 0)), ("seam", links.get("seam", 0)),
                       ("wall link", links.get("wall", 0))) if n)
    regions = (f", {st['regions']} phase regions in {st['components']} linked groups, {st['undecided_regions']} undecided"
               + (f" (links taken: {taken})" if taken else "")
               + (f", {st['floating_regions']} floating (tied to no piece of the plane: the network's level alone,"
                  f" {st['floating_fraction']:.2%} of the pixels)" if st.get("floating_regions") else "")
               + (f", {st['refused_links']} links refused by the network's levels" if st["refused_links"] else "")
               + (f", {st['beyond_margin_moved']} px beyond the move margin moved with their neighbours"
                  if st.get("beyond_margin_moved") else "")
               + (f", rims: {st['rim_to_object']} px to the objects ({st.get('rim_lowered', 0)} a fall read as a"
                  f" rise, one order lower) and {st['rim_to_plane']} to the plane" if st.get("rim_runs") else "")
               if st["method"] == "orders" else "")
    return (f"refine {name}: {st['moved_fraction']:.1%} of the pixels moved ({st['method']}, mean move "
            f"{st['mean_abs_move_mm']:.2f} mm, phase origin {st['offset_rad']:+.2f} rad{regions}, {st['rig']})")


# ============================================================================ bench
def add_bench(parser: argparse.ArgumentParser) -> None:
    from uhrnet.scoring.bench import DEFAULT_MODELS, OPT_VARIANTS

    parser.add_argument("--models", nargs="+", default=list(DEFAULT_MODELS), metavar="NAME",
                        help=f"models to measure (any name of uhrnet.models.list_models(); default: "
                             f"{' '.join(DEFAULT_MODELS)})")
    parser.add_argument("--height", type=int, default=352,
                        help="input height in pixels, a multiple of 16 from 16 to 4096 (default 352)")
    parser.add_argument("--width", type=int, default=640,
                        help="input width in pixels, a multiple of 16 from 16 to 4096 (default 640)")
    parser.add_argument("--batch-size", type=int, default=1, help="batch size (default 1, as in the paper)")
    parser.add_argument("--device", default="auto", choices=DEVICES, help="default: cuda if available")
    parser.add_argument("--repeats", type=int, default=10, help="timed repetitions; the median is reported (default 10)")
    parser.add_argument("--warmup", type=int, default=3, help="untimed warm-up repetitions (default 3)")
    parser.add_argument("--amp", choices=["off", "fp16", "bf16"], default="off",
                        help="forward and training step under torch.autocast with this dtype (default off)")
    parser.add_argument("--channels-last", action="store_true", help="use the channels_last memory format")
    parser.add_argument("--compile", action="store_true",
                        help="wrap each model in torch.compile (compiles during warm-up, so at least 2 warm-up "
                             "calls are made)")
    parser.add_argument("--base-channels", type=int, default=None, metavar="B",
                        help="width override: uhrnet and unet get base B, the half-width models (model_a, hnet) B/2 "
                             "(for quick runs; parameter counts then differ from the paper)")
    parser.add_argument("--no-train", action="store_true", help="skip the training-step measurement")
    parser.add_argument("--optimize", action="store_true",
                        help="also time each model in its deployable forms (see --variants; every form is checked to "
                             "give the eager model's output within 1e-4 x its range) and report the fastest torch "
                             "form as forward ms; the UHRNet / U-Net ratio (JSON uhrnet_unet_forward_ratio) is then "
                             "that of each model in its fastest form of all, re-timed in --repeats alternating pairs")
    parser.add_argument("--variants", nargs="+", default=None, choices=list(OPT_VARIANTS), metavar="V",
                        help="forms tried by --optimize (only with --optimize): fold (batch norms folded, "
                             "inference_mode), fold_cl (+ channels_last), compile (fold_cl + torch.compile), onnxruntime and "
                             "openvino (the ONNX export of fold under each runtime, float32; columns of their own) "
                             f"(default: {' '.join(OPT_VARIANTS)})")
    parser.add_argument("--json", type=Path, default=None, metavar="OUT",
                        help="also write the results as JSON to OUT (an existing OUT is replaced only when it is a "
                             "report bench wrote)")


def run_bench(args) -> int:
    from uhrnet.errors import UsageError
    from uhrnet.scoring.bench import OPT_VARIANTS, BenchConfig, bench

    if args.variants is not None and not args.optimize:
        raise UsageError("--variants chooses the forms --optimize times: give --optimize too, or leave --variants out")

    config = BenchConfig(models=list(args.models), height=args.height, width=args.width, batch_size=args.batch_size,
                         device=args.device, repeats=args.repeats, warmup=args.warmup,
                         amp=args.amp, channels_last=args.channels_last, compile=args.compile,
                         base_channels=args.base_channels, train=not args.no_train, optimize=args.optimize,
                         variants=list(args.variants or OPT_VARIANTS), json=args.json)
    bench(config, echo=lambda line: print(line, flush=True))
    return 0


# ============================================================================ evaluate-phase
def add_evaluate_phase(p: argparse.ArgumentParser) -> None:
    from fppsim.dataio.readers import READ_CONVENTIONS
    from uhrnet.physics.refine import REFINE_METHODS

    p.add_argument("checkpoints", nargs="+", metavar="CKPT", help="checkpoint files or run folders (best.pt)")
    p.add_argument("--phase-root", required=True, metavar="DIR",
                   help="folder with PSin/, PCos/, Fringe/ (variable Order), iPattern/ sub-folders of <id>.mat")
    p.add_argument("--out", required=True, metavar="DIR", help="report folder")
    p.add_argument("--degree", type=int, default=3, help="total degree of the reference-plane polynomial in x, y [3]")
    p.add_argument("--robust", action="store_true", help="Huber IRLS instead of plain least squares")
    p.add_argument("--convention", choices=READ_CONVENTIONS, default="auto",
                   help="benchmark: phase = atan2(-PSin,-PCos) + pi + 2 pi Order (the public data); fppsim: "
                        "atan2(PSin, PCos) + 2 pi Order; auto: benchmark unless a frame's phase is clearly written "
                        "another way (it then jumps by pi every period or half period: read the smooth way, and "
                        "said) [auto]")
    p.add_argument("--negate-sin", action="store_true", help="the files store PSin with the opposite sign")
    p.add_argument("--mask-predicted-invalid", action="store_true",
                   help="leave out pixels the model labels invalid (default: keep them: real phase exists there, so "
                        "a predicted shadow is a prediction error)")
    p.add_argument("--names", nargs="+", metavar="NAME", help="model names (one per checkpoint)")
    p.add_argument("--ids", nargs="+", metavar="ID", help="evaluate only these ids [all]")
    p.add_argument("--limit", type=int, metavar="N", help="evaluate only the first N ids")
    p.add_argument("--figures", type=int, default=3, metavar="N", help="residual-map figures for the first N ids [3]")
    p.add_argument("--refine", choices=("none", "phase"), default="none",
                   help="phase: also score each model's heights after the image's own phase (as uhrnet predict "
                        "--refine phase), one more row per model on the same pixels [none]")
    p.add_argument("--refine-method", choices=REFINE_METHODS, default="orders",
                   help="how --refine sets each phase region's level (as uhrnet predict) [orders]")
    p.add_argument("--rig", metavar="FILE",
                   help="rig calibration --refine works through [the checkpoint's rig, else fppsim's default rig]")
    p.add_argument("--device", choices=DEVICES, default="auto", help="where the models run [auto: cuda when available]")


def run_evaluate_phase(args) -> int:
    from uhrnet.scoring.phase_residual import PhaseEvalConfig, evaluate_phase_folder

    config = PhaseEvalConfig(checkpoints=list(args.checkpoints), phase_root=args.phase_root, out=args.out,
                             degree=args.degree, robust=args.robust, convention=args.convention,
                             negate_sin=args.negate_sin, mask_predicted_invalid=args.mask_predicted_invalid,
                             names=args.names, ids=args.ids, limit=args.limit, figures=args.figures,
                             device=args.device, refine=None if args.refine == "none" else args.refine,
                             refine_method=args.refine_method, rig=args.rig)
    if args.refine == "none" and (args.rig or args.refine_method != "orders"):
        from uhrnet.errors import UsageError  # noqa: PLC0415 (as the other commands)
        raise UsageError("--rig and --refine-method are used only with --refine phase")
    result = evaluate_phase_folder(config, echo=print)
    out = Path(args.out)
    print(result["markdown"], end="")
    print(f"report: {out / 'phase_results.md'} (also phase_results.json)")
    if result["figures"]:
        n = len(result["figures"])
        print(f"figures: {out / 'figures'} ({n} residual map{'s' if n > 1 else ''})")
    return 0


# ============================================================================ export
def add_export(parser: argparse.ArgumentParser) -> None:
    from uhrnet.inference.export import CHECK_RTOL, DEFAULT_OPSET, EXPORT_FORMATS, OPSET_RANGE, RUNTIMES

    parser.description = (
        "Export a checkpoint's model (batch norms folded: the same function) as ONNX or "
        "TorchScript. Input 'fringe' (N, C, H, W) float32 in [-1, 1]; output 'label' (N, 1, H, W) in label units. "
        f"--check runs the export (ONNX: under --runtime; TorchScript: torch.jit.load) and the checkpoint's model on a seeded input "
        f"(uniform in [-1, 1], seed 0) and fails (exit 1) unless max |difference| <= {CHECK_RTOL:g} x the range "
        "(max - min) of the checkpoint model's output; the export is checked under a temporary name and only a "
        "passing one replaces --out. --out may not be a uhrnet checkpoint. "
        "--format reference writes {'state_dict': ...} for the authors' reference code (fead1/UHRNet: "
        "UHRNet().load_state_dict(strict=True)): only UHRNet at base width 64, height head, 1 in / 1 out channel; "
        "the network then outputs figshare labels (Z; Z / 6 = mm); --check reads the file back and compares."
    )
    parser.add_argument("checkpoint", type=Path, help="checkpoint file or run folder (best.pt, else last.pt)")
    parser.add_argument("--format", choices=EXPORT_FORMATS, default="onnx",
                        help="onnx, torchscript, or reference (the reference code's weights file) (default: onnx)")
    parser.add_argument("--out", type=Path, required=True,
                        help="output file: onnx x.onnx, torchscript x.pt / .ts, reference x.pth (a suffix of another "
                             "format is refused)")
    parser.add_argument("--check", action="store_true", help="verify the export against the checkpoint (see above)")
    parser.add_argument("--runtime", choices=RUNTIMES, default="onnxruntime",
                        help="what runs the ONNX file for --check: onnxruntime (default) or openvino (its CPU "
                             "plugin in float32, the fastest CPU form measured here; pip install openvino); "
                             "only with --format onnx")
    parser.add_argument("--opset", type=int, default=DEFAULT_OPSET,
                        help=f"ONNX opset, {OPSET_RANGE[0]}-{OPSET_RANGE[1]} (default {DEFAULT_OPSET})")
    parser.add_argument("--height", type=int, default=352, help="export/check input height, multiple of 16 (default 352)")
    parser.add_argument("--width", type=int, default=640, help="export/check input width, multiple of 16 (default 640)")
    parser.add_argument("--dynamic", action="store_true",
                        help="ONNX: free batch, height and width axes (only with --format onnx)")
    parser.add_argument("--no-optimize", action="store_true", help="export the model as trained (batch norms not folded)")


def run_export(args) -> int:
    from uhrnet.inference.export import ExportConfig, export_checkpoint

    config = ExportConfig(checkpoint=args.checkpoint, out=args.out, format=args.format, height=args.height,
                          width=args.width, opset=args.opset, dynamic=args.dynamic, check=args.check,
                          optimize=not args.no_optimize, runtime=args.runtime)
    summary = export_checkpoint(config)
    shape = f"{summary['entries']} entries" if "entries" in summary else f"input {summary['input_shape']}"
    print(f"wrote {summary['path']} ({summary['format']}, {summary['model']}, {shape})")
    if summary["check"] is not None:
        r = summary["check"]
        where = f" ({summary['runtime']})" if summary.get("runtime") else ""
        print(f"check passed{where}: max |exported - checkpoint| = {r['max_abs_diff']:.3g} <= {r['tolerance']:.3g}")
    return 0


# ============================================================================ import-weights
def add_import_weights(parser: argparse.ArgumentParser) -> None:
    from fppsim.dataio.formats import PRESETS
    from uhrnet.inference.reference_weights import IMPORT_FORMATS, PLANE_OFFSET_RANGE, REFERENCE_FORMAT

    PLANE, (lo, hi) = PRESETS["figshare"].plane_offset, PLANE_OFFSET_RANGE

    parser.description = (
        "Turn published weights into a uhrnet run folder (best.pt = last.pt, config.json) that predict, "
        "evaluate, evaluate-phase, adapt and export read. --format reference: the authors' reference code "
        "(fead1/UHRNet, UHRNet_weight.pth): a state dict, bare or under 'state_dict' (a DataParallel 'module.' "
        "prefix is dropped), every key and shape checked; the model is uhrnet (base 64, fusion blocks), its "
        "output figshare labels (figshare label preset, mm = (Z - plane offset) / 6: by default heights above "
        "the reference plane, (Z + 97) / 6, as every uhrnet run; --plane-offset 0 gives the reference evaluation's "
        "plain Z / 6). Fine-tune it with train --init-from RUN --raw-output. Files in --out that another tool or "
        "a person wrote are never replaced."
    )
    parser.add_argument("source", type=Path, metavar="FILE", help="weights file (e.g. UHRNet_weight.pth)")
    parser.add_argument("--out", type=Path, required=True, metavar="RUN", help="run folder to write")
    parser.add_argument("--format", choices=IMPORT_FORMATS, default=REFERENCE_FORMAT,
                        help=f"layout of FILE (default: {REFERENCE_FORMAT})")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace weights an earlier import-weights wrote to --out (never another tool's run)")
    parser.add_argument("--plane-offset", type=float, default=PLANE, metavar="LABEL",
                        help=f"figshare label of height 0, in ({lo:g}, {hi:g}]: {PLANE:g} gives heights in mm above "
                             "the reference plane like the rest of uhrnet (what adapt, refine, point clouds and "
                             "fine-tuning expect); 0 gives Z / 6 exactly as the reference code's evaluation "
                             f"(default: {PLANE:g})")


def run_import_weights(args) -> int:
    from uhrnet.inference.reference_weights import ImportWeightsConfig, import_weights

    result = import_weights(ImportWeightsConfig(source=args.source, out=args.out, format=args.format,
                                                overwrite=args.overwrite, plane_offset=args.plane_offset))
    print(f"import-weights: {result['entries']} entries, {result['parameters']:,} parameters from "
          f"{result['source']} (sha256 {result['sha256'][:12]}) -> {result['checkpoint']} (uhrnet, figshare labels)")
    return 0


# ============================================================================ sim2real
def variant_commands() -> dict:
    """How ``--variant`` flags are read (:func:`uhrnet.workflows.sim2real.variants.variant_from_flags`): each
    command's own parser and the config fields its flags give."""
    from fppsim.cli import build_parser as fppsim_parser
    from fppsim.cli import generate_options
    from uhrnet.workflows.sim2real.variants import FlagReader

    return {"generate": FlagReader(fppsim_parser, generate_options),
            "train": FlagReader(lambda: build_parser("train"), train_options),
            "adapt": FlagReader(lambda: build_parser("adapt"), adapt_options)}


def adapt_options(args) -> dict:
    """The ``AdaptConfig`` fields the ``adapt`` flags ``args`` give (not the checkpoint, images and folder)."""
    from dataclasses import fields

    from uhrnet.training.adapt import AdaptConfig

    out = {f.name: getattr(args, f.name) for f in fields(AdaptConfig)
           if hasattr(args, f.name) and f.name not in ("checkpoint", "images", "out")}
    return {**out, "figures": not args.no_figures, "progress": not args.no_progress}


def add_sim2real(p: argparse.ArgumentParser) -> None:
    from uhrnet.training.losses import LOSSES, loss_help
    from uhrnet.models import list_models
    from uhrnet.physics.refine import REFINE_METHODS
    from uhrnet.workflows.sim2real import SCALES
    from uhrnet.workflows.sim2real.variants import VARIANT_SYNTAX

    def scales(key):
        return ", ".join(f"{s}: {'the model default' if v[key] is None else v[key]}" for s, v in SCALES.items())

    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.description = (
        "Sim-to-real experiment: fppsim generate -> uhrnet train on the synthetic data alone -> evaluate on REAL\n"
        "data -> OUT/report.md and OUT/report.json. --scale cpu is the judged recipe (400 samples, seed 100,\n"
        "U-Net base 16, compound loss, 10 epochs, batch 2, lr 5e-4, CPU; under 60 minutes on 2 cores); --scale\n"
        "gpu is UHRNet at 352 x 640 on 2000 samples (--amp). Each --variant adds a row to the ablation table;\n"
        "variants with the same generate flags share one dataset (OUT/data/<key>). Re-running the same\n"
        "command re-uses finished datasets, runs and evaluations. Per variant: OUT/<name>/run (the training\n"
        "run), OUT/<name>/eval (real_metrics.json, predictions.npz, real_*.png, synthetic_level.json), logs\n"
        "OUT/data/<key>.log and OUT/<name>/train.log.\n\n"
        f"Variants: --variant SPEC, SPEC =\n  {VARIANT_SYNTAX}\nwith the flags of fppsim generate, "
        "uhrnet train and uhrnet adapt; the steps add rows without training again:\n"
        "  --variant 'phase-head: | --head phase'            the physics head (one more training run)\n"
        "  --variant 'default: | | adapt'                    + the model adapted on the UNLABELLED real images\n"
        "  --variant 'ph: | --head phase | adapt --epochs 20 | refine relief,orders'\n"
        "gives the rows ph, ph +refine relief, ph +refine orders, ph +adapt, ph +adapt +refine relief, ...\n"
        "adapt: uhrnet adapt of the run's last.pt on --adapt-images (default: the --real and --real-phase\n"
        "folders; only their fringe images are read, never a label) -> OUT/<name>/adapt (adapt.log); refine:\n"
        "the predictions after uhrnet predict --refine phase --refine-method METHOD through --rig.\n"
        "Rows are evaluated in OUT/<name>/eval, eval-refine-<m>, eval-adapt, eval-adapt-refine-<m>.\n\n"
        "Re-using runs: --reuse-run NAME=RUN_DIR takes a finished uhrnet train folder (last.pt at --epochs)\n"
        "as variant NAME's training run, read in place (nothing is written there): its config.json must hold\n"
        "the variant's training options (everything a resume locks, epochs, lr; not the data path or\n"
        "device) and its dataset --count samples of --seed; that dataset is then the variant's. A run folder\n"
        "copied to OUT/<name>/run is taken the same way (one of other options is refused).\n\n"
        "Real data: figshare-format folders (f1_80.npy + Z.npy, or fringe_pattern.npy + height_map.npy);\n"
        "labels <= -100 are invalid and mm = label / 6. Metrics in mm: object RMSE over valid pixels more\n"
        "than --object-mm above the reference plane, median |error|, share within 1 mm, coverage (share of\n"
        "object pixels predicted valid), RMSE over all valid pixels, and more (see uhrnet.workflows.sim2real.real_metrics).\n"
        "--real-phase: real phase-shifting folders (PSin/ PCos/ Fringe/ iPattern/, no labels): the\n"
        "calibration-free phase residual (rad) of every row on every frame, as uhrnet evaluate-phase reports.")
    p.add_argument("--scale", choices=sorted(SCALES), default="cpu", help="recipe size [cpu]")
    p.add_argument("--real", nargs="+", required=True, metavar="DIR",
                   help="real figshare-format folder(s); evaluation only, never trained on")
    p.add_argument("--out", required=True, metavar="DIR", help="experiment folder (re-running resumes it)")
    p.add_argument("--meshes", nargs="+", metavar="PATH",
                   help="meshes of the synthetic scenes (files or folders) [the meshes fppsim ships, assets/meshes]")
    for name, typ, what in (("count", int, "synthetic samples"), ("seed", int, "generator seed"),
                            ("workers", int, "generator processes, 0: all cores"), ("epochs", int, "training epochs"),
                            ("batch-size", int, "images per training step"), ("lr", float, "Adam learning rate"),
                            ("base-channels", int, "model width (channels of the first level)")):
        key = name.replace("-", "_")
        p.add_argument(f"--{name}", type=typ, metavar="N" if typ is int else "X",
                       help=f"{what} [{scales(key)}]")
    p.add_argument("--model", choices=list_models(), help=f"architecture [{scales('model')}]")
    p.add_argument("--loss", choices=list(LOSSES), help=loss_help(scales("loss")))
    p.add_argument("--device", choices=DEVICES, help=f"training device; evaluation runs on cuda if this is cuda, else on cpu [{scales('device')}]")
    p.add_argument("--variant", action="append", default=[], metavar="SPEC",
                   help=f"{VARIANT_SYNTAX} (flags of fppsim generate / uhrnet train / uhrnet adapt; "
                        f"refine methods: {', '.join(REFINE_METHODS)}; see above; repeatable) [one variant "
                        "'default', the recipe]")
    p.add_argument("--ablation", metavar="FILE",
                   help="YAML/JSON list of variants {name, generate, train, adapt (flags, or true), refine}")
    p.add_argument("--real-phase", nargs="+", default=[], metavar="DIR",
                   help="real phase-shifting folder(s) (PSin/ PCos/ Fringe/ iPattern/, no labels): phase residual "
                        "of every row per frame; adaptation images too; evaluation only, never trained on")
    p.add_argument("--rig", metavar="FILE",
                   help="the real data's rig for refine and adapt [the checkpoint's rig, else fppsim's default]")
    p.add_argument("--adapt-images", nargs="+", metavar="PATH",
                   help="unlabelled images the adapt steps fine-tune on [the --real and --real-phase folders]")
    p.add_argument("--reuse-run", action="append", default=[], metavar="NAME=RUN_DIR",
                   help="use this finished training run as variant NAME's (see above; repeatable)")
    p.add_argument("--object-mm", type=float, default=1.0, metavar="MM",
                   help="object pixels: valid and more than this many mm above the plane [1]")
    p.add_argument("--no-figures", action="store_true", help="skip the per-image figures")


def parse_reuse(items: list[str]) -> dict[str, str]:
    """``--reuse-run NAME=RUN_DIR`` items as ``{NAME: RUN_DIR}``."""
    from uhrnet.errors import UsageError

    out = {}
    for item in items:
        name, sep, run = item.partition("=")
        if not sep or not name.strip() or not run.strip() or name.strip() in out:
            raise UsageError(f"--reuse-run expects NAME=RUN_DIR once per variant, got {item!r}")
        out[name.strip()] = run.strip()
    return out


def _variant_of(cfg, spec, commands, file):
    """``variant_from_flags``; a flag error of an ``--ablation`` file's entry names the file, exit 1 as the file's other
    errors (on the command line, exit 2)."""
    from uhrnet.errors import Sim2RealError, UsageError
    from uhrnet.workflows.sim2real.variants import variant_from_flags

    try:
        return variant_from_flags(cfg, spec, commands)
    except (UsageError, Sim2RealError) as exc:
        if file is None:
            raise
        raise Sim2RealError(f"{file}: {exc}") from None


def run_sim2real(args) -> int:
    from dataclasses import replace

    from uhrnet.workflows.sim2real import Sim2RealConfig, markdown_report, run_sim2real
    from uhrnet.workflows.sim2real.variants import load_variants, parse_variant, recipe_commands

    specs = [(parse_variant(v), None) for v in args.variant]
    if args.ablation:
        specs += [(s, args.ablation) for s in load_variants(args.ablation)]
    cfg = Sim2RealConfig(
        out=args.out, real=args.real, **({"meshes": list(args.meshes)} if args.meshes else {}), scale=args.scale,
        count=args.count, seed=args.seed, workers=args.workers, model=args.model, base_channels=args.base_channels,
        loss=args.loss, epochs=args.epochs, batch_size=args.batch_size, lr=args.lr, device=args.device,
        object_mm=args.object_mm, figures=not args.no_figures, real_phase=list(args.real_phase), rig=args.rig,
        adapt_images=args.adapt_images)
    reuse = parse_reuse(args.reuse_run)  # names the variants: checked once they are known
    commands = variant_commands()
    cfg = replace(cfg, variants=[_variant_of(cfg, s, commands, f) for s, f in specs] if specs else cfg.variants,
                  reuse=reuse)
    report = run_sim2real(cfg, log=lambda line: print(line, flush=True), recipe=recipe_commands)
    print(markdown_report(report))
    print(f"report: {Path(args.out) / 'report.md'} and report.json")
    return 0


# ============================================================================ adapt
def add_adapt(p: argparse.ArgumentParser) -> None:
    from uhrnet.training.adapt import AdaptConfig

    d = AdaptConfig.__dataclass_fields__
    p.add_argument("checkpoint", metavar="RUN", help="the model to adapt: a run folder (best.pt, else last.pt) or a .pt")
    p.add_argument("--images", nargs="+", required=True, metavar="PATH",
                   help="UNLABELLED real fringe images: image/.npy files or folders as predict takes them, figshare "
                        "folders (fringes only; labels are never read) and phase-shifting folders (iPattern images)")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="the adaptation's run folder: last.pt (predict/evaluate accept it), history.csv, config.json, "
                        "images.json, figures/<image>_adapt.png; re-running resumes it")
    p.add_argument("--rig", metavar="FILE",
                   help="rig (fppsim JSON/YAML or OpenCV stereo YAML) [the checkpoint's rig, else fppsim's default]")
    p.add_argument("--epochs", type=int, default=d["epochs"].default,
                   help=f"passes over the images, one image per step [{d['epochs'].default}; about 1 s a step for the "
                        "recipe's U-Net on 2 CPU cores]")
    p.add_argument("--lr", type=float, default=d["lr"].default, help=f"Adam learning rate [{d['lr'].default:g}]")
    for name, what in (("w_grad", "weight of the fringe-gradient consistency (phase steps between neighbours, rad)"),
                       ("w_drift", "weight of the anchor to the source model's prediction (mean |change| / 10 mm)"),
                       ("max_step", "phase-step disagreements above this (rad, > 0) are ignored: aliasing walls, "
                                    "shadow edges"),
                       ("min_reliability", "pixels whose single-shot phase reliability (0 to 1) is below this (in "
                                           "[0, 1)) count in no phase term")):
        p.add_argument("--" + name.replace("_", "-"), type=float, default=d[name].default,
                       help=f"{what} [{d[name].default:g}]")
    p.add_argument("--seed", type=int, default=0, help="order of the images [0]")
    p.add_argument("--overwrite", action="store_true", help="replace an adaptation already in --out")
    p.add_argument("--no-figures", action="store_true", help="skip the before/after figures")
    p.add_argument("--device", choices=DEVICES, default="auto", help="[auto: cuda when available, as train]")
    p.add_argument("--no-progress", action="store_true", help="one line per epoch instead of a progress bar")
    p.add_argument("--tensorboard", action="store_true",
                   help="also log the loss and its terms, the learning rate and the first image's height per epoch "
                        "to DIR/tensorboard/ (needs the optional tensorboard package)")


def run_adapt(args) -> int:
    from uhrnet.run_folder import HISTORY_CSV, LAST_PT  # the command's modules load when it runs
    from uhrnet.training.adapt import AdaptConfig, adapt

    cfg = AdaptConfig(checkpoint=args.checkpoint, images=list(args.images), out=args.out, rig=args.rig,
                      epochs=args.epochs, lr=args.lr, w_grad=args.w_grad, w_drift=args.w_drift,
                      max_step=args.max_step, min_reliability=args.min_reliability, device=args.device, seed=args.seed,
                      overwrite=args.overwrite, figures=not args.no_figures, progress=not args.no_progress,
                      tensorboard=args.tensorboard)
    result = adapt(cfg, log=lambda line: print(line, flush=True))
    for im in result.images:
        print(f"adapt {im['name']}: median phase residual {im['before_rad']:.3f} -> {im['after_rad']:.3f} rad, "
              f"mean change {im['mean_change_mm']:.2f} mm")
    print(f"adapt: {result.out / LAST_PT} after {result.epochs} epoch(s); history {result.out / HISTORY_CSV}")
    return 0


# ============================================================================ main
COMMANDS: dict[str, Command] = {
    "train": Command(add_train, run_train, "train a model on real (figshare) and/or synthetic (fppsim) data"),
    "evaluate": Command(add_evaluate, run_evaluate,
                        "evaluate checkpoints on the test split like the paper (Table 3, figures)"),
    "evaluate-phase": Command(add_evaluate_phase, run_evaluate_phase,
                              "evaluate checkpoints on real phase-shifting data without height labels "
                              "(PSin/PCos/Fringe/iPattern folders): calibration-free phase residual"),
    "predict": Command(add_predict, run_predict, "predict height maps and point clouds from fringe images"),
    "adapt": Command(add_adapt, run_adapt,
                     "fine-tune a model on unlabelled real fringe images through the rig (fringe consistency)"),
    "bench": Command(add_bench, run_bench, "parameters, forward/training-step time and peak memory per model"),
    "export": Command(add_export, run_export,
                      "export a checkpoint as ONNX or TorchScript (batch norms folded), or as the reference "
                      "code's weights (--format reference), with --check"),
    "import-weights": Command(add_import_weights, run_import_weights,
                              "make a run folder from the reference code's UHRNet weights (UHRNet_weight.pth)"),
    "sim2real": Command(add_sim2real, run_sim2real,
                        "sim-to-real experiment: generate synthetic data, train on it alone, evaluate on real data"),
}


def build_parser(load: str | None = None) -> argparse.ArgumentParser:
    """The parser; with ``load`` only that command's flags are declared (the others: name and help)."""
    return build_command_parser(
        "uhrnet", "UHRNet and baselines for single-shot fringe projection profilometry. "
        "Heights are in label units in datasets and in millimetres in reports and predict's maps.", COMMANDS,
        load=load)


def main(argv: list[str] | None = None) -> int:
    from fppsim.errors import FppsimError
    from fppsim.errors import UsageError as FppsimUsageError
    from uhrnet.errors import DataError, UhrnetError, UsageError

    argv = sys.argv[1:] if argv is None else list(argv)
    chosen = next((a for a in argv if not a.startswith("-")), None)
    if chosen not in COMMANDS and not any(a in ("-h", "--help") for a in argv):
        parser = build_parser(load="")
        parser.print_usage(sys.stderr)
        print(f"uhrnet: error: choose a command from: {', '.join(COMMANDS)}", file=sys.stderr)
        return 2
    # FolderBusy, BackendError ... of the fppsim side are one line too (uhrnet reads through fppsim)
    return run_commands(build_parser(load=chosen if chosen in COMMANDS else ""), COMMANDS, argv,
                        (UhrnetError, DataError, FppsimError),
                        resume_hint={"train": " (resume with --resume)"},
                        usage_errors=(UsageError, FppsimUsageError))


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python
"""Heights in mm on real phase-shifting frames through a rig: the network alone and ``uhrnet predict --rig``'s path.

``uhrnet evaluate-phase`` scores a prediction without a calibration: it regresses the frame's phase on a cubic
plane plus ``a h + b h^2``, which absorbs any error of the heights' level and scale. On a frame with no plane in
view (objects on black) that hides what a user sees in mm. Here each frame's own phase-shifting phase is taken
through the SAME rig the network works in (``--rig``, e.g. the assumed-pose rig of docs/own_rig.md), so it gives
the heights that rig makes of the true phase; a frame with no plane fixes their level only up to whole fringe
periods, so the truth is shifted by the whole periods nearest each prediction, and the error is reported
without its mean (level-free) as well as with it.

For each run (one seed each) and frame id: the network's map as ``uhrnet predict --refine none`` writes it (at
the run's ``--resize``, NaN where the input is black) and the path's (``predict --rig``: the mean with the image
mirrored along the fringes, every phase region at one order); on the pixels with phase-shifting phase and a lit
input: the error's RMS (with any sub-period offset between the rig's phase origin and the frame's), standard
deviation (level-free), the standard deviation within 3 px of the unscored pixels (the rims) and further in, the
share within half a fringe period of height of the truth (after the mean; all pixels and the rims), and
evaluate-phase's residual / flat, as it is and with the pixels half a period off or more put at the truth. A third
row, ``path_truth_estimate``, runs the path with the frame's own phase-shifting heights (through the rig, at the
path's level) as its estimate: what the path would leave with a network that knew the answer, so the part of the
error that is the network's estimate and the part that is the path's.

With ``--pair`` (a labelled figshare pair: fringe_pattern.npy + height_map.npy) also a frame no choice was made
on: the pair with every pixel off its objects (valid, more than 1 mm above the plane) blacked out, as a frame of
objects on black would show them. Its labels are heights in another rig's frame, so each prediction is mapped to
them by the least-squares ``alpha h + beta`` over the object pixels (two numbers, the depth scale and level an
assumed-pose rig cannot know), and scored after it: RMSE, within 1 mm, and the rims' RMSE. ``--pair-background``
sets the black's gray level: 0 as the public frames zero their pixels without phase, or a camera's dark level.

Writes OUT/noplane_heights.json (every number), OUT/noplane_heights.md (the tables; mean ± sd over runs) and, with
``--pair``, OUT/pair_first_run.png (the first run's maps and errors on the pair).

    python pipelines/noplane_heights.py --runs RUN0 RUN1 RUN2 --frames FOLDER --rig RIG --out OUT [--pair DIR]
        [--pair-background GRAY]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage as ndi

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fppsim.dataio.readers import list_psp_ids, load_psp_folder_sample  # noqa: E402
from fppsim.files import atomic_write_text, json_text  # noqa: E402
from fppsim.geometry.rig import load_rig  # noqa: E402
from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint  # noqa: E402
from uhrnet.data.datasets import parse_size  # noqa: E402
from uhrnet.inference.prediction import network_heights, path_estimate, refine_with_phase  # noqa: E402
from uhrnet.physics.refine import layer_for  # noqa: E402
from uhrnet.plots import plot_comparison  # noqa: E402
from uhrnet.scoring.phase_residual import fit_phase  # noqa: E402
from uhrnet.workflows.sim2real.real_metrics import object_mask  # noqa: E402

RIM_PX = 3.0
KINDS = ("network", "path", "path_truth_estimate")
KEYS = ("rmse_mm", "sd_mm", "rim_sd_mm", "inner_sd_mm", "within_half_period", "rim_within_half_period",
        "phase_ratio", "phase_ratio_orders_true")
PAIR_KEYS = ("rmse_mm", "rim_rmse_mm", "inner_rmse_mm", "within_1mm", "alpha")
MIN_PIXELS = 24  # the phase fit's unknowns are 12: fewer pixels than twice that score nothing


class Network:
    """One run's network: (network, path) heights in mm of a dataset-encoded fringe, as ``uhrnet predict`` makes
    them (the checkpoint read once)."""

    def __init__(self, run: str):
        ck = load_checkpoint(run)
        self.model, self.transform = model_from_checkpoint(ck, "cpu")
        self.size = parse_size(ck.get("args", {}).get("resize"))

    def heights(self, fringe: np.ndarray, rig) -> tuple[np.ndarray, np.ndarray]:
        net = network_heights(self.model, self.transform, fringe, self.size)
        est = path_estimate(self.model, self.transform, fringe, self.size, rig, net)
        return net, refine_with_phase(est, fringe, rig, "orders", network_mm=net)[0].astype(np.float64)


def truth_heights(h: np.ndarray, psp_phase: np.ndarray, m: np.ndarray, layer) -> tuple[np.ndarray, np.ndarray]:
    """(the rig's heights of the phase-shifting phase shifted by the whole periods nearest ``h`` over ``m``, half a
    fringe period of height at each pixel), both (H, W) float64 mm."""
    t = lambda a: torch.as_tensor(np.nan_to_num(a), dtype=torch.float64)  # noqa: E731
    with torch.no_grad():
        orders = np.round(np.median(((psp_phase - layer.phase_from_height(t(h)).numpy()) / (2 * np.pi))[m]))
        truth = layer.height_from_phase(t(psp_phase - 2 * np.pi * orders)).numpy()
        half = np.pi / np.abs(layer.sensitivity(t(truth)).numpy())
    return truth, half


def scores(h: np.ndarray, psp_phase: np.ndarray, scored: np.ndarray, layer, rim: np.ndarray) -> dict:
    """The error of ``h`` against the rig's heights of the phase-shifting phase shifted by the whole periods nearest
    ``h`` (a sub-period offset between the rig's phase origin and the frame's stays in ``rmse_mm``; ``sd_mm`` and
    the shares are without the mean), on the ``scored`` pixels where ``h`` is finite; evaluate-phase's ratio on
    the same pixels, and that ratio with the pixels more than half a period off (after the mean) put at the truth:
    what the orders alone still cost."""
    m = scored & np.isfinite(h)
    if m.sum() < MIN_PIXELS:
        raise SystemExit(f"only {int(m.sum())} pixels have both a phase and a height: nothing to score")
    truth, half = truth_heights(h, psp_phase, m, layer)
    e = h - truth
    c = e - e[m].mean()
    off = m & (np.abs(c) >= half)
    level = e[m & ~off].mean() if (m & ~off).any() else e[m].mean()
    flat = fit_phase(psp_phase, np.zeros_like(h), m).rmse_rad
    ratio = lambda x: fit_phase(psp_phase, x, m).rmse_rad / flat  # noqa: E731
    return {"rmse_mm": float(np.sqrt(np.mean(e[m] ** 2))), "sd_mm": float(c[m].std()),
            "rim_sd_mm": float(c[m & rim].std()), "inner_sd_mm": float(c[m & ~rim].std()),
            "within_half_period": float(1.0 - off.sum() / m.sum()),
            "rim_within_half_period": float(1.0 - off[rim].sum() / max((m & rim).sum(), 1)),
            "phase_ratio": float(ratio(np.where(m, h, 0.0))),
            # at the level of the pixels in order (the mean over all would carry the off pixels' own periods)
            "phase_ratio_orders_true": float(ratio(np.where(off, truth + level, np.where(m, h, 0.0)))),
            "pixels": int(m.sum())}


def pair_frame(folder: Path, background: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(fringe with everything off the objects black, object mask, label heights in mm above the plane).
    ``background``: the black's gray level (0: exactly black, as the public frames zero pixels without phase;
    above 0: that level with a camera's noise of 2 gray levels, drawn from ``seed``)."""
    fringe = np.load(folder / "fringe_pattern.npy").astype(np.float32)
    label = np.load(folder / "height_map.npy").astype(np.float64)
    obj, plane = object_mask(label, label > -100)
    black = np.zeros(fringe.shape)
    if background > 0:
        black = np.clip(np.rint(background + 2.0 * np.random.default_rng(seed).standard_normal(fringe.shape)), 0, 255)
    return np.where(obj, fringe, (black / 127.5 - 1.0).astype(np.float32)), obj, (label - plane) / 6.0


def affine(h: np.ndarray, truth: np.ndarray, obj: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(``alpha h + beta``, alpha, beta): fitted to ``truth`` over the object pixels where ``h`` is finite."""
    m = obj & np.isfinite(h)
    if m.sum() < 2:
        raise SystemExit("the pair's objects have no predicted height to score")
    alpha, beta = np.polyfit(h[m], truth[m], 1)
    return alpha * h + beta, float(alpha), float(beta)


def pair_scores(h: np.ndarray, truth: np.ndarray, obj: np.ndarray, rim: np.ndarray) -> dict:
    m = obj & np.isfinite(h)
    mapped, alpha, beta = affine(h, truth, obj)
    e = mapped - truth
    r = lambda k: float(np.sqrt(np.mean(e[k] ** 2)))  # noqa: E731
    return {"rmse_mm": r(m), "rim_rmse_mm": r(m & rim), "inner_rmse_mm": r(m & ~rim),
            "within_1mm": float(np.mean(np.abs(e[m]) <= 1.0)), "alpha": alpha, "beta": beta,
            "coverage": float(m.sum() / obj.sum())}


def per_run(rows: list[dict]) -> list[dict]:
    """One row per run: its frames' scores averaged, so the spread in the tables is over runs (seeds)."""
    runs = list(dict.fromkeys(r["run"] for r in rows))
    kinds = [k for k in KINDS if k in rows[0]]
    return [{kind: {k: float(np.mean([r[kind][k] for r in rows if r["run"] == run])) for k in rows[0][kind]}
             for kind in kinds} for run in runs]


def table(rows: list[dict], keys, head) -> str:
    """Mean ± sd over runs (sd over 1 run: 0)."""
    rows = per_run(rows)
    out = ["| " + " | ".join(["estimate", "runs"] + head) + " |", "|" + "---|" * (len(head) + 2)]
    fmt = lambda a: f"{a.mean():.3g} ± {a.std(ddof=1) if len(a) > 1 else 0:.2g}"  # noqa: E731
    for kind in [k for k in KINDS if k in rows[0]]:
        out.append(f"| {kind} | {len(rows)} | " + " | ".join(fmt(np.array([r[kind][k] for r in rows])) for k in keys)
                   + " |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", nargs="+", required=True, metavar="RUN", help="checkpoints or run folders (their best epoch), one per seed")
    ap.add_argument("--frames", required=True, metavar="DIR", help="phase-shifting frames (PSin/ PCos/ Fringe/ iPattern/)")
    ap.add_argument("--rig", required=True, metavar="FILE", help="the rig the networks were trained for")
    ap.add_argument("--out", required=True, metavar="DIR")
    ap.add_argument("--pair", metavar="DIR", help="a labelled figshare pair to score with its plane blacked out")
    ap.add_argument("--pair-background", type=float, default=0.0, metavar="GRAY",
                    help="gray level of the pair's black (0: exactly black, as the public frames zero pixels without "
                         "phase; above 0: that level plus a camera's noise of 2 gray levels) [0]")
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    rig = load_rig(args.rig)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    frames = {sid: load_psp_folder_sample(args.frames, sid, convention="auto") for sid in list_psp_ids(args.frames)}
    for sid, s in frames.items():
        if "misread" in s.meta:
            print(f"{args.frames} {sid}: the files look written another way: {s.meta['misread']}", flush=True)
    nets = {run: Network(run) for run in args.runs}
    rows = []
    for run, network in nets.items():
        for sid, s in frames.items():
            fringe = (s.image.astype(np.float32) / 127.5 - 1.0)
            scored = s.valid & (s.image > 0)
            rim = ndi.distance_transform_edt(scored) <= RIM_PX
            layer = layer_for(rig, fringe.shape)
            net, pth = network.heights(fringe, rig)
            known = np.where(scored, truth_heights(pth, s.phase, scored & np.isfinite(pth), layer)[0], net)
            ideal = refine_with_phase(known, fringe, rig, "orders", network_mm=known)[0].astype(np.float64)
            rows.append({"run": run, "id": sid, "network": scores(net, s.phase, scored, layer, rim),
                         "path": scores(pth, s.phase, scored, layer, rim),
                         "path_truth_estimate": scores(ideal, s.phase, scored, layer, rim)})
            r = rows[-1]
            print(f"{run} {sid}: evaluate-phase ratio network {r['network']['phase_ratio']:.3f}, path "
                  f"{r['path']['phase_ratio']:.3f}, path from the truth {r['path_truth_estimate']['phase_ratio']:.3f}",
                  flush=True)
    pair_rows = []
    if args.pair:
        fringe, obj, truth = pair_frame(Path(args.pair), args.pair_background)
        rim = obj & (ndi.distance_transform_edt(obj) <= RIM_PX)
        for run, network in nets.items():
            net, pth = network.heights(fringe, rig)
            pair_rows.append({"run": run, "network": pair_scores(net, truth, obj, rim),
                              "path": pair_scores(pth, truth, obj, rim)})
            if len(pair_rows) == 1:  # the first run's maps, each after its own alpha h + beta
                plot_comparison(fringe, truth, obj, {"network": affine(net, truth, obj)[0], "path": affine(pth, truth, obj)[0]},
                                out / "pair_first_run.png", title=f"{run}: the pair on black")
            print(f"{run} pair: network {pair_rows[-1]['network']['rmse_mm']:.2f} mm, "
                  f"path {pair_rows[-1]['path']['rmse_mm']:.2f} mm", flush=True)
    atomic_write_text(out / "noplane_heights.json", json_text(
        {"rig": args.rig, "frames": args.frames, "rows": rows, "pair": args.pair,
         "pair_background": args.pair_background, "pair_rows": pair_rows}, indent=1))
    md = (f"# Heights through {args.rig} on {args.frames}\n\n" + table(
        rows, KEYS, ["RMSE (mm)", "level-free sd (mm)", f"rims <= {RIM_PX:g} px, sd", "inside, sd",
                     "within half a period", "rims: within half a period", "evaluate-phase ratio",
                     "that ratio, the pixels off by half a period or more at the truth"]) + "\n")
    if pair_rows:
        md += (f"\n## {args.pair}, plane blacked out (gray {args.pair_background:g}), after alpha h + beta\n\n" + table(
            pair_rows, PAIR_KEYS, ["object RMSE (mm)", f"rims <= {RIM_PX:g} px", "inside", "within 1 mm", "alpha"])
            + "\n")
    atomic_write_text(out / "noplane_heights.md", md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())

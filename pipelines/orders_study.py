#!/usr/bin/env python
"""Fringe orders on real frames: the network alone against ``uhrnet predict --refine phase --refine-method orders``.

For each training run given (one seed each) and on real frames only:

* the labelled figshare pair (``--pair``, default ../shared/real-sample), scored in mm through the
  depth-fitted rig (``assets/figshare_depth_rig.json``: its distance and baseline were fitted to the pair's
  labels, a calibration of two numbers) and through fppsim's default rig: object RMSE, median |error|, share
  within 1 mm and share at the right fringe order (|error| under half a fringe period of height at the pixel,
  through the rig scored) over the object pixels (valid, more than 1 mm above the plane). The network's map is
  the one ``uhrnet predict`` writes (invalid pixels NaN), the path's is its ``--refine phase --refine-method
  orders`` through the rig. The order choice uses no label.
* real phase-shifting frames (``--phase``, default the three folders of ../shared/real-phase): the calibration-free
  phase residual ``uhrnet evaluate-phase`` computes (degree-3 plane + a h + b h^2 over pixels with real phase
  and a lit input), network and path on the same pixels, and its ratio (also without the pixels where the
  reference's own temporal order slipped, ``fppsim.phase.reference_check``: the score counts them); for FP1523 (the pair's rig) through the
  depth-fitted rig, for the other rigs through a rig ``fppsim fit-rig`` builds from the frame itself (no
  ``--base``, written to OUT/rigs/). Also the share of the path's moved pixels whose absolute phase sits at the
  phase-shifting data's own order (the plane as reference).

Writes OUT/orders.json (every number, per run and frame), OUT/orders.md (the tables) and OUT/figures/ (per run:
the pair and each frame, regions coloured by confidence with their chosen order, and the error where known).
Re-running recomputes (a run takes about a minute on 2 cores). OUT keeps an ownership record (``fppsim.owned``):
every file the run will write is claimed before any work, and one there the study did not write, or changed since
it wrote it (an orders.json, a figure, a rig), is refused in one line (exit 2), not replaced; a folder the study
wrote before it kept the record is recognised by its orders.json. Refused as well, before any work: a bad
checkpoint, a pair that is not two numeric arrays of the depth rig's size, a --phase folder without frames or
sharing its name with another (rigs and results are filed by name), and an --out that is one of the inputs.
Figures are named by seed (``seed<k>_run<i>`` where two runs share one).

    python pipelines/orders_study.py --runs runs/s2r0/default/run runs/seed1 runs/seed2 --out docs/experiments/orders
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "pipelines"))

from fppsim.dataio.readers import list_psp_ids, load_psp_folder_sample  # noqa: E402
from fppsim.errors import FppsimError  # noqa: E402
from fppsim.files import atomic_write_text, json_text  # noqa: E402
from fppsim.owned import claim, output_folder, same_folder, stamp  # noqa: E402
from fppsim.phase.reference_check import order_slips  # noqa: E402
from fppsim.geometry.rig import load_rig, make_default_rig  # noqa: E402
from uhrnet.checkpoint import load_checkpoint, model_from_checkpoint  # noqa: E402
from uhrnet.errors import UhrnetError  # noqa: E402
from uhrnet.inference.prediction import network_heights, order_choice, path_estimate  # noqa: E402
from uhrnet.physics.refine import layer_for  # noqa: E402
from uhrnet.plots import plot_orders  # noqa: E402
from uhrnet.scoring.phase_residual import fit_phase  # noqa: E402
from uhrnet.workflows.sim2real.real_metrics import object_mask  # noqa: E402
from orders_ceiling import frame_ceiling, pair_ceiling, reference_orders  # noqa: E402

SHARED = ROOT.parent / "shared"
MD_HEADER = "| seed | rig | prediction | object RMSE (mm) | median (mm) | within 1 mm | right order |"  # orders.md's first line
TOOL = "orders_study"  # its files' owner in the --out folder's ownership record (fppsim.owned)


class StudyError(Exception):
    """A bad argument or input of the study (one line, exit 2)."""


def network(model, transform, fringe: np.ndarray, mask_invalid: bool) -> np.ndarray:
    """The network's height (mm) of a dataset-encoded fringe; NaN where predict marks it invalid (when asked)."""
    return network_heights(model, transform, fringe, None, keep_all=not mask_invalid)


def path(h: np.ndarray, fringe: np.ndarray, rig, model=None, transform=None, name: str = "image"):
    """The order choice as ``uhrnet predict --refine phase --refine-method orders`` makes it: from the network's
    mean over the image and its mirror along the fringes (``path_estimate``) when ``model`` is given, else
    from ``h`` (the network's single pass, as before 2026-11-28); the pixels it leaves alone keep ``h``, as
    predict's keep the network's own map (since stop 63). ``name`` heads the errors of a frame without fringes."""
    if model is not None:
        return order_choice(path_estimate(model, transform, fringe, None, rig, h), fringe, rig, network_mm=h, name=name)
    return order_choice(h, fringe, rig, name=name)


def pair_scores(pred: np.ndarray, truth: np.ndarray, obj: np.ndarray, layer) -> dict:
    e = pred - truth
    m = obj & np.isfinite(pred)
    with torch.no_grad():
        half = np.pi / np.abs(layer.sensitivity(torch.as_tensor(np.nan_to_num(truth), dtype=torch.float64)).numpy())
    return {"object_rmse_mm": float(np.sqrt(np.mean(e[m] ** 2))), "median_abs_mm": float(np.median(np.abs(e[m]))),
            "within_1mm": float(np.mean(np.abs(e[m]) <= 1.0)), "right_order": float(np.mean(np.abs(e[m]) < half[m])),
            "coverage": float(m.sum() / obj.sum())}


def order_share(choice, layer, psp_phase: np.ndarray, scored: np.ndarray, flat_mm: float = 1.0) -> float:
    """Share of the moved pixels whose absolute phase (rig phase of the chosen height + origin) is at the PSP
    phase's order, relative to the plane's (the moved pixels the path puts within ``flat_mm`` of 0; the reading:
    :func:`orders_ceiling.reference_orders`)."""
    r, plane = reference_orders(choice, layer, psp_phase, flat_mm)
    m = choice.moved & scored & np.isfinite(r)
    plane &= scored
    if not plane.any() or not m.any():
        return float("nan")
    return float(np.mean(np.abs(r[m] - np.median(r[plane])) < 0.5))


def fitted_rig(folder: Path, out: Path, owner: Path | None = None):
    """The rig ``fppsim fit-rig`` builds from ``folder``'s frames, written to ``out`` and read back. Without
    ``owner`` a rig already at ``out`` is reused (harnesses); with ``owner`` (the study's --out folder, which has
    claimed ``out``) it is fitted again on every run, since another folder of the same name, or the same folder
    with other frames, would need another rig (a fit takes a few seconds), and a failed fit is a
    :class:`StudyError` naming the folder and fit-rig's own reason."""
    out.parent.mkdir(parents=True, exist_ok=True)
    if owner is not None or not out.exists():
        done = subprocess.run([sys.executable, "-m", "fppsim", "fit-rig", str(folder), "--out", str(out),
                               *(["--force"] if out.exists() else [])],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        if done.returncode != 0:
            if owner is None:
                raise subprocess.CalledProcessError(done.returncode, done.args, stderr=done.stderr)
            why = (done.stderr.strip().splitlines() or ["no message"])[-1]
            raise StudyError(f"fppsim fit-rig {folder} failed: {why}")
    return load_rig(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", nargs="+", required=True, metavar="RUN", help="training runs (best.pt) or checkpoints")
    ap.add_argument("--out", required=True, metavar="DIR")
    ap.add_argument("--pair", default=str(SHARED / "real-sample"), metavar="DIR",
                    help="labelled figshare pair (fringe_pattern.npy + height_map.npy) [../shared/real-sample]")
    ap.add_argument("--phase", nargs="*", default=[str(SHARED / "real-phase" / f) for f in ("FP1523", "FP672", "FP147")],
                    metavar="DIR", help="phase-shifting folders; one named FP1523 is the pair's rig [../shared/real-phase/*]")
    ap.add_argument("--depth-rig", default=str(ROOT / "assets" / "figshare_depth_rig.json"), metavar="FILE")
    ap.add_argument("--single-pass", action="store_true",
                    help="the path starts from the network's single pass, not its mean with the image mirrored "
                         "along the fringes (uhrnet predict's estimate)")
    args = ap.parse_args(argv)
    try:
        return run(args)
    except (StudyError, FppsimError, UhrnetError, OSError) as exc:
        print(f"orders_study: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("orders_study: interrupted; files it had not rewritten yet keep their earlier versions", file=sys.stderr)
        return 130


def run(args) -> int:
    torch.set_num_threads(2)
    out = Path(args.out)
    checkpoints = {r: load_checkpoint(r) for r in args.runs}
    models = {r: (ck, *model_from_checkpoint(ck, "cpu")) for r, ck in checkpoints.items()}  # every one checked first
    depth_rig = load_rig(args.depth_rig)
    pair = _read_pair(Path(args.pair), depth_rig)
    folders = [Path(f) for f in args.phase]
    ids = _phase_ids(folders)
    run_folders = [Path(r) if Path(r).is_dir() else Path(r).parent for r in args.runs]
    for given, flag in [(args.pair, "--pair"), *((f, "--phase") for f in folders), *((r, "--runs") for r in run_folders)]:
        if same_folder(out, given):
            raise StudyError(f"--out {out} is the {flag} folder {given}: choose another --out")
    tags = _run_tags(models)
    figures = [figure_name("pair", t) for t in tags] + [
        figure_name(f"{f.name}/{sid}", t) for t in tags for f in folders for sid in ids[f]]
    written = ["orders.json", "orders.md", *figures, *(f"rigs/{f.name}.json" for f in folders if f.name != "FP1523")]
    with output_folder(out, TOOL, error=StudyError):
        claim(out, TOOL, written, legacy=lambda: _legacy_files(out))
        done: list[str] = []  # what this run has written, in order
        try:
            return _study(args, models, tags, pair, depth_rig, ids, out, done)
        finally:  # a file edited after the study wrote it is no longer the study's (claim refuses it next time)
            stamp(out, done)


def _read_pair(folder: Path, rig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The labelled pair: (fringe, height above the plane in mm, object mask), checked against the depth rig."""
    arrays = []
    for name in ("fringe_pattern.npy", "height_map.npy"):
        try:
            a = np.load(folder / name, allow_pickle=False)
        except FileNotFoundError:
            raise StudyError(f"--pair {folder}: no {name}") from None
        except (OSError, ValueError) as exc:
            raise StudyError(f"--pair {folder / name}: not a numpy array ({exc})") from None
        a = np.squeeze(a)
        if a.shape != (rig.camera.height, rig.camera.width) or not np.issubdtype(a.dtype, np.number):
            raise StudyError(f"--pair {folder / name}: {a.dtype} array of shape {a.shape}, expected numbers "
                             f"{rig.camera.height} x {rig.camera.width} (the depth rig's camera)")
        arrays.append(a)
    fringe, label = arrays[0].astype(np.float32), arrays[1].astype(np.float64)
    obj, plane = object_mask(label, label > -100)
    return fringe, (label - plane) / 6.0, obj


def _phase_ids(folders: list[Path]) -> dict:
    """Each --phase folder's frame ids; a folder that is missing, holds no frame or shares its name with another
    (its rig and results are filed under the name) is refused."""
    ids, seen = {}, {}
    for folder in folders:
        if folder.name in seen:
            raise StudyError(f"--phase {folder} and {seen[folder.name]} share the name {folder.name!r}: "
                             "their rigs and results would be filed together")
        seen[folder.name] = folder
        if not folder.is_dir():
            raise StudyError(f"--phase {folder}: no such folder")
        ids[folder] = list_psp_ids(folder)
        if not ids[folder]:
            raise StudyError(f"--phase {folder}: no phase-shifting frame (iPattern/, PSin/, PCos/, Fringe/)")
    return ids


def figure_name(what: str, tag: str) -> str:
    """A figure's path in OUT: ``figures/pair_<tag>.png`` or ``figures/<folder>_<id>_<tag>.png`` for the frame
    ``<folder>/<id>``."""
    return f"figures/{what.replace('/', '_')}_{tag}.png"


def _run_tags(models: dict) -> list[str]:
    """Each run's name in the figures: ``seed<k>``, or ``seed<k>_run<i>`` where two runs share a seed."""
    seeds = [ck.get("args", {}).get("seed", i) for i, (ck, _, _) in enumerate(models.values())]
    return [f"seed{s}" if seeds.count(s) == 1 else f"seed{s}_run{i}" for i, s in enumerate(seeds)]


def _legacy_files(out: Path) -> set[str]:
    """A folder the study wrote before it kept an ownership record: the files its orders.json names, else none."""
    try:
        rows = json.loads((out / "orders.json").read_text())
        if not isinstance(rows, list) or not rows or not all(
                isinstance(r, dict) and {"run", "seed", "pair", "frames"} <= r.keys() for r in rows):
            return set()
        own = {"orders.json"}
        md = out / "orders.md"
        if not md.exists() or md.read_text(errors="replace").startswith(MD_HEADER):
            own.add("orders.md")
        for r in rows:
            own.add(figure_name("pair", f"seed{r['seed']}"))
            for frame in r["frames"]:
                own.add(figure_name(frame, f"seed{r['seed']}"))
                if not frame.startswith("FP1523/"):
                    own.add(f"rigs/{frame.split('/')[0]}.json")
        return own
    except (OSError, ValueError, TypeError, AttributeError):
        return set()


def _study(args, models: dict, tags: list[str], pair, depth_rig, ids: dict, out: Path, done: list[str]) -> int:
    (out / "figures").mkdir(parents=True, exist_ok=True)
    fringe, truth, obj = pair
    rigs = {"depth": depth_rig, "default": make_default_rig()}
    frames = []
    for folder, frame_ids in ids.items():
        if folder.name == "FP1523":
            rig = rigs["depth"]
        else:
            rig = fitted_rig(folder, out / "rigs" / f"{folder.name}.json", out)
            done.append(f"rigs/{folder.name}.json")
        for sid in frame_ids:
            s = load_psp_folder_sample(folder, sid)
            frames.append((f"{folder.name}/{sid}", s, rig, order_slips(s.wrapped, s.phase, s.valid).mask))
    results = []
    for k, (run, (ck, model, transform)) in enumerate(models.items()):
        seed, tag = ck.get("args", {}).get("seed", k), tags[k]
        row = {"run": str(run), "seed": seed, "estimate": "single pass" if args.single_pass else "mirror mean",
               "pair": {}, "frames": {}}
        mirror = () if args.single_pass else (model, transform)
        h = network(model, transform, fringe, mask_invalid=True)
        for name, rig in rigs.items():
            layer = layer_for(rig, h.shape)
            choice = path(h, fringe, rig, *mirror, name=f"the pair ({args.pair})")
            row["pair"][name] = {"network": pair_scores(h, truth, obj, layer),
                                 "orders": pair_scores(choice.height, truth, obj, layer), "stats": choice.stats,
                                 "ceiling": pair_scores(pair_ceiling(choice.height, choice.labels, truth, obj, layer),
                                                        truth, obj, layer)}
            if name == "depth":
                figure = figure_name("pair", tag)
                plot_orders(fringe, h, choice, out / figure,
                            error_mm=np.where(obj, choice.height - truth, np.nan),
                            title=f"real pair, seed {seed}, depth-fitted rig: object RMSE "
                                  f"{row['pair'][name]['orders']['object_rmse_mm']:.2f} mm (network "
                                  f"{row['pair'][name]['network']['object_rmse_mm']:.2f})")
                done.append(figure)
        for fname, s, rig, slipped in frames:
            img = s.image.astype(np.float32) / 127.5 - 1.0
            hn = network(model, transform, img, mask_invalid=False)  # as evaluate-phase scores it
            choice = path(hn, img, rig, *mirror, name=f"{fname} ({s.path})")
            scored = s.valid & (s.image > 0)
            net_res = fit_phase(s.phase, hn, scored).rmse_rad
            path_res = fit_phase(s.phase, choice.height.astype(np.float64), scored).rmse_rad
            flat_res = fit_phase(s.phase, np.zeros(hn.shape), scored).rmse_rad
            layer = layer_for(rig, hn.shape)
            keep = scored & ~slipped  # the reference's own order slips left out (fppsim.phase.reference_check)
            row["frames"][fname] = {"network_rad": net_res, "orders_rad": path_res, "flat_rad": flat_res,
                                    "ratio": path_res / net_res, "right_order_moved": order_share(choice, layer, s.phase, scored),
                                    "slipped_px": int((scored & slipped).sum()),
                                    "ratio_without_slips": fit_phase(s.phase, choice.height.astype(np.float64),
                                                                     keep).rmse_rad / fit_phase(s.phase, hn, keep).rmse_rad,
                                    "stats": choice.stats,
                                    "ceiling": frame_ceiling(choice, s.phase, scored, slipped, layer)}
            figure = figure_name(fname, tag)
            plot_orders(img, hn, choice, out / figure,
                        title=f"{fname}, seed {seed}: residual {path_res:.3f} rad (network {net_res:.3f}, flat {flat_res:.3f})")
            done.append(figure)
        results.append(row)
        print(progress_line(seed, row), flush=True)
    atomic_write_text(out / "orders.json", json_text(results, indent=1, default=float))
    atomic_write_text(out / "orders.md", markdown(results))
    done += ["orders.json", "orders.md"]
    print(markdown(results))
    return 0


def progress_line(seed: int, row: dict) -> str:
    """One seed's line on stdout: strict JSON (a ratio of a zero residual, NaN or inf, is null)."""
    return json_text({"seed": seed, "pair_depth": row["pair"]["depth"]["orders"],
                      "frames": {f: round(v["ratio"], 3) for f, v in row["frames"].items()}})


def _ms(values) -> str:
    v = np.asarray(values, float)
    return f"{v.mean():.2f} ± {v.std(ddof=1):.2f}" if len(v) > 1 else f"{v.mean():.2f}"


def markdown(results: list[dict]) -> str:
    lines = [MD_HEADER,
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in results:
        for rig, d in r["pair"].items():
            for what in ("network", "orders"):
                m = d[what]
                lines.append(f"| {r['seed']} | {rig} | {what} | {m['object_rmse_mm']:.2f} | {m['median_abs_mm']:.2f} | "
                             f"{m['within_1mm']:.1%} | {m['right_order']:.1%} |")
    for rig in ("depth", "default"):
        for what in ("network", "orders"):
            vals = [r["pair"][rig][what] for r in results]
            lines.append(f"| mean ± sd | {rig} | {what} | {_ms([v['object_rmse_mm'] for v in vals])} | "
                         f"{_ms([v['median_abs_mm'] for v in vals])} | {_ms([100 * v['within_1mm'] for v in vals])} % | "
                         f"{_ms([100 * v['right_order'] for v in vals])} % |")
    lines += ["", "| seed | frame | network (rad) | orders (rad) | flat (rad) | orders / network | moved pixels at the PSP order "
              "| orders / network without the reference's slips (px) |",
              "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    frames = list(results[0]["frames"]) if results else []
    for r in results:
        for f in frames:
            d = r["frames"][f]
            lines.append(f"| {r['seed']} | {f} | {d['network_rad']:.3f} | {d['orders_rad']:.3f} | {d['flat_rad']:.3f} | "
                         f"{d['ratio']:.3f} | {d['right_order_moved']:.1%} | {d['ratio_without_slips']:.3f} "
                         f"({d['slipped_px']}) |")
    for f in frames:
        vals = [r["frames"][f] for r in results]
        lines.append(f"| mean ± sd | {f} | {_ms([v['network_rad'] for v in vals])} | {_ms([v['orders_rad'] for v in vals])} | "
                     f"{_ms([v['flat_rad'] for v in vals])} | {_ms([v['ratio'] for v in vals])} | "
                     f"{_ms([100 * v['right_order_moved'] for v in vals])} % | "
                     f"{_ms([v['ratio_without_slips'] for v in vals])} |")
    return "\n".join(lines + ceiling_markdown(results)) + "\n"


def ceiling_markdown(results: list[dict]) -> list[str]:
    """The ceiling of a perfect per-region order choice (pipelines/orders_ceiling.py) and the parts of the residual."""
    lines = ["", "| seed | pair RMSE (mm): orders / every region at the label's order | frame | orders / network: path | "
             "every region at the reference's order | without no-region px | without rim split's order errors | "
             "without region px a whole order off | without the reference's slips |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in results:
        pair = r["pair"]["depth"]
        for f, d in r["frames"].items():
            c, net = d["ceiling"], d["network_rad"]
            ceiling = ("no plane to read the orders against" if c["regions_moved"] is None
                       else f"{c['ceiling_rad'] / net:.3f} ({c['regions_moved']} regions)")
            parts = " | ".join(f"{c['parts'][p]['rad_without'] / net:.3f} ({c['parts'][p]['share']:.0%})"
                               for p in ("no_region", "rim_split_order_off", "region_order_off", "reference_slipped"))
            lines.append(f"| {r['seed']} | {pair['orders']['object_rmse_mm']:.2f} / {pair['ceiling']['object_rmse_mm']:.2f} "
                         f"| {f} | {d['ratio']:.3f} | {ceiling} | {parts} |")
    return lines


if __name__ == "__main__":
    sys.exit(main())

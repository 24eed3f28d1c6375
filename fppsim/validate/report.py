"""Dataset-level PSP validation: reading the samples, pooling their errors, report, tables, error maps.

:func:`validate_dataset` runs :func:`fppsim.validate.sample.evaluate_sample` over every sample of a
native dataset, pools the pixels (:class:`Pool`), writes ``report.json`` and the per-sample error maps;
:func:`format_table` / :func:`format_sweep_table` print what the command line shows.

The report and map names are claimed in ``out``'s ownership record (:mod:`fppsim.owned`) before anything
is written: a ``report.json`` or ``maps/<id>.png`` of the user's is refused, never replaced. Folders
written before the record existed are adopted by :func:`own_report_files`: a ``report.json`` of this tool
and the PNG maps it lists.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from fppsim.fitting.compare import format_value
from fppsim.errors import DatasetError, ValidateError
from fppsim.dataio.encoding import json_default, png_size
from fppsim.files import atomic_write_text, json_text
from fppsim.owned import claim, output_folder
from fppsim.dataio.formats import read_manifest, read_settings
from fppsim.dataio.readers import load_native_sample, open_source, read_native_psp
from fppsim.validate.sample import BREAKDOWN, breakdown_fractions, evaluate_sample
from fppsim.plots import save_figure

__all__ = ["VALIDATE_TOOL", "report_files", "own_report_files", "resolve_dataset", "read_records", "read_dataset_settings",
           "load_sample", "Pool", "write_error_map", "validate_dataset", "format_table", "format_sweep_table"]

VALIDATE_TOOL = "fppsim validate-psp"
_HIST_EDGES = np.concatenate([[0.0], np.logspace(-6, 4, 4001)])  # |error| in mm, 0.58 % per bin


# ====================================================================== input
def resolve_dataset(path) -> Path:
    """The native sample root of a dataset folder (itself, or ``<path>/native`` for figshare output).

    Raises :class:`ValidateError` for a missing folder, an empty one, or one that is not an fppsim dataset.
    """
    p = Path(path)
    if not p.exists():
        raise ValidateError(f"dataset folder not found: {p}")
    if not p.is_dir():
        raise ValidateError(f"not a folder: {p}")
    if not any(p.iterdir()):
        raise ValidateError(f"{p}: empty folder (no samples to validate)")
    samples = open_source(p).fppsim_samples()  # the folder itself, or a figshare export's native/ samples
    if samples is None or not samples.has_manifest:
        raise ValidateError(f"{p}: not an fppsim dataset folder (no manifest.jsonl)")
    return samples.path


def read_records(root: Path) -> list[dict]:
    try:
        records = [r for r in read_manifest(root) if (root / str(r.get("id"))).is_dir()]
    except DatasetError as exc:
        raise ValidateError(str(exc)) from None
    if not records:
        raise ValidateError(f"{root}: no finished samples to validate")
    return records


def read_dataset_settings(root: Path) -> dict | None:
    try:
        return read_settings(root)
    except DatasetError as exc:
        raise ValidateError(str(exc)) from None


def load_sample(root: Path, rec: dict) -> tuple[dict, dict | None]:
    """Arrays + meta of one sample and its PSP stacks ``{f: (N, H, W) uint8}`` (None if images are missing)."""
    folder = root / str(rec["id"])
    try:
        s = load_native_sample(folder)
    except (OSError, KeyError, ValueError) as exc:
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ValidateError(f"{folder}: unreadable sample ({why})") from None
    psp = s["meta"].get("psp")
    if not psp or "phase_psp" not in s or "height_psp" not in s or "mask_psp" not in s:
        raise ValidateError(f"{root}: no PSP data in sample {rec['id']} (generated with --no-psp?): "
                            "re-generate without --no-psp")
    try:
        _, stacks, _, _ = read_native_psp(folder)  # the one reader of a sample's phase-shifting images
    except DatasetError:  # images missing or damaged: the sample is scored without the rejection reasons
        return s, None
    return s, stacks


# ====================================================================== aggregation
class Pool:
    """Pooled statistics over samples (counts, sums of squares, histograms of |error|)."""
    COUNTS = ("n_valid", "n_accepted", "n_rejected", "n_order_errors", "n_order_errors_accepted",
              "n_order_errors_rejected", "n_rejected_correct_order", "n_edge", "n_interior")

    def __init__(self):
        self.counts = dict.fromkeys(self.COUNTS, 0)
        self.breakdown = dict.fromkeys(["n_valid_with_images"] + [f"n_{k}" for k in BREAKDOWN], 0)
        self.sums = {}   # name -> [n, sum, sum of squares, max |e|]
        self.hist = {}
        self.rmse = []

    def _add(self, name: str, e: np.ndarray, hist: bool = False) -> None:
        s = self.sums.setdefault(name, [0, 0.0, 0.0, 0.0])
        if e.size:
            s[0] += e.size
            s[1] += float(e.sum())
            s[2] += float((e * e).sum())
            s[3] = max(s[3], float(np.abs(e).max()))
        if hist:
            h = np.histogram(np.minimum(np.abs(e), _HIST_EDGES[-1]), _HIST_EDGES)[0]
            self.hist[name] = self.hist.get(name, 0) + h

    def add(self, stats: dict, maps: dict) -> None:
        for k in self.COUNTS:
            self.counts[k] += stats[k]
        if "n_low_modulation" in stats:
            self.breakdown["n_valid_with_images"] += stats["n_valid"]
            for k in BREAKDOWN:
                self.breakdown[f"n_{k}"] += stats[f"n_{k}"]
        err, acc, wrong, edge = maps["error_mm"], maps["accepted"], maps["wrong"], maps["edge"]
        ok = acc & ~wrong
        self._add("incl", err[acc], hist=True)
        self._add("excl", err[ok], hist=True)
        self._add("edge", err[ok & edge])
        self._add("interior", err[ok & ~edge], hist=True)
        if stats["rmse_mm_incl_order_errors"] is not None:
            self.rmse.append(stats["rmse_mm_incl_order_errors"])

    def _p99(self, name):
        h = self.hist.get(name)
        if h is None or h.sum() == 0:
            return None
        i = int(np.searchsorted(np.cumsum(h), 0.99 * h.sum()))
        return float(_HIST_EDGES[min(i + 1, len(_HIST_EDGES) - 1)])

    def result(self, n_samples: int) -> dict:
        c = self.counts
        nv = c["n_valid"]
        frac = (lambda n: float(n) / nv if nv else None)
        out = {"n_samples": n_samples, **c,
               "rejected_fraction": frac(c["n_rejected"]),
               "order_error_fraction": frac(c["n_order_errors_accepted"]),
               "order_error_fraction_before_rejection": frac(c["n_order_errors"]),
               "rejected_correct_order_fraction": frac(c["n_rejected_correct_order"]),
               "order_errors_caught_fraction": (c["n_order_errors_rejected"] / c["n_order_errors"])
               if c["n_order_errors"] else None}

        def rm(name):
            n, s, ss, mx = self.sums.get(name, [0, 0.0, 0.0, 0.0])
            return (math.sqrt(ss / n), s / n, mx) if n else (None, None, None)

        for tag, name in (("incl_order_errors", "incl"), ("excl_order_errors", "excl")):
            r, m, mx = rm(name)
            out[f"rmse_mm_{tag}"], out[f"mean_mm_{tag}"], out[f"max_abs_mm_{tag}"] = r, m, mx
            out[f"p99_abs_mm_{tag}"] = self._p99(name)
        out["rmse_mm_edge_excl_order_errors"] = rm("edge")[0]
        out["rmse_mm_interior_excl_order_errors"] = rm("interior")[0]
        out["p99_abs_mm_interior_excl_order_errors"] = self._p99("interior")
        if self.breakdown["n_valid_with_images"]:
            out.update(self.breakdown)
            out.update(breakdown_fractions(self.breakdown))
        r = np.asarray(self.rmse)
        out["per_sample_rmse_mm_incl_order_errors"] = (
            {"mean": float(r.mean()), "median": float(np.median(r)), "min": float(r.min()), "max": float(r.max())}
            if r.size else None)
        return out


# ====================================================================== error map
def write_error_map(path, error_mm: np.ndarray, valid: np.ndarray, accepted: np.ndarray, wrong: np.ndarray,
                    title: str = "", vmax: float | None = None) -> Path:
    """PNG of the PSP height error (mm) with a symmetric colour scale.

    Accepted pixels: colour (``RdBu_r``, +-``vmax``; default the 99th percentile of |error| without order
    errors); order-error pixels magenta, exact-valid pixels PSP rejected grey, pixels outside the exact
    mask (shadow, outside the projector) black.
    """
    import matplotlib  # (a bare Figure renders without pyplot or a backend: nothing to set up)
    from matplotlib import colors
    from matplotlib.cm import ScalarMappable
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch


    path = Path(path)
    ok = accepted & ~wrong
    if vmax is None:
        vmax = float(np.percentile(np.abs(error_mm[ok]), 99)) if ok.any() else 1.0
    vmax = max(vmax, 1e-3)
    cmap = matplotlib.colormaps["RdBu_r"]
    norm = colors.Normalize(-vmax, vmax, clip=True)
    rgb = cmap(norm(np.nan_to_num(error_mm)))[..., :3]
    rgb[~valid] = (0.0, 0.0, 0.0)
    rgb[valid & ~accepted] = (0.55, 0.55, 0.55)
    rgb[wrong & accepted] = (1.0, 0.0, 1.0)  # rejected wrong orders stay grey: PSP refused them
    H, W = error_mm.shape
    iw, ih = W / 100.0, H / 100.0  # 1 image pixel = 1 PNG pixel at dpi 100
    fw, fh = iw + 1.3, ih + 0.75
    fig = Figure(figsize=(fw, fh), dpi=100)
    ax = fig.add_axes((0.1 / fw, 0.35 / fh, iw / fw, ih / fh))
    ax.imshow(rgb, interpolation="nearest")
    ax.set_axis_off()
    ax.set_title(title, fontsize=7)
    cax = fig.add_axes(((iw + 0.25) / fw, 0.35 / fh + 0.1 * ih / fh, 0.12 / fw, 0.8 * ih / fh))
    cb = fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), cax=cax, extend="both")
    cb.set_label("PSP - exact height (mm)", fontsize=7)
    cb.ax.tick_params(labelsize=6)
    fig.legend(handles=[Patch(color=(1, 0, 1), label="order error"),
                        Patch(color=(0.55, 0.55, 0.55), label="PSP rejected"),
                        Patch(color=(0, 0, 0), label="not valid (exact mask)")],
               loc="lower left", bbox_to_anchor=(0.1 / fw, 0.0), ncol=3, fontsize=7, frameon=False)
    return save_figure(fig, path)


# ====================================================================== which files are validate-psp's
def report_files(ids, maps: bool = True, prefix: str = "") -> list[str]:
    """The names a validation of samples ``ids`` writes under ``out`` (``prefix``: their subfolder of it)."""
    return [prefix + "report.json"] + ([f"{prefix}maps/{sid}.png" for sid in ids] if maps else [])


def _own_report(folder: Path, prefix: str) -> list[str]:
    try:
        doc = json.loads((folder / "report.json").read_text())
    except (OSError, ValueError):
        return []
    if not (isinstance(doc, dict) and str(doc.get("tool", "")).startswith(VALIDATE_TOOL)
            and ({"samples", "aggregate"} <= doc.keys() or {"grid", "rows"} <= doc.keys())):
        return []
    rows = doc.get("samples") if isinstance(doc.get("samples"), list) else []
    maps = []
    for row in rows:
        name = row.get("error_map") if isinstance(row, dict) else None
        if not (isinstance(name, str) and name.startswith("maps/") and name.count("/") == 1 and name.endswith(".png")):
            continue
        if png_size(folder / name) is not None:
            maps.append(prefix + name)
    return [prefix + "report.json", *maps]


def own_report_files(out) -> list[str]:
    """The files of ``out`` that validate-psp wrote before it kept an ownership record: its ``report.json``
    (the tool and keys it writes) and the PNG maps that report lists, also in each ``sweep/<setting>/``."""
    out = Path(out)
    names = _own_report(out, "")
    if (out / "sweep").is_dir():
        for sub in sorted(p for p in (out / "sweep").iterdir() if p.is_dir()):
            names += _own_report(sub, f"sweep/{sub.name}/")
    return names


# ====================================================================== dataset validation
def validate_dataset(dataset, out, maps: bool = True, progress: bool = True, edge_px: int = 3,
                     min_modulation: float | None = None, extra: dict | None = None, claimed: bool = False) -> dict:
    """Validate every sample of a native dataset; write ``<out>/report.json`` (and ``<out>/maps/<id>.png``).

    Returns the report: ``{"dataset", "settings", "analysis", "samples": [...], "aggregate": {...}}``. The
    names are claimed in ``out``'s ownership record first (a file of the user's: :class:`ForeignFiles`, nothing
    written); ``claimed``: the caller holds ``out`` (or a folder above it) and has claimed them already.
    """
    root = resolve_dataset(dataset)
    records = read_records(root)
    settings = read_dataset_settings(root)
    if settings is not None and not (settings.get("config") or {}).get("psp_freqs", [1]):
        raise ValidateError(f"{root}: no PSP data (generated with --no-psp): re-generate without --no-psp")
    out = Path(out)
    if claimed:
        return _validate_records(root, records, settings, out, maps, progress, edge_px, min_modulation, extra)
    with output_folder(out, VALIDATE_TOOL, error=ValidateError):  # never a report or map of the user's
        claim(out, VALIDATE_TOOL, report_files([str(r["id"]) for r in records], maps),
              legacy=lambda: own_report_files(out))
        return _validate_records(root, records, settings, out, maps, progress, edge_px, min_modulation, extra)


def _validate_records(root: Path, records, settings, out: Path, maps, progress, edge_px, min_modulation, extra) -> dict:
    from tqdm import tqdm

    out.mkdir(parents=True, exist_ok=True)
    if maps:
        (out / "maps").mkdir(exist_ok=True)
    pool, samples = Pool(), []
    used_min_mod = None
    for rec in tqdm(records, desc="validate-psp", unit="sample", disable=not progress, dynamic_ncols=True):
        s, stacks = load_sample(root, rec)
        meta = s["meta"]
        st = evaluate_sample(s, meta, stacks, edge_px=edge_px, min_modulation=min_modulation, with_errors=True)
        m = st.pop("_maps")
        used_min_mod = st.get("min_modulation", used_min_mod)
        pool.add(st, m)
        sid = str(rec["id"])
        row = {"id": sid, "index": meta.get("index"), "seed": meta.get("seed"), "optics": meta.get("optics"),
               "noise_free": meta.get("noise_free"), **st}
        if maps:
            title = (f"{sid}: RMSE {_mm_cell(st['rmse_mm_incl_order_errors'])} mm "
                     f"(excl. order errors {_mm_cell(st['rmse_mm_excl_order_errors'])} mm), "
                     f"{st['n_order_errors_accepted']} order-error px, "
                     f"{_pct(st['rejected_fraction'])} % rejected")
            write_error_map(out / "maps" / f"{sid}.png", m["error_mm"], m["valid"], m["accepted"], m["wrong"], title)
            row["error_map"] = f"maps/{sid}.png"
        samples.append(row)
    report = {
        "tool": "fppsim validate-psp",
        "dataset": str(root.resolve()),
        "settings": settings,
        "analysis": {
            "order_error_rule": "|phase_psp - phase_true| > pi (absolute phase of the highest ladder frequency)",
            "fractions_relative_to": "exact-valid pixels (mask: seen and lit)",
            "height_error": "height_psp - height (mm) on accepted pixels (exact-valid and PSP-valid)",
            "edge_px": edge_px,
            "edge_rule": "within edge_px of an invalid pixel, a depth jump > 4 pixel footprints, or the image border",
            "min_modulation_for_breakdown": used_min_mod,
            "pooled_p99": "from a log-spaced |error| histogram, 0.58 % relative resolution (upper bin edge)",
        },
        **(extra or {}),
        "samples": samples,
        "aggregate": pool.result(len(samples)),
    }
    atomic_write_text(out / "report.json", json_text(report, indent=1, default=json_default))
    return report


# ====================================================================== tables
def _mm_cell(v, spec="{:.4f}"):
    """A length (mm) in a table cell; "-" when undefined."""
    return format_value(spec, v, missing="-")


def _pct(v):
    return "-" if v is None else f"{100 * v:.3f}"


_COLS = [("RMSE mm", "rmse_mm_incl_order_errors", _mm_cell), ("RMSE_ok mm", "rmse_mm_excl_order_errors", _mm_cell),
         ("p99_ok mm", "p99_abs_mm_excl_order_errors", _mm_cell),
         ("max_ok mm", "max_abs_mm_excl_order_errors", _mm_cell),
         ("max mm", "max_abs_mm_incl_order_errors", lambda v: _mm_cell(v, "{:.3f}")),
         ("order err %", "order_error_fraction", _pct), ("rejected %", "rejected_fraction", _pct)]
_LEGEND = ("RMSE/max: all accepted pixels; *_ok: excluding order errors (|phase_psp - phase_true| > pi); "
           "order err %: accepted pixels with a wrong order; rejected %: exact-valid pixels PSP rejected "
           "(both % of exact-valid pixels)")


def _table(header0: str, rows: list[tuple[str, dict]]) -> str:
    head = [header0, "valid px"] + [c[0] for c in _COLS]
    body = [[name, str(r.get("n_valid", "-"))] + [f(r.get(k)) for _, k, f in _COLS] for name, r in rows]
    widths = [max(len(x[i]) for x in [head] + body) for i in range(len(head))]
    line = lambda cells: "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths)))
    return "\n".join([line(head), "  ".join("-" * w for w in widths)] + [line(b) for b in body])


def format_table(report: dict, max_rows: int = 20) -> str:
    """Per-sample rows (the first ``max_rows``) and the pooled row of a :func:`validate_dataset` report."""
    samples, max_rows = report["samples"], max(0, max_rows)
    rows = [(s["id"], s) for s in samples[:max_rows]]
    rows.append((f"all ({len(samples)}, pooled)", report["aggregate"]))
    text = _table("sample", rows)
    if len(samples) > max_rows:
        text += f"\n({len(samples) - max_rows} more samples in report.json)"
    return text + "\n" + _LEGEND


def format_sweep_table(rows: list[dict]) -> str:
    """One pooled row per sweep setting (``rows`` = [{"name", "aggregate"}, ...])."""
    return _table("setting", [(r["name"], r["aggregate"]) for r in rows]) + "\n" + _LEGEND



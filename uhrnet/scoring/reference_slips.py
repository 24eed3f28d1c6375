"""What ``uhrnet evaluate-phase`` says about its reference: patches where the phase-shifting data's own fringe order
slipped by whole periods (:func:`fppsim.phase.reference_check.order_slips`), and every score again without them.

The scores themselves are unchanged: they count every pixel with a phase and light, slipped or not. A slipped patch
is a whole number of periods (``2 pi n`` rad per pixel) off any surface continuous with its surroundings, so a
prediction that is right there is scored wrong; the scores without those pixels say how much of a residual is the
reference's. Measured on FP1523/1201 (the figshare rig's held-out frame): 213 px, 4 periods, beside the right
figurine's shadow; an epoch-4 recipe network's residual 1.850 -> 1.706 rad without them, the orders path's 1.390 ->
1.184 (its ratio to the network 0.751 -> 0.694).
"""

from __future__ import annotations

import numpy as np

from fppsim.phase.reference_check import OrderSlips, order_slips, slip_periods, slips_words

__all__ = ["frame_slips", "slip_scores", "slip_line", "slip_markdown"]


def frame_slips(s, scored: np.ndarray) -> tuple[OrderSlips | None, dict | None]:
    """The slips of frame ``s`` (a :class:`fppsim.dataio.readers.PspMat`) among its ``scored`` pixels, and their
    record (None, None where there are none): the patches holding scored pixels, each with its ``scored_pixels``."""
    slips = order_slips(s.wrapped, s.phase, s.valid)
    mask = slips.mask & scored
    if not mask.any():
        return None, None
    counts = np.bincount(slips.labels[mask], minlength=len(slips.patches) + 1)[1:]
    patches = [{**p, "scored_pixels": int(c)} for p, c in zip(slips.patches, counts) if c]
    return slips, {"pixels": int(mask.sum()), "fraction": float(mask.sum() / max(int(scored.sum()), 1)),
                   "patches": patches}


def slip_scores(fit, phase: np.ndarray, h: np.ndarray, ok: np.ndarray, slips: OrderSlips, **fit_kw) -> dict | None:
    """``fit`` (:func:`uhrnet.scoring.phase_residual.fit_phase`) of the prediction ``h`` and of the flat baseline
    on ``ok`` less the slipped pixels: ``{"prediction": rmse_rad, "flat": rmse_rad}``; None where too few are left."""
    keep = ok & ~slips.mask
    try:
        return {"prediction": fit(phase, h, keep, **fit_kw).rmse_rad,
                "flat": fit(phase, np.zeros_like(h), keep, **fit_kw).rmse_rad}
    except ValueError:
        return None


def slip_line(sid: str, record: dict, models: dict) -> str:
    """One line: where the reference slipped, and each model's residual (and flat's) without those pixels."""
    scores = ", ".join(f"{name} {w['prediction']:.3f} rad (flat {w['flat']:.3f})" if (w := r.get("without_slips"))
                       else f"{name}: too few pixels left to fit" for name, r in models.items()
                       if "without_slips" in r)
    return (f"{sid}: note: the reference's fringe order slips {slips_words(record['patches'], record['pixels'])} "
            f"({record['fraction']:.2%} of the scored), where its own wrapped phase and gradient run on (temporal "
            f"unwrapping wrong there, likely); the scores count them; without them: {scores}")


def slip_markdown(per_image: list[dict]) -> str:
    """A paragraph for phase_results.md listing the frames whose reference slipped (empty when none did)."""
    rows = [r for r in per_image if r.get("reference_slips")]
    if not rows:
        return ""
    md = ("\nReference order slips (patches whose phase-shifting order is whole periods off while its wrapped phase "
          "and gradient run on; `fppsim.phase.reference_check`). The scores above count them; residual (rad) "
          "without them:\n\n| frame | pixels | periods | model | residual | flat |\n"
          "| --- | --- | --- | --- | --- | --- |\n")
    for r in rows:
        rec = r["reference_slips"]
        for name, m in r["models"].items():
            w = m.get("without_slips")
            cells = (f"{w['prediction']:.3f} | {w['flat']:.3f}" if w else "- | -")
            md += f"| {r['id']} | {rec['pixels']} | {slip_periods(rec['patches'])} | {name} | {cells} |\n"
    return md

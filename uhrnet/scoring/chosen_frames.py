"""Which real phase-shifting frames chose a checkpoint: the frames of ``train --val-phase`` folders
(:func:`phase_frames`) and, for ``uhrnet evaluate-phase``, which of the frames it scores chose the checkpoint's
weights (:func:`chosen_frames`, :func:`chosen_on`): a score on them is not held out.

A checkpoint records its frames (``val_phase_frames``: root, id, held out or not, and a content hash,
:meth:`fppsim.dataio.readers.PspMat.digest`); a frame is the same when its content is, so a copied or renamed
folder is recognised. Checkpoints written before the hash compare by folder and id; those written before the
record take every frame of their ``--val-phase`` folders. numpy only (no torch).
"""

from __future__ import annotations

from pathlib import Path

from fppsim.dataio.readers import open_source
from fppsim.errors import PSPMatError
from uhrnet.errors import ConfigError

__all__ = ["phase_frames", "chosen_frames", "chosen_on", "chosen_words"]


def phase_frames(roots, what: str = "--val-phase") -> list[tuple]:
    """``(root, frame id)`` of every frame in the phase-shifting folders ``roots`` (their files are not read);
    :class:`ConfigError` naming ``what`` (the flag) for a folder that holds none or cannot be listed, as
    :class:`uhrnet.scoring.phase_residual.PhaseValidation` refuses it (and a check before a run that will build one)."""
    frames = []
    for root in roots:
        try:
            frames += [(root, sid) for sid in open_source(root).scan_ids()]
        except PSPMatError as exc:
            raise ConfigError(f"{what}: {exc}") from None
    # a folder given twice (or through a link) is one frame: its copy must not be "held out"
    frames = list({(str(Path(r).resolve()), sid): (r, sid) for r, sid in frames}.values())
    if not frames:
        raise ConfigError(f"{what}: no frames given")
    return frames


def _record(ckpt: dict) -> list[dict]:
    """The frames that chose ``ckpt`` (its run's best epoch by ``--val-phase``), else []."""
    roots, best = (ckpt.get("args") or {}).get("val_phase") or [], ckpt.get("best") or {}
    if not roots or best.get("metric") != "val_phase_ratio" or ckpt.get("epoch") != best.get("epoch"):
        return []
    record = ckpt.get("val_phase_frames")
    if record is None:  # written before the record: every frame of its folders
        try:
            record = [{"root": str(Path(r).resolve()), "id": sid, "held_out": False} for r, sid in phase_frames(roots)]
        except ConfigError:  # its folders moved or are gone: nothing to compare with
            return []
    return [f for f in record if not f.get("held_out")]


def chosen_frames(ckpt: dict, root, ids, digests: dict | None = None) -> list[tuple[str, dict]]:
    """``(id, recorded frame)`` for each of ``ids`` of the phase-shifting folder ``root`` that chose ``ckpt``, its
    run's best epoch by ``--val-phase``. ``digests``: id -> :meth:`~fppsim.dataio.readers.PspMat.digest` of the
    frames as read here; a frame with one is the recorded frame of that content (a copy or a renamed folder too);
    one without, or a frame recorded without a hash, is compared by folder and id. Empty for any other checkpoint."""
    chose = _record(ckpt)
    if not chose:
        return []
    here, digests = str(Path(root).resolve()), digests or {}
    by_digest = {f["digest"]: f for f in chose if f.get("digest")}
    out = []
    for sid in ids:
        found = by_digest.get(digests[sid]) if sid in digests else None
        if found is None:  # content differs from every hashed frame: only an unhashed record can name it
            found = next((f for f in chose if f["root"] == here and f["id"] == sid
                          and not (f.get("digest") and sid in digests)), None)
        if found is not None:
            out.append((sid, found))
    return out


def chosen_on(ckpt: dict, root, ids, digests: dict | None = None) -> list[str]:
    """The ids among ``ids`` of the folder ``root`` that chose ``ckpt`` (:func:`chosen_frames`)."""
    return [sid for sid, _ in chosen_frames(ckpt, root, ids, digests)]


def chosen_words(root, matches: list[tuple[str, dict]]) -> str:
    """``a, b of ROOT``, and where some are copies of the recorded frames, ``(the same frames as c of ORIG)``."""
    here = str(Path(root).resolve())
    words = f"{', '.join(sid for sid, _ in matches)} of {root}"
    copies = {}
    for sid, f in matches:
        if (f["root"], f["id"]) != (here, sid):
            copies.setdefault(f["root"], []).append(f["id"])
    if copies:
        words += " (the same frames as " + "; ".join(f"{', '.join(i)} of {r}" for r, i in copies.items()) + ")"
    return words

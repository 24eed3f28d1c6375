"""evaluate-phase says when it scores a checkpoint on the frames that chose it (``train --val-phase``): such a
score is not held out. Checkpoints as dicts (no training), frames written with fppsim's writer."""

from __future__ import annotations

import numpy as np

from fppsim.dataio.writers import save_psp_folder_sample, sums_from_phase
from uhrnet.scoring.phase_residual import chosen_on


def _frames(root, ids):
    xx = np.arange(48)[None, :] * np.ones((32, 1))
    valid = np.ones(xx.shape, bool)
    for sid in ids:
        image = (120 + 80 * np.cos(2 * np.pi * xx / 11.6)).astype(np.uint8)
        save_psp_folder_sample(root, sid, *sums_from_phase(1.0 + 2 * np.pi * xx / 11.6, valid, 30.0), image)


def _ckpt(roots, epoch=3, best_epoch=3, record=None):
    ck = {"args": {"val_phase": [str(r) for r in roots]}, "epoch": epoch,
          "best": {"metric": "val_phase_ratio", "value": 0.5, "epoch": best_epoch}}
    if record is not None:
        ck["val_phase_frames"] = record
    return ck


def test_chosen_on_names_the_frames_that_chose_best(tmp_path):
    root = tmp_path / "val"
    _frames(root, ["a", "b", "c"])
    here = str(root.resolve())
    record = [{"root": here, "id": "a", "held_out": False}, {"root": here, "id": "b", "held_out": True},
              {"root": here, "id": "c", "held_out": False}]
    assert chosen_on(_ckpt([root], record=record), root, ["a", "b", "c"]) == ["a", "c"]  # b was held out
    assert chosen_on(_ckpt([root], record=record), tmp_path / "val" / ".." / "val", ["b", "c"]) == ["c"]
    assert chosen_on(_ckpt([root], record=record), tmp_path / "other", ["a"]) == []
    # a checkpoint of another epoch than the best (last.pt) was not chosen on them; nor one without --val-phase
    assert chosen_on(_ckpt([root], epoch=4, record=record), root, ["a"]) == []
    assert chosen_on({"args": {"val_phase": []}, "epoch": 1, "best": {"metric": "val_rmse_mm", "epoch": 1}},
                     root, ["a"]) == []
    # a checkpoint written before the record: every frame of its --val-phase folders; gone folders: nothing
    assert chosen_on(_ckpt([root]), root, ["a", "b"]) == ["a", "b"]
    assert chosen_on(_ckpt([tmp_path / "gone"]), root, ["a"]) == []

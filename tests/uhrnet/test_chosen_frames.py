"""evaluate-phase says when it scores a checkpoint on the frames that chose it (``train --val-phase``): such a
score is not held out. Checkpoints as dicts (no training), frames written with fppsim's writer."""

from __future__ import annotations

import numpy as np

from fppsim.dataio.writers import save_psp_folder_sample, sums_from_phase
from uhrnet.scoring.chosen_frames import chosen_on


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


def test_a_copy_of_a_frame_that_chose_best_is_recognised_by_its_content(tmp_path):
    """A frame's record holds a hash of its arrays: a copy in another folder, under another id, is the same frame
    (read with another convention too); a frame with other content at the recorded path is not. A record without
    hashes, or a frame not read here, compares folder and id as before."""
    import shutil

    from fppsim.dataio.readers import open_source
    from uhrnet.scoring.chosen_frames import chosen_words

    def digests(root, ids, **kw):
        return {sid: open_source(root).scan(sid, **kw).digest() for sid in ids}

    root = tmp_path / "val"
    _frames(root, ["a", "b"])
    xx = np.arange(48)[None, :] * np.ones((32, 1))
    save_psp_folder_sample(root, "b", *sums_from_phase(2.0 + 2 * np.pi * xx / 9.0, np.ones(xx.shape, bool), 30.0),
                           np.full(xx.shape, 90, np.uint8))  # b: another frame than a
    here, got = str(root.resolve()), digests(root, ["a", "b"])
    record = [{"root": here, "id": "a", "held_out": False, "digest": got["a"]},
              {"root": here, "id": "b", "held_out": True, "digest": got["b"]}]
    assert got["a"] != got["b"]
    copy = tmp_path / "elsewhere" / "renamed"
    shutil.copytree(root, copy)
    for sub in ("PSin", "PCos", "Fringe", "iPattern"):
        (copy / sub / "a.mat").rename(copy / sub / "z.mat")
    # independent truth: the copy's files are the recorded frame's, byte for byte
    assert (copy / "PSin" / "z.mat").read_bytes() == (root / "PSin" / "a.mat").read_bytes()
    ck = _ckpt([root], record=record)
    for kw in ({}, {"negate_sin": True}, {"convention": "fppsim"}):
        assert chosen_on(ck, copy, ["b", "z"], digests(copy, ["b", "z"], **kw)) == ["z"], kw  # b was held out
    assert chosen_on(ck, copy, ["b", "z"]) == []  # not read here: by folder and id
    assert chosen_on(ck, root, ["a", "b"]) == ["a"]
    matches = [("z", record[0])]
    assert chosen_words(copy, matches) == f"z of {copy} (the same frames as a of {here})"
    # the recorded path now holding other content is another frame
    save_psp_folder_sample(root, "a", *sums_from_phase(0.5 + 2 * np.pi * xx / 13.0, np.ones(xx.shape, bool), 30.0),
                           np.full(xx.shape, 100, np.uint8))
    assert chosen_on(ck, root, ["a", "b"], digests(root, ["a", "b"])) == []
    # a record without hashes (a checkpoint written before them): folder and id, as before
    old = _ckpt([root], record=[{k: v for k, v in f.items() if k != "digest"} for f in record])
    assert chosen_on(old, root, ["a", "b"], digests(root, ["a", "b"])) == ["a"]
    assert chosen_on(old, copy, ["z"], digests(copy, ["z"])) == []

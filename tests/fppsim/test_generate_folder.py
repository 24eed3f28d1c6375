"""`fppsim generate` / `merge` and the --out folder: never a file it did not write, nothing left by a failed run,
one format and one sample set per folder, the seed range, the help, the manifest's object count (QA, stop 67)."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from fppsim.cli import main
from fppsim.dataio.formats import manifest_record, read_manifest, reconcile
from fppsim.errors import SampleError, UsageError
from fppsim.owned import RECORD
from _helpers import one_line

MESH = Path(__file__).resolve().parents[2] / "assets" / "meshes" / "bust_s0.ply"


def _gen(out, *extra, count=2):
    return main(["generate", "-q", "--meshes", str(MESH), "--out", str(out), "--count", str(count), "--no-psp", *extra])


def _tree(folder: Path) -> dict:
    """Every file under ``folder`` with its bytes (folders as None)."""
    return {p.relative_to(folder).as_posix(): (p.read_bytes() if p.is_file() else None) for p in folder.rglob("*")}


# ------------------------------------------------------------------------------------ 4: the seed
def test_a_negative_seed_is_a_usage_error_before_anything_is_written(tmp_path, capsys):
    for cmd in (["generate", "--meshes", str(MESH), "--count", "2"], ["validate-psp", "--meshes", str(MESH), "--count", "1"]):
        with pytest.raises(SystemExit) as e:
            main([*cmd, "--out", str(tmp_path / "gs"), "--seed", "-1"])
        assert e.value.code == 2
        assert "--seed: expected an integer >= 0, got -1" in capsys.readouterr().err
    assert not (tmp_path / "gs").exists()
    from fppsim.generation import GenerateConfig, generate_dataset

    with pytest.raises(UsageError, match="--seed must be an integer >= 0"):
        GenerateConfig(meshes=[str(MESH)], out=tmp_path / "gs", count=1, seed=-1)
    with pytest.raises(ValueError, match="--seed must be an integer >= 0"):
        generate_dataset([str(MESH)], tmp_path / "gs", 1, seed=-1)
    assert not (tmp_path / "gs").exists()
    # numpy's SeedSequence takes any integer >= 0, however large
    assert GenerateConfig(meshes=[str(MESH)], out=tmp_path / "gs", count=1, seed=10 ** 20).seed == 10 ** 20


# ------------------------------------------------------------------------------------ 5: help
def test_help_states_the_defaults(capsys):
    with pytest.raises(SystemExit):
        main(["generate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "pixel centres; default 1)" in text and "(default -100, the reference code's)" in text


# ------------------------------------------------------------------------------------ 6: the manifest's counts
def test_manifest_counts_objects_and_pedestals_apart(tmp_path):
    meta = {"index": 0, "seed": 0, "stats": {"valid_fraction": 0.5},
            "objects": [{"mesh": "a.ply"}, {"mesh": "pedestal:1"}, {"mesh": "procedural:bust:3"}]}
    rec = manifest_record("000000", meta)
    assert (rec["objects"], rec["pedestals"]) == (2, 1)
    # a manifest written before the split is rebuilt from meta.json, never left mixed
    (tmp_path / "000000").mkdir()
    (tmp_path / "000000" / "meta.json").write_text(json.dumps(meta))
    (tmp_path / "manifest.jsonl").write_text(json.dumps({"id": "000000", "index": 0, "seed": 0, "objects": 3}) + "\n")
    assert [(r["objects"], r["pedestals"]) for r in reconcile(tmp_path)] == [(2, 1)]


def test_generated_manifest_objects_follow_objects_flag(tmp_path):
    out = tmp_path / "g"
    assert _gen(out, "--objects", "2", "--pedestal", "1", "--no-preview", count=1) == 0
    rec = read_manifest(out)[0]
    meta = json.loads((out / "000000" / "meta.json").read_text())
    assert rec["objects"] == 2 and rec["objects"] + rec["pedestals"] == len(meta["objects"])

"""uhrnet.workflows.stages.read_config_file, the one reader of experiment files (pipelines/scaling.py's
--arms-file, sim2real's --ablation): whatever the path holds, one line through the caller's error class."""

import os
from pathlib import Path

import pytest

from uhrnet.workflows.scaling.arms import UsageProblem, load_arms
from uhrnet.workflows.sim2real.variants import load_variants
from uhrnet.workflows.stages import read_config_file
from uhrnet.errors import Sim2RealError

ROOT = Path(__file__).resolve().parents[1]


class Problem(Exception):
    pass


def _one_line(exc) -> str:
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


@pytest.mark.parametrize("content, message", [
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff\xfe", "not a text YAML/JSON file"),
    (bytes(range(256)), "not a text YAML/JSON file"),
    (b"a: [1, 2", "not valid YAML/JSON"),
    (b"when: 2020-13-45", "not valid YAML/JSON"),  # YAML's date constructor raises ValueError
    (b"a: \x00", "not valid YAML/JSON"),  # UTF-8, but a character YAML refuses
])
def test_a_file_that_is_not_yaml_text_is_one_line(tmp_path, content, message):
    f = tmp_path / "arms.yaml"
    f.write_bytes(content)
    with pytest.raises(Problem) as exc:
        read_config_file(f, "arms file", Problem)
    assert _one_line(exc).startswith(f"{f}: {message}")


def test_a_folder_or_a_missing_file_is_named_as_such(tmp_path):
    with pytest.raises(Problem) as exc:
        read_config_file(tmp_path, "arms file", Problem)
    assert _one_line(exc) == f"{tmp_path}: is a folder; give the YAML/JSON file"
    with pytest.raises(Problem) as exc:
        read_config_file(tmp_path / "nope.yaml", "arms file", Problem)
    assert _one_line(exc) == f"arms file not found: {tmp_path / 'nope.yaml'}"
    if os.path.exists("/dev/null"):
        with pytest.raises(Problem, match="not a regular file"):
            read_config_file("/dev/null", "arms file", Problem)
    (tmp_path / "ok.json").write_text('{"arms": [{"name": "x"}]}')
    assert read_config_file(tmp_path / "ok.json", "arms file", Problem) == {"arms": [{"name": "x"}]}


def test_the_callers_refuse_them_in_one_line(tmp_path):
    binary = tmp_path / "arms.bin"
    binary.write_bytes(b"\xff\xd8\xff\xe0JFIF\x00")
    for path, message in ((binary, "not a text YAML/JSON file"), (tmp_path, "is a folder")):
        with pytest.raises(UsageProblem, match=message):
            load_arms(path)
        with pytest.raises(Sim2RealError, match=message):
            load_variants(path)

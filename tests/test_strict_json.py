"""Every JSON file the tools write is strict JSON: a non-finite number is null (fppsim.files.json_text), never the
bare NaN / Infinity Python's json module writes by default, which strict parsers refuse."""

import ast
import json
import math
from pathlib import Path

import numpy as np
import pytest

from fppsim.dataio.encoding import json_default
from fppsim.files import finite_or_null, json_text

ROOT = Path(__file__).resolve().parents[1]


def strict_loads(text: str):
    """json.loads refusing NaN / Infinity / -Infinity, as a strict parser (JavaScript's JSON.parse, jq) does."""
    return json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))


def test_pythons_own_json_is_not_strict_and_json_text_is():
    doc = {"nan": float("nan"), "inf": np.float32("inf"), "ninf": -math.inf, "f64": np.float64("nan"),
           "arr": np.array([1.5, np.nan]), "nested": [{"t": (2.0, float("nan"))}], "ok": 0.1, "n": 3, "b": True,
           "none": None, "path": Path("/x"), "i64": np.int64(7)}
    with pytest.raises(ValueError):  # the truth this fixes: what json.dumps writes, a strict parser refuses
        strict_loads(json.dumps({"nan": float("nan")}))
    back = strict_loads(json_text(doc, indent=1, default=json_default))
    assert back == {"nan": None, "inf": None, "ninf": None, "f64": None, "arr": [1.5, None],
                    "nested": [{"t": [2.0, None]}], "ok": 0.1, "n": 3, "b": True, "none": None, "path": "/x", "i64": 7}
    assert finite_or_null([float("inf"), "NaN"]) == [None, "NaN"]  # strings stay strings


def test_a_value_that_slips_through_fails_loudly():
    class Odd:  # a default that hands back a non-finite float after the walk would be caught by allow_nan=False
        pass

    assert json_text({"x": Odd()}, default=lambda o: float("nan")) == '{"x": null}'
    with pytest.raises(TypeError):
        json_text({"x": Odd()})


def _writes(call: ast.Call) -> bool:
    name = getattr(call.func, "attr", getattr(call.func, "id", None))
    return name in ("atomic_write_text", "write_text", "write", "print")


def test_no_tool_writes_json_dumps_to_a_file_without_refusing_nan():
    """A json.dumps handed to a file write, or printed (pipelines print JSON lines that other tools parse), must pass
    allow_nan=False (json_text does, after turning NaN into null)."""
    offenders = []
    for pkg in ("fppsim", "uhrnet", "pipelines"):
        for path in sorted((ROOT / pkg).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if not (isinstance(node, ast.Call) and _writes(node)):
                    continue
                for inner in ast.walk(node):
                    if isinstance(inner, ast.Call) and isinstance(inner.func, ast.Attribute) \
                            and inner.func.attr == "dumps" and getattr(inner.func.value, "id", "") == "json":
                        strict = any(k.arg == "allow_nan" and isinstance(k.value, ast.Constant)
                                     and k.value.value is False for k in inner.keywords)
                        if not strict:
                            offenders.append(f"{path.relative_to(ROOT)}:{inner.lineno}")
    assert not offenders, offenders


def test_the_pipelines_json_on_stdout_is_strict():
    """gpu_bench.py's step previews and orders_study.py's line per seed were plain json.dumps: a NaN timing, or the
    ratio of a zero network residual, came out as a bare NaN / Infinity."""
    from _helpers import load_pipeline

    shown = load_pipeline("gpu_bench").shown
    assert shown({"ms": float("nan"), "ok": 1.5}) == '{"ms": null, "ok": 1.5}'
    assert strict_loads(shown({"steps": {"fp16": {"ms": np.float32("inf")}}}, 4000, indent=1)) == {
        "steps": {"fp16": {"ms": None}}}
    row = {"pair": {"depth": {"orders": float("nan")}}, "frames": {"1201": {"ratio": math.inf}, "541": {"ratio": 0.5}}}
    line = load_pipeline("orders_study").progress_line(3, row)
    assert strict_loads(line) == {"seed": 3, "pair_depth": None, "frames": {"1201": None, "541": 0.5}}

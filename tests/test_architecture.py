"""docs/ARCHITECTURE.md stays true: every module has one row in its tables, and every module, name, file and
folder the page names exists (issue 48: the map had modules in the wrong table and named ones that were gone)."""

import importlib
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "ARCHITECTURE.md"
PACKAGES = ("fppsim", "uhrnet")


def _modules() -> set[str]:
    out = set()
    for pkg in PACKAGES:
        for f in (ROOT / pkg).rglob("*.py"):
            parts = f.relative_to(ROOT).with_suffix("").parts
            out.add(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return out


def _table_modules(text: str) -> list[str]:
    section = text[text.index("### The modules, one row each"):text.index("## Rules the code keeps")]
    return re.findall(r"^\| `((?:fppsim|uhrnet)[\w.]*)` \|", section, flags=re.M)


def test_every_module_has_exactly_one_row():
    named = _table_modules(DOC.read_text())
    twice = sorted({m for m in named if named.count(m) > 1})
    assert not twice, f"named twice in ARCHITECTURE.md: {twice}"
    actual = _modules()
    assert not sorted(actual - set(named)), f"modules without a row in ARCHITECTURE.md: {sorted(actual - set(named))}"
    assert not sorted(set(named) - actual), f"rows for modules that do not exist: {sorted(set(named) - actual)}"


def _inline_code(text: str) -> list[str]:
    """The page's inline code spans (fenced blocks dropped first: their triple backticks would pair wrongly)."""
    return re.findall(r"`([^`\n]+)`", re.sub(r"```.*?```", "", text, flags=re.S))


def _resolves(dotted: str) -> bool:
    parts = dotted.split(".")
    if "__main__" in parts:  # importing it would run the command line: the file is what must exist
        return (ROOT / Path(*parts).with_suffix(".py")).is_file()
    for k in range(len(parts), 0, -1):  # the longest importable prefix, then attributes
        try:
            obj = importlib.import_module(".".join(parts[:k]))
        except ImportError:
            continue
        try:
            for name in parts[k:]:
                obj = getattr(obj, name)
        except AttributeError:
            return False
        return True
    return False


def test_every_dotted_name_the_page_uses_exists():
    spans = _inline_code(DOC.read_text())
    names = {m for s in spans for m in re.findall(r"\b(?:fppsim|uhrnet)(?:\.[A-Za-z_]\w*)+", s)}
    assert len(names) > 100  # the page names most of the code: a parsing slip would pass everything
    missing = sorted(n for n in names if not _resolves(n))
    assert not missing, f"ARCHITECTURE.md names what does not exist: {missing}"


def test_every_path_the_page_names_exists():
    spans = _inline_code(DOC.read_text())
    paths = {m.rstrip("/") for s in spans
             for m in re.findall(r"\b(?:fppsim|uhrnet|tests|pipelines|docs|assets)/[\w./-]*", s)
             if "<" not in s and "*" not in s}
    assert len(paths) > 10
    missing = sorted(p for p in paths if not (ROOT / p).exists())
    assert not missing, f"ARCHITECTURE.md names paths that do not exist: {missing}"

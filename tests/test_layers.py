"""Architecture rules: every module imports on its own, no import cycles, the library never imports a CLI."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("fppsim", "uhrnet")


def _modules():
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            yield ".".join(parts[:-1] if parts[-1] == "__init__" else parts), path


def _imported(path: Path, module: str) -> set[str]:
    """Absolute names of the fppsim/uhrnet modules ``path`` imports (at any depth of the file)."""
    tree = ast.parse(path.read_text())
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[:len(parts) - node.level + 1] + ([base] if base else []))
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names)
    return {m for m in out if m.split(".")[0] in PACKAGES}


def _is_cli(module: str) -> bool:
    """The command-line layer: ``cli`` and ``__main__`` modules."""
    last = module.split(".")[-1]
    return last in ("cli", "__main__")


def test_library_modules_never_import_a_cli_module():
    offenders = []
    for module, path in _modules():
        if _is_cli(module):
            continue
        bad = sorted(m for m in _imported(path, module)
                     if any(_is_cli(".".join(m.split(".")[:k])) for k in range(2, len(m.split(".")) + 1)))
        if bad:
            offenders.append(f"{module} imports {bad}")
    assert not offenders, offenders


def test_every_module_imports_alone_in_a_fresh_interpreter():
    """A cycle (a module needing a partly-initialised other one) fails when that module is imported first."""
    names = [m for m, _ in _modules() if not m.endswith("__main__")]
    code = ("import importlib, sys\n"
            f"for name in {names!r}:\n"
            "    for m in [k for k in sys.modules if k.split('.')[0] in ('fppsim', 'uhrnet')]:\n"
            "        del sys.modules[m]\n"
            "    importlib.import_module(name)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]


def test_library_entry_points_exist():
    import fppsim
    import uhrnet

    assert callable(fppsim.generate) and callable(fppsim.validate_psp)
    assert callable(uhrnet.train) and callable(uhrnet.evaluate) and callable(uhrnet.predict)


def test_the_command_line_lives_in_one_module_per_package():
    extra = sorted(m for m, _ in _modules() if m.split(".")[-1].startswith("cli") and m.split(".")[-1] != "cli")
    assert not extra, extra

"""Architecture rules: every module imports on its own, no import cycles, the library never imports a CLI
nor runs a subprocess, no library module over 650 lines, one definition of each shared helper, no
private name used across modules, a command framework that names no package, rendering code imported in
uhrnet only by the workflow layer (``uhrnet.workflows``), which only the command layer imports."""

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


# ---------------------------------------------------------------------------- seams (issue 24)
MAX_LINES = 650
ONE_DEFINITION = ("check_seed", "plane_level", "poly_basis", "open_dataset", "open_labelled", "open_source", "mean_phasor", "circular_median",
                  "lowpass", "demodulate",
                  "demodulated_residual", "object_residual", "phase_at_height", "ray_cut")
TWINS = {"wrap": ["fppsim/phase/__init__.py", "uhrnet/physics/rig_layer.py"], "circular_mean": ["fppsim/phase/__init__.py", "uhrnet/physics/rig_layer.py"],
         "_wrap": [], "wrap_phase": []}
"""Phase helpers: one numpy definition (fppsim.phase) and one torch twin (uhrnet.physics.rig_layer), no private copies."""


def _library_modules():
    return [(m, p) for m, p in _modules() if not _is_cli(m)]


def test_no_library_module_imports_subprocess():
    """Library code calls functions; only command lines and pipelines/ start processes."""
    offenders = []
    for module, path in _library_modules():
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            if any(n == "subprocess" or n.startswith("subprocess.") for n in names):
                offenders.append(f"{module}:{node.lineno}")
    assert not offenders, offenders


def test_no_library_module_is_longer_than_the_limit():
    long = {m: n for m, p in _library_modules() if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"split along a seam (limit {MAX_LINES} lines): {long}"


MAX_FUNCTION_LINES = 100


def test_no_library_function_is_longer_than_the_limit():
    """A function over 100 lines (its def line to its last, docstring included) is split into its steps (as
    orders.choose_orders was); sim2real's run_sim2real grew to 101 unnoticed."""
    long = [f"{m}.{node.name}: {node.end_lineno - node.lineno + 1}" for m, p in _library_modules()
            for node in ast.walk(ast.parse(p.read_text())) if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
            and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES]
    assert not long, f"split into steps (limit {MAX_FUNCTION_LINES} lines): {long}"


def test_shared_helpers_are_defined_once():
    """One plane level, one polynomial plane basis, one name per dataset opener (a torch Dataset:
    ``uhrnet.data.datasets.open_dataset``; a numpy reader: ``fppsim.dataio.readers.open_labelled``), one home for the phase
    helpers and the camera ray cut at a height."""
    where: dict[str, list[str]] = {name: [] for name in ONE_DEFINITION + tuple(TWINS)}
    for pkg in PACKAGES + ("pipelines",):
        for path in sorted((ROOT / pkg).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.name in where:
                    where[node.name].append(f"{path.relative_to(ROOT)}:{node.lineno}")
    twins = {k: sorted(p.split(":")[0] for p in where.pop(k)) for k in TWINS}
    assert twins == TWINS, twins
    assert {k: len(v) for k, v in where.items()} == {k: 1 for k in where}, where
    assert where["open_dataset"][0].startswith("uhrnet/data/datasets.py") and where["open_labelled"][0].startswith("fppsim/dataio/readers/")
    assert where["plane_level"][0].startswith("fppsim/phase/plane.py") and where["poly_basis"][0].startswith("fppsim/phase/plane.py")
    assert where["circular_median"][0].startswith("fppsim/phase/__init__.py")
    assert where["check_seed"][0].startswith("fppsim/errors.py")  # below both packages' rendering and training


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def test_no_module_uses_a_private_name_of_another_module():
    """``_name`` is private to its module: nothing imports it, nothing reaches it as ``module._name``, and
    no module of ours has a private name (anything shared across modules is public)."""
    offenders = []
    for module, path in _modules():
        tree = ast.parse(path.read_text())
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        aliases = set()  # names bound to our modules
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")
                    base = ".".join(parts[:len(parts) - node.level + 1] + ([base] if base else []))
                if base.split(".")[0] not in PACKAGES:
                    continue
                if any(_private(p) for p in base.split(".")):
                    offenders.append(f"{module}:{node.lineno} imports from {base}")
                for a in node.names:
                    if _private(a.name):
                        offenders.append(f"{module}:{node.lineno} imports {base}.{a.name}")
                    aliases.add(a.asname or a.name)
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.split(".")[0] in PACKAGES:
                        if any(_private(p) for p in a.name.split(".")):
                            offenders.append(f"{module}:{node.lineno} imports {a.name}")
                        aliases.add(a.asname or a.name.split(".")[0])
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and _private(node.attr) and isinstance(node.value, ast.Name) \
                    and node.value.id in aliases:
                offenders.append(f"{module}:{node.lineno} uses {node.value.id}.{node.attr}")
    assert not offenders, offenders


def test_the_command_framework_names_no_package():
    """``fppsim.commands`` serves both command lines: error classes come in as arguments, and no string
    of it names a module of either package."""
    tree = ast.parse((ROOT / "fppsim" / "commands.py").read_text())
    strings = [n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)]
    docstrings = {ast.get_docstring(n, clean=False) for n in ast.walk(tree)
                  if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef))}
    named = [s for s in strings if s not in docstrings and any(f"{p}." in s or s == p for p in PACKAGES)]
    assert not named, named
    allowed = {"fppsim.files", "fppsim.files.signals_raise", "fppsim.files.command_named"}  # fppsim.files alone
    assert _imported(ROOT / "fppsim" / "commands.py", "fppsim.commands") <= allowed


# ---------------------------------------------------------------------------- import cycles (issue 29)
def _import_graph() -> dict[str, set[str]]:
    """Module -> the fppsim/uhrnet modules it imports, at ANY depth of the file (module level, functions,
    ``if`` blocks). ``from pkg import name`` depends on ``pkg.name`` when that is a module, else on ``pkg``."""
    mods = dict(_modules())
    graph = {}
    for module, path in mods.items():
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")
                    base = ".".join(parts[:len(parts) - node.level + 1] + ([base] if base else []))
                names = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
            else:
                continue
            for name in names:
                parts = name.split(".")
                hit = next((".".join(parts[:k]) for k in range(len(parts), 0, -1) if ".".join(parts[:k]) in mods), None)
                if hit and hit != module:
                    deps.add(hit)
        graph[module] = deps
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycle_at_any_depth():
    """No two modules import each other, directly or through others, at any depth: an import inside a
    function hides a cycle from the fresh-interpreter test above but not from this one. (An import
    inside a function is only for an optional heavy dependency: SciPy, torch, pyrender, matplotlib...)"""
    assert _cycles(_import_graph()) == KNOWN_CYCLES


KNOWN_CYCLES: list = []  # none; nothing may be added here


# ---------------------------------------------------------------------------- the workflow layer (issue 29)
WORKFLOWS = ("uhrnet.workflows",)
"""Experiments that compose both packages (render with fppsim, train and evaluate with uhrnet): above the
library, below the commands."""
COMMAND_LAYER = ("uhrnet.cli",)
"""The only package modules that may import the workflow layer (``pipelines/`` and tests may too)."""
RENDERING = ("fppsim.generation", "fppsim.rendering.render", "fppsim.rendering.scene", "fppsim.rendering.shapes", "fppsim.rendering.meshio", "fppsim.geometry.jitter",
             "fppsim.rendering.synth", "fppsim.rendering.optics", "fppsim.rendering.preview", "fppsim.validate", "fppsim.fitting.fit_optics")
"""fppsim's rendering side (docs/ARCHITECTURE.md's data flow: scenes, depth rendering, image formation, one
sample, a whole run; and what renders to validate or fit the simulator)."""


def _within(module: str, prefixes: tuple[str, ...]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def test_uhrnet_imports_rendering_code_only_in_the_workflow_layer():
    """No uhrnet module outside ``uhrnet.workflows`` imports a rendering module of fppsim, at any depth of
    the file (imports inside functions too); and no uhrnet library module (the command layer aside) reaches
    one through other modules either."""
    graph = _import_graph()
    assert all(m in graph for m in RENDERING), [m for m in RENDERING if m not in graph]  # the list names modules
    outside = [m for m in graph if m.split(".")[0] == "uhrnet" and not _within(m, WORKFLOWS)]
    direct = {m: sorted(d for d in graph[m] if _within(d, RENDERING)) for m in outside}
    assert not {m: d for m, d in direct.items() if d}, {m: d for m, d in direct.items() if d}
    reached = {}
    for module in outside:
        if _is_cli(module):
            continue
        seen, todo = set(), [module]
        while todo:
            for dep in graph.get(todo.pop(), ()):
                if dep not in seen:
                    seen.add(dep)
                    todo.append(dep)
        if bad := sorted(d for d in seen if _within(d, RENDERING)):
            reached[module] = bad
    assert not reached, reached


def test_only_the_command_layer_imports_the_workflow_layer():
    """No library module (fppsim, uhrnet outside ``uhrnet.workflows``) imports the workflow layer, at any
    depth, nor names it in a string (a lazy attribute table, ``importlib.import_module``); ``uhrnet.cli`` may."""
    graph = _import_graph()
    offenders = [f"{m} imports {sorted(d for d in deps if _within(d, WORKFLOWS))}" for m, deps in graph.items()
                 if not _within(m, WORKFLOWS + COMMAND_LAYER) and any(_within(d, WORKFLOWS) for d in deps)]
    for module, path in _modules():
        if _within(module, WORKFLOWS + COMMAND_LAYER):
            continue
        tree = ast.parse(path.read_text())
        docstrings = {ast.get_docstring(n, clean=False) for n in ast.walk(tree)
                      if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef))}
        offenders += [f"{module} names {n.value!r}" for n in ast.walk(tree)
                      if isinstance(n, ast.Constant) and isinstance(n.value, str) and n.value not in docstrings
                      and _within(n.value, WORKFLOWS)]
    assert not offenders, offenders


def test_no_experiment_package_in_the_library():
    """The sim-to-real experiment lives in ``uhrnet.workflows.sim2real``; no ``uhrnet.sim2real`` shim."""
    assert not list((ROOT / "uhrnet" / "sim2real").glob("*.py"))
    assert (ROOT / "uhrnet" / "workflows" / "sim2real" / "__init__.py").is_file()


# The names of the data layouts on disk (sub-folders and files). A string constant EQUAL to one of them
# is code that recognises (or writes) that layout; docstrings, help and messages only mention them
# inside longer text, so they are not counted.
LAYOUT_NAMES = {"PSin", "PCos", "Fringe", "iPattern", "f1_80.npy", "Z.npy", "fringe_pattern.npy", "height_map.npy"}
LAYOUT_HOMES = ("fppsim/dataio/readers/", "fppsim/dataio/formats.py", "fppsim/dataio/writers.py")


def test_data_layouts_are_recognised_only_by_the_readers():
    """Which layout a path holds is decided in one place (``fppsim.dataio.readers.open_source``, on the names the
    contract ``fppsim.dataio.formats`` and ``fppsim.dataio.readers.psp_mat`` define); the writers write the same names.
    No other module names a layout's file or folder: it asks the readers (or uses ``FIGSHARE_PAIRS``)."""
    found = []
    for _, path in _modules():
        rel = path.relative_to(ROOT).as_posix()
        if rel.startswith(LAYOUT_HOMES):
            continue
        found += [f"{rel}:{node.lineno} {node.value!r}" for node in ast.walk(ast.parse(path.read_text()))
                  if isinstance(node, ast.Constant) and node.value in LAYOUT_NAMES]
    assert not found, found
    # and the phase-shifting folder is recognised by one function (is_psp_folder), called only by open_source
    callers = set()
    for _, path in _modules():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", None)) == "is_psp_folder":
                callers.add(path.relative_to(ROOT).as_posix())
    assert callers == {"fppsim/dataio/readers/source.py"}, callers


# ---------------------------------------------------------------------------- stage order (issue 37)
def _stated_order() -> dict[str, list[str]]:
    """The order ARCHITECTURE.md states (the two lines after its ``<!-- layers -->`` mark), bottom first."""
    text = (ROOT / "docs" / "ARCHITECTURE.md").read_text()
    block = text.split("<!-- layers -->", 1)[1].split("```")[1]
    order = {}
    for line in block.strip().splitlines():
        pkg, _, chain = line.partition(":")
        names = [n.strip() for n in chain.split("<")]
        order[pkg.strip()] = [pkg.strip() if n == pkg.strip() else f"{pkg.strip()}.{n}" for n in names]
    return order


def _stage(module: str) -> str:
    """The stage a module belongs to: its package's sub-folder, or the top-level module itself (a name
    imported from the package itself, such as ``__version__``, is the package)."""
    parts = module.split(".")
    if len(parts) == 1 or not ((ROOT / parts[0] / parts[1]).is_dir() or (ROOT / parts[0] / f"{parts[1]}.py").is_file()):
        return parts[0]
    return ".".join(parts[:2])


def test_stage_folders_flow_one_way_in_the_stated_order():
    order = _stated_order()
    assert set(order) == set(PACKAGES)
    upward, unplaced = [], set()
    for module, path in _modules():
        pkg, here = module.split(".")[0], _stage(module)
        if here not in order[pkg]:
            unplaced.add(here)
            continue
        for target in _imported(path, module):
            if target.split(".")[0] != pkg:
                if pkg == "fppsim":
                    upward.append(f"{module} imports {target} (fppsim never imports uhrnet)")
                continue
            there = _stage(target)
            if there not in order[pkg]:
                unplaced.add(there)
            elif order[pkg].index(there) > order[pkg].index(here):
                upward.append(f"{module} ({here}) imports {target} ({there}), which stands above it")
    assert not unplaced, f"stages missing from ARCHITECTURE.md's order: {sorted(unplaced)}"
    assert not upward, upward


# ---------------------------------------------------------------------------- one reader per layout (issue 37)
LAYOUT_FILES = {"manifest.jsonl", "dataset.json", "f1_80.npy", "Z.npy", "fringe_pattern.npy", "height_map.npy",
                "native", "PSin", "PCos", "Fringe", "iPattern", "arrays.npz", "fringe.png"}
KIND_NAMES = {"image", "npy", "file", "missing", "psp", "ipattern", "psp-partial", "figshare", "real-sample", "native",
              "folder"}


def test_layouts_are_known_only_to_their_readers():
    """Outside fppsim/dataio no code tests a layout: no path joined with a layout's file name (``p / "native"``,
    ``p / "manifest.jsonl"``), no comparison with one, and no test of a reader's ``.kind``
    (messages and docstrings may name the files)."""
    offenders = []
    for module, path in _modules():
        if module.startswith("fppsim.dataio") or _is_cli(module):
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            consts = []
            if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
                consts = [n for n in (node.left, node.right) if isinstance(n, ast.Constant)]
            elif isinstance(node, ast.Compare):
                sides = [node.left, *node.comparators]
                if any(isinstance(n, ast.Attribute) and n.attr == "kind" and not (
                        isinstance(n.value, ast.Attribute) and n.value.attr == "dtype") for n in sides):
                    offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}: tests a reader's .kind")
                consts = [n for n in sides if isinstance(n, ast.Constant)]
                consts += [e for n in sides if isinstance(n, (ast.Tuple, ast.List, ast.Set)) for e in n.elts
                           if isinstance(e, ast.Constant)]
            for c in consts:
                if isinstance(c.value, str) and c.value in LAYOUT_FILES:
                    offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}: layout name {c.value!r}")
    assert not offenders, offenders


# ---------------------------------------------------------------------------- registries (issue 37)
HEAD_NAMES = {"phase", "height"}  # and every registered head (the test adds them)


def test_neither_the_trainer_nor_build_model_names_a_head():
    """Everything head-specific goes through ``uhrnet.models.heads.HEADS`` (what a head needs, how it wraps a
    backbone, its options, its training loss): no head's name is a string in ``uhrnet/training/trainer.py`` or in
    ``build_model`` (docstrings aside), so adding a head never edits them."""
    from uhrnet.models.heads import HEADS

    names = HEAD_NAMES | set(HEADS)
    models = ast.parse((ROOT / "uhrnet" / "models" / "__init__.py").read_text())
    build = [n for n in models.body if isinstance(n, ast.FunctionDef) and n.name == "build_model"]
    assert len(build) == 1
    places = {"uhrnet/training/trainer.py": ast.parse((ROOT / "uhrnet" / "training" / "trainer.py").read_text()),
              "uhrnet/models/__init__.py build_model": build[0]}
    found = []
    for where, tree in places.items():
        docstrings = {ast.get_docstring(n, clean=False) for n in ast.walk(tree)
                      if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef))}
        found += [f"{where}:{n.lineno} {n.value!r}" for n in ast.walk(tree)
                  if isinstance(n, ast.Constant) and isinstance(n.value, str) and n.value not in docstrings
                  and n.value.strip().lower() in names]
    assert not found, found


# ---------------------------------------------------------------------------- imports at the top (issue 37)
def test_internal_imports_inside_functions_say_why():
    """An import of fppsim / uhrnet inside a library function is allowed only with a comment saying why (a
    lazy start, an optional heavy dependency), on its line or the line above; the command-line modules
    import lazily by design. Everything else imports at the top, where the stage order can be read."""
    silent = []
    for module, path in _modules():
        if _is_cli(module):
            continue
        lines = path.read_text().splitlines()
        tree = ast.parse("\n".join(lines))

        def visit(node, depth):
            for child in ast.iter_child_nodes(node):
                inner = depth + isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
                if depth and isinstance(child, (ast.Import, ast.ImportFrom)):
                    names = [a.name for a in child.names] if isinstance(child, ast.Import) else [child.module or "."]
                    if any(n.split(".")[0] in PACKAGES or n.startswith(".") for n in names):
                        here = "\n".join(lines[child.lineno - 1:child.end_lineno])
                        above = lines[child.lineno - 2].strip() if child.lineno > 1 else ""
                        if "#" not in here and not above.startswith("#"):
                            silent.append(f"{path.relative_to(ROOT)}:{child.lineno}")
                visit(child, inner)

        visit(tree, 0)
    assert not silent, f"{len(silent)} function-level imports without a reason: {silent[:20]}"


RUN_FOLDER_NAMES = {"last.pt", "best.pt", "history.csv", "history.png", "config.json", "images.json"}


def test_run_folder_names_are_spelled_only_by_the_run_folder_module():
    """A run folder's file names are ``uhrnet.run_folder``'s constants (``LAST_PT``, ``HISTORY_CSV``, ...): no other
    module of either package nor a pipeline has a string equal to one (messages and docstrings may name them)."""
    files = [p for _, p in _modules()] + sorted((ROOT / "pipelines").glob("*.py"))
    found = [f"{p.relative_to(ROOT)}:{n.lineno} {n.value!r}" for p in files if p != ROOT / "uhrnet" / "run_folder.py"
             for n in ast.walk(ast.parse(p.read_text())) if isinstance(n, ast.Constant) and n.value in RUN_FOLDER_NAMES]
    assert not found, found

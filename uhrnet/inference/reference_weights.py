"""The published UHRNet weights: the reference code's state-dict layout <-> this project's ``uhrnet``.

The authors' reference code (github fead1/UHRNet, ``UHRNet.py``) publishes ``UHRNet_weight.pth``, a
``{'state_dict': ...}`` that their ``errortest.py`` loads into ``UHRNet()``. That network computes the same
function as ``build_model("uhrnet")`` at base width 64 with 1 input / 1 output channel (763 state-dict
entries and 30,330,977 parameters each): it reads the figshare fringe encoding (``I / 127.5 - 1``) and
writes heights in figshare label units (``Z``); their evaluation divides labels by 6 for millimetres, the
``figshare`` preset's ``mm_per_unit`` (:data:`fppsim.dataio.formats.PRESETS`).

The two layouts differ in names (:func:`key_table`, built from :data:`MODULES`) and in one channel order:
a High-resolution Fusion Block concatenates the maps it resampled from the other encoder levels and mixes
them with a 3x3 convolution. Ours concatenates them finest level first at every level; the reference does so
at its levels 2 and 3 but concatenates coarsest first at level 1 (``up3_(x4_), up2_(x3_), up1_(x2_)``), so
that block's mixing convolution (reference ``cov1.conv``, ours ``fusion.0.mix.0``) takes its input channels
in another order (:data:`FUSION`). Everything else (the Multi-Level conv Blocks' branch order, the
decoder's ``cat(upsampled, skip)``, the fusion merge's ``cat(own map, mixed)``) has the same order.

Library: :func:`to_reference_state_dict` / :func:`from_reference_state_dict` (pure, exact),
:func:`read_reference_file`, ``import_weights(ImportWeightsConfig)`` (``uhrnet import-weights``: a run
folder that ``predict``, ``evaluate``, ``evaluate-phase``, ``adapt``, ``export`` and ``train --init-from
... --raw-output`` accept) and :func:`export_reference` (``uhrnet export --format reference``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import pickle
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import torch

from fppsim.files import tmp_path, unlink_quietly
from fppsim.owned import output_folder, owners
from fppsim.dataio.formats import PRESETS, LabelTransform
from uhrnet.checkpoint import FORMAT, VERSION, atomic_save, checkpoint_kind, model_from_checkpoint, output_mm, save_epoch
from uhrnet.errors import CheckpointError, ConfigError, ExportError, UsageError
from uhrnet.inference.export_check import check_input, compare_outputs
from uhrnet.models import ALIASES, build_model, count_parameters
from uhrnet.models.heads import DEFAULT_HEAD
from uhrnet.models.uhrnet import UHRNet
from uhrnet.run_folder import (BEST_PT, CONFIG_JSON, IMPORT_TOOL, LAST_PT, RUN_FILES, TRAINED_FILES, claim_run_folder,
                               package_version, write_run_config)

__all__ = ["REFERENCE_FORMAT", "REFERENCE_CONFIG", "MODULES", "FUSION", "key_table", "model_shapes",
           "to_reference_state_dict", "from_reference_state_dict", "read_reference_file", "ImportWeightsConfig",
           "import_weights", "check_exportable", "reference_output_affine", "export_reference"]

REFERENCE_FORMAT = "reference"
REFERENCE_CONFIG = {"in_channels": 1, "out_channels": 1, "base_channels": 64, "fusion": True}
"""The only ``uhrnet`` the reference code builds (``UHRNet()`` takes no arguments)."""

_PARAMS = {"conv": ("weight", "bias"),
           "bn": ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")}


def _mlb(ref: str, ours: str) -> list[tuple[str, str, str]]:
    """A Multi-Level conv Block: the reference's ``ResB`` (``branch0`` is the 1x1 shortcut, ``branchK``
    a chain of K convs ``convK_j`` + ``btK_j``; ``branch1``'s are ``conv1`` / ``bt1``) and ours."""
    rows = [(f"{ref}.branch0.conv0", f"{ours}.shortcut.0", "conv"), (f"{ref}.branch0.bt0", f"{ours}.shortcut.1", "bn"),
            (f"{ref}.branch1.conv1", f"{ours}.branches.0.0.0", "conv"),
            (f"{ref}.branch1.bt1", f"{ours}.branches.0.0.1", "bn")]
    for k in (2, 3, 4):
        for j in range(1, k + 1):
            rows += [(f"{ref}.branch{k}.conv{k}_{j}", f"{ours}.branches.{k - 1}.{j - 1}.0", "conv"),
                     (f"{ref}.branch{k}.bt{k}_{j}", f"{ours}.branches.{k - 1}.{j - 1}.1", "bn")]
    return rows


FUSION: tuple[tuple[tuple[str, str, str], str, str, tuple[int, int, int]], ...] = (
    (("up1_", "up2_", "up3_"), "cov1", "cov1_", (2, 1, 0)),
    (("down0_", "up2__", "up3__"), "cov2", "cov2_", (0, 1, 2)),
    (("down0__", "down1_", "up3___"), "cov3", "cov3_", (0, 1, 2)),
)
"""Per fusion level of ours (``fusion.0`` = full resolution = the reference's level 1): the reference's
resampling layers in OUR ``resample`` order (the other encoder levels, finest first), its mixing and merging
``cbl`` blocks, and the order in which the reference concatenates the resampled maps, as indices into our
``resample`` list: ``(2, 1, 0)`` at level 1 (``x4_, x3_, x2_``), ours at levels 2 and 3."""


def _modules() -> list[tuple[str, str, str]]:
    """(reference module, our module, ``"conv"`` or ``"bn"``) for every module with weights, in the
    reference's registration order (so :func:`to_reference_state_dict` writes its key order)."""
    rows = []
    for i in range(4):
        rows += _mlb(f"down{i + 1}.res", f"encoder.blocks.{i}")
    rows += _mlb("res", "bottleneck")
    for i in range(4):
        rows.append((f"up{i + 1}.up", f"decoder.stages.{i}.up", "conv"))
        rows += _mlb(f"up{i + 1}.res", f"decoder.stages.{i}.block")
    rows.append(("outc.conv", "head", "conv"))
    for level, (resample, mix, merge, _) in enumerate(FUSION):
        rows += [(name, f"fusion.{level}.resample.{j}", "conv") for j, name in enumerate(resample)]
        for ref, ours in ((mix, "mix"), (merge, "merge")):
            rows += [(f"{ref}.conv", f"fusion.{level}.{ours}.0", "conv"), (f"{ref}.bt", f"fusion.{level}.{ours}.1", "bn")]
    return rows


MODULES: tuple[tuple[str, str, str], ...] = tuple(_modules())


def key_table() -> list[tuple[str, str]]:
    """``(reference key, our key)`` for all 763 state-dict entries, in the reference's order."""
    return [(f"{ref}.{p}", f"{ours}.{p}") for ref, ours, kind in MODULES for p in _PARAMS[kind]]


_MIX = {f"fusion.{level}.mix.0.weight": order for level, (_, _, _, order) in enumerate(FUSION)
        if order != tuple(range(len(order)))}  # our mixing weights whose input channels the reference orders otherwise


def model_shapes(base_channels: int = 64) -> dict[str, tuple[int, ...]]:
    """Shape of every state-dict entry of ours (``uhrnet``, fusion, 1 in / 1 out) at ``base_channels``,
    in our order; built on the meta device (no memory, no time)."""

    with torch.device("meta"):
        net = UHRNet(in_channels=1, out_channels=1, base_channels=base_channels, fusion=True)
    return {k: tuple(v.shape) for k, v in net.state_dict().items()}


def _check_entries(state: Mapping, expected: dict[str, tuple[int, ...]], what: str, hint: str = "") -> None:
    """Every key of ``expected`` present with its shape, no other key; else one-line CheckpointError
    naming the first offending key (missing first, then unexpected, then shape)."""
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    more = lambda n: f" (and {n - 1} more)" if n > 1 else ""  # noqa: E731
    if missing:
        raise CheckpointError(f"{what}: missing key {missing[0]!r}{more(len(missing))}"
                              + (f"; unexpected key {unexpected[0]!r}{more(len(unexpected))}" if unexpected else "")
                              + hint)
    if unexpected:
        raise CheckpointError(f"{what}: unexpected key {unexpected[0]!r}{more(len(unexpected))}{hint}")
    for k, shape in expected.items():
        v = state[k]
        if not isinstance(v, torch.Tensor):
            raise CheckpointError(f"{what}: {k!r} is a {type(v).__name__}, not a tensor")
        if tuple(v.shape) != shape:
            raise CheckpointError(f"{what}: {k!r} has shape {tuple(v.shape)}, expected {shape}{hint}")


def _permute_inputs(weight: torch.Tensor, order: tuple[int, ...]) -> torch.Tensor:
    """``weight`` (out, in, kh, kw) with its input channels in ``len(order)`` equal blocks; block ``i`` of the
    result is block ``order[i]`` of ``weight``."""
    blocks = weight.chunk(len(order), dim=1)
    return torch.cat([blocks[j] for j in order], dim=1).contiguous()


def _strip_module_prefix(state: Mapping) -> Mapping:
    """DataParallel saves every key as ``module.<key>``: drop that prefix when all keys have it."""
    keys = list(state)
    if keys and all(isinstance(k, str) and k.startswith("module.") for k in keys):
        return {k[len("module."):]: v for k, v in state.items()}
    return state


def to_reference_state_dict(model_state: Mapping[str, torch.Tensor], *, base_channels: int = 64,
                            what: str = "uhrnet state dict") -> dict[str, torch.Tensor]:
    """Our ``uhrnet`` state dict (``build_model("uhrnet").state_dict()``) in the reference's layout and order.

    Exact: tensors are moved, not recomputed; the level-1 mixing weight gets its input channels permuted
    (:data:`FUSION`). The other tensors are the inputs themselves (shared, not copied).
    ``base_channels`` other than 64 only for tests: the reference itself is fixed at 64. Raises
    :class:`CheckpointError` naming the first missing/unexpected key or wrong shape.
    """
    _check_entries(model_state, model_shapes(base_channels), what)
    out = {}
    for ref, ours in key_table():
        v = model_state[ours]
        out[ref] = _permute_inputs(v, _MIX[ours]) if ours in _MIX else v
    return out


def from_reference_state_dict(ref_state: Mapping[str, torch.Tensor], *, base_channels: int = 64,
                              what: str = "reference state dict") -> dict[str, torch.Tensor]:
    """A reference-layout state dict (bare; a DataParallel ``module.`` prefix is dropped) as our ``uhrnet``'s,
    in our order: ``build_model("uhrnet").load_state_dict(result)`` then computes the reference's function.
    The exact inverse of :func:`to_reference_state_dict`. Raises :class:`CheckpointError` naming the first
    missing/unexpected key or wrong shape."""
    ref_state = _strip_module_prefix(ref_state)
    table = key_table()
    shapes = model_shapes(base_channels)
    hint = ""
    if any(isinstance(k, str) and k.startswith(("encoder.", "fusion.", "decoder.")) for k in ref_state):
        hint = " (this looks like uhrnet's own layout, not the reference code's)"
    _check_entries(ref_state, {ref: shapes[ours] for ref, ours in table}, what, hint)
    back = {}
    for ref, ours in table:
        v = ref_state[ref]
        if ours in _MIX:  # inverse permutation: our block k is the reference's block order.index(k)
            order = _MIX[ours]
            v = _permute_inputs(v, tuple(order.index(k) for k in range(len(order))))
        back[ours] = v
    return {k: back[k] for k in shapes}


# --------------------------------------------------------------------------------------------------
# Files


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 22), b""):
            h.update(chunk)
    return h.hexdigest()


def read_reference_file(path: str | Path) -> tuple[dict[str, torch.Tensor], dict]:
    """The state dict in a reference weights file: ``{'state_dict': ...}`` (``UHRNet_weight.pth``) or a bare
    state dict, loaded with ``weights_only=True`` (no code runs). Returns ``(state dict, info)``, info
    ``{"path", "sha256", "wrapped", "module_prefix"}``. The keys are not checked here
    (:func:`from_reference_state_dict` does). Raises :class:`CheckpointError` (one line naming the file)."""
    path = Path(path)
    if path.is_dir():
        raise CheckpointError(f"{path}: is a folder; give the weights file (e.g. UHRNet_weight.pth)")
    if not path.is_file():
        raise CheckpointError(f"{path}: weights file not found")
    if path.stat().st_size == 0:
        raise CheckpointError(f"{path}: empty file (0 bytes), not a weights file")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:  # torch advises weights_only=False: wrong for a file we do not trust
        found = re.search(r"Unsupported global: GLOBAL (\S+)", str(exc))
        if found:  # a real torch file that pickles a Python object besides the tensors
            raise CheckpointError(f"{path}: holds a Python object ({found.group(1)}) that cannot be loaded without "
                                  "running code; save its state dict alone (torch.save({'state_dict': ...}))") from None
        raise CheckpointError(f"{path}: cannot load: not a PyTorch weights file (truncated or another format)") from None
    except Exception as exc:  # truncated file, another format: torch's own text is about its internals
        raise CheckpointError(f"{path}: cannot load: not a complete PyTorch weights file (truncated, or another "
                              f"format; {type(exc).__name__})") from None
    if not isinstance(obj, Mapping):
        raise CheckpointError(f"{path}: holds a {type(obj).__name__}, not a state dict")
    if obj.get("format") == "uhrnet-checkpoint":
        raise CheckpointError(f"{path}: is already a uhrnet checkpoint; predict/evaluate read it as it is")
    wrapped = isinstance(obj.get("state_dict"), Mapping)
    state = obj["state_dict"] if wrapped else obj
    if not state or not all(isinstance(v, torch.Tensor) for v in state.values()):
        keys = ", ".join(map(str, list(obj)[:5]))
        raise CheckpointError(f"{path}: neither a state dict nor {{'state_dict': ...}} (keys: {keys})")
    prefix = _strip_module_prefix(state) is not state
    return dict(state), {"path": str(path.resolve()), "sha256": _sha256(path), "wrapped": wrapped,
                         "module_prefix": prefix}


# --------------------------------------------------------------------------------------------------
# uhrnet import-weights

IMPORT_FORMATS = (REFERENCE_FORMAT,)
IMPORT_FILES = (BEST_PT, LAST_PT, CONFIG_JSON)  # what import-weights writes
# labels of the plane import-weights accepts: above the invalid threshold (-100), and no higher than the
# tallest figshare label seen (+181) leaves room for: 1000 labels = 167 mm
PLANE_OFFSET_RANGE = (PRESETS["figshare"].invalid_threshold, 1000.0)


@dataclass
class ImportWeightsConfig:
    """``uhrnet import-weights``: ``source`` a weights file in ``format`` layout, ``out`` the run folder to
    write (refused when it holds a run, unless ``overwrite``)."""

    source: Path
    out: Path
    format: str = REFERENCE_FORMAT
    overwrite: bool = False
    # label of height 0: the figshare preset's plane (-97), so heights are above the reference plane as
    # everywhere else in uhrnet; 0 gives the reference evaluation's plain Z / 6
    plane_offset: float = PRESETS["figshare"].plane_offset

    def __post_init__(self):
        if self.format not in IMPORT_FORMATS:
            raise UsageError(f"--format must be one of {', '.join(IMPORT_FORMATS)}, got {self.format!r}")
        try:
            self.plane_offset = float(self.plane_offset)
        except (TypeError, ValueError):
            raise UsageError(f"--plane-offset must be a number (a figshare label), got {self.plane_offset!r}") from None
        lo, hi = PLANE_OFFSET_RANGE
        if not (math.isfinite(self.plane_offset) and lo < self.plane_offset <= hi):
            raise UsageError(f"--plane-offset must be a label above the invalid threshold {lo:g} and at most {hi:g} "
                             f"(the plane's label: -97 for heights above the plane, 0 for Z / 6), "
                             f"got {self.plane_offset!r}")
        self.source, self.out = Path(self.source), Path(self.out)


def import_weights(config: ImportWeightsConfig) -> dict:
    """Turn a reference weights file into a run folder ``config.out``: ``best.pt`` (and the identical
    ``last.pt``) with the ``uhrnet`` model (base 64, fusion), its weights mapped by
    :func:`from_reference_state_dict`, network output = label (``output`` scale 1, shift 0) and the
    ``figshare`` label transform with ``plane_offset`` = ``config.plane_offset``, so ``predict`` writes
    ``(Z - plane_offset) / 6`` mm: with the default -97 heights above the figshare reference plane as the rest
    of this project reports them (what adapt, refine, the point clouds and ``train --init-from RUN
    --raw-output`` expect); 0 gives exactly the reference evaluation's ``Z / 6`` (differences, and so RMSE, are
    the same either way); plus ``config.json`` naming the source and its SHA-256. ``epoch`` is 0 and there is
    nothing to ``--resume``. The folder's files are recorded as import-weights' own (:mod:`fppsim.owned`):
    a file another tool or a person put there is refused, never replaced.

    Returns ``{"out", "checkpoint", "entries", "parameters", "source", "sha256"}``. Raises
    :class:`CheckpointError` for a file that does not fit, :class:`ConfigError` for an ``out`` that holds
    earlier imported weights (without ``overwrite``), files of another tool or nobody's, or cannot be written.
    """

    state, info = read_reference_file(config.source)
    ours = from_reference_state_dict(state, what=str(config.source))
    broken = next((k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())), None)
    if broken is not None:  # a network with NaN/inf weights predicts nothing usable
        raise CheckpointError(f"{config.source}: entry {broken!r} holds NaN or inf values; these are not usable weights")
    net = build_model("uhrnet", **REFERENCE_CONFIG)
    net.load_state_dict(ours)  # strict: the keys and shapes were checked above
    transform = dataclasses.replace(PRESETS["figshare"], plane_offset=config.plane_offset)
    out = config.out
    n_params = int(count_parameters(net))
    record = {"format": config.format, "path": info["path"], "sha256": info["sha256"], "wrapped": info["wrapped"],
              "module_prefix": info["module_prefix"], "entries": len(ours)}
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out}: is a file, not a run folder; choose a folder")
    # created, locked, and every run-file name claimed for import-weights before anything is written: a file
    # another tool (train, adapt) or a person wrote is never replaced, --overwrite or not
    with output_folder(out, IMPORT_TOOL, error=ConfigError):
        held = [n for n in (*TRAINED_FILES, CONFIG_JSON) if (out / n).exists()]
        mine = owners(out) or {}
        if held and not config.overwrite and all(mine.get(n) == IMPORT_TOOL for n in held):
            raise ConfigError(f"{out} already holds imported weights ({', '.join(held)}): pass --overwrite to "
                              "replace them, or choose another --out")
        # a run's other files (a training history) beside imported weights would describe another model
        foreign = [n for n in RUN_FILES if n not in IMPORT_FILES and (out / n).exists()]
        if foreign:
            who = mine.get(foreign[0])
            raise ConfigError(f"{out / foreign[0]} " + (f"was written by {who}, not {IMPORT_TOOL}" if who else
                                                         f"exists and was not written by {IMPORT_TOOL}")
                              + ": move it away or choose another --out")
        claim_run_folder(out, IMPORT_TOOL, IMPORT_FILES, checkpoint_kind, kind="import")
        payload = {"format": FORMAT, "version": VERSION, "model": {"name": net.config["name"], "config": dict(net.config)},
                   "state_dict": net.state_dict(), "output": {"scale": 1.0, "shift": 0.0},
                   "label_transform": transform.to_dict(), "epoch": 0, "imported": record,
                   "n_parameters": n_params, "uhrnet_version": package_version()}
        save_epoch(out, payload, is_best=True)
        write_run_config(out, {"command": "import-weights", "imported": record, "model": dict(net.config),
                               "output": payload["output"], "label_transform_resolved": transform.to_dict(),
                               "n_parameters": n_params})
    return {"out": str(out), "checkpoint": str(out / BEST_PT), "entries": len(ours), "parameters": n_params,
            "source": info["path"], "sha256": info["sha256"]}


# --------------------------------------------------------------------------------------------------
# uhrnet export --format reference


def check_exportable(ckpt: dict) -> None:
    """Refuse (:class:`ExportError`, one line) a checkpoint the reference ``UHRNet()`` cannot hold: another
    architecture, the phase head, fusion off (model_b), a base width other than 64, other channel counts."""

    config = dict(ckpt["model"]["config"])
    name = str(config.get("name", "?"))
    arch = ALIASES[name][0] if name in ALIASES else name
    where = f"{ckpt.get('path', 'checkpoint')}: --format reference"
    if arch != "uhrnet":
        raise ExportError(f"{where} holds only UHRNet; this checkpoint is {name}")
    if config.get("head", DEFAULT_HEAD) != DEFAULT_HEAD:
        raise ExportError(f"{where} holds only the plain height head; this checkpoint has the {config['head']} head")
    for key, want in REFERENCE_CONFIG.items():
        if config.get(key, want) != want:
            raise ExportError(f"{where} is UHRNet with {key}={want}; this checkpoint has {key}={config.get(key)!r}")


def _reference_labels(ckpt: dict, transform: LabelTransform) -> LabelTransform:
    """The label transform of the reference's output ``Z`` for this checkpoint: the figshare preset, except
    that weights imported from the reference output its ``Z`` by construction whatever plane offset
    ``import-weights --plane-offset`` chose for reading ``Z`` as mm."""
    figshare = PRESETS["figshare"]
    if (ckpt.get("imported") or {}).get("format") == REFERENCE_FORMAT:
        return dataclasses.replace(figshare, plane_offset=transform.plane_offset)
    return figshare


def reference_output_affine(ckpt: dict) -> tuple[float, float]:
    """``(a, b)``: figshare label ``Z = a * net(x) + b`` for the checkpoint's bare network (the reference's
    network outputs ``Z`` itself). Combines the checkpoint's label head (``output`` scale, shift) with its
    label transform, converted to the figshare preset through millimetres when it differs."""

    out = ckpt.get("output", {"scale": 1.0, "shift": 0.0})
    scale, shift = float(out["scale"]), float(out["shift"])
    transform = LabelTransform.from_dict(ckpt["label_transform"])
    figshare = _reference_labels(ckpt, transform)
    if transform.same_labels(figshare):
        return scale, shift
    a_mm, b_mm = output_mm(scale, shift, transform)
    return a_mm * figshare.units_per_mm, b_mm * figshare.units_per_mm + figshare.plane_offset


def _reference_state_of(ckpt: dict) -> dict[str, torch.Tensor]:
    """The checkpoint's weights in the reference layout, its label head folded into the final 1x1 conv."""
    state = {k: v.detach().cpu() for k, v in ckpt["state_dict"].items()}
    a, b = reference_output_affine(ckpt)
    if (a, b) != (1.0, 0.0):  # fold in float64, store in the weights' own dtype
        w, bias = state["head.weight"], state["head.bias"]
        state["head.weight"] = (w.double() * a).to(w.dtype)
        state["head.bias"] = (bias.double() * a + b).to(bias.dtype)
    ref = to_reference_state_dict(state, what=str(ckpt.get("path", "checkpoint")))
    return {k: v.contiguous() for k, v in ref.items()}


def export_reference(ckpt: dict, out: Path, check: bool = False,
                     input_shape: tuple[int, int, int, int] = (1, 1, 352, 640)) -> dict:
    """Write ``{'state_dict': ...}`` for the reference ``UHRNet()`` (``load_state_dict(strict=True)``) from a
    loaded checkpoint (:func:`uhrnet.checkpoint.load_checkpoint`); ``uhrnet export --format reference``.

    The reference network outputs figshare labels, so the checkpoint's label head (and its label transform,
    when not figshare's) is folded into the final convolution (:func:`reference_output_affine`). With
    ``check``: the file is written under a temporary name, read back through
    :func:`from_reference_state_dict` into a bare ``uhrnet`` and run against the checkpoint's model (in
    figshare labels) on the seeded input of :func:`uhrnet.inference.export.check_input`; it replaces ``out`` only when
    ``max |difference| <= CHECK_RTOL x output range``, else :class:`ExportError`. Returns the summary
    ``uhrnet export`` prints."""

    check_exportable(ckpt)
    payload = {"state_dict": _reference_state_of(ckpt)}
    out = Path(out)
    summary = {"path": str(out), "format": REFERENCE_FORMAT, "model": ckpt["model"]["config"].get("name"),
               "input_shape": list(input_shape), "check": None, "runtime": None, "entries": len(payload["state_dict"])}
    if not check:
        atomic_save(payload, out)
        return summary
    stage = tmp_path(out)
    try:
        atomic_save(payload, stage)
        result = _check_reference_file(stage, ckpt, input_shape)
        summary["check"] = result
        if not result["passed"]:
            raise ExportError(f"{out}: check failed, nothing written: max |exported - checkpoint| = "
                              f"{result['max_abs_diff']:.3g} > {result['tolerance']:.3g}")
        stage.replace(out)
    finally:
        unlink_quietly(stage)
    return summary


def _check_reference_file(path: Path, ckpt: dict, input_shape: tuple[int, int, int, int]) -> dict:
    """The exported file read back as the reference reads it (no label head: figshare labels) against the
    checkpoint's model converted to figshare labels, on the seeded check input."""

    state, _ = read_reference_file(path)
    bare = build_model("uhrnet", **REFERENCE_CONFIG)
    bare.load_state_dict(from_reference_state_dict(state, what=str(path)))
    model, transform = model_from_checkpoint(ckpt)
    n, c, h, w = input_shape
    x = check_input(c, h, w).expand(n, c, h, w).contiguous()
    figshare = _reference_labels(ckpt, transform)
    with torch.no_grad():
        got = bare.eval()(x).double().numpy()
        label = model(x).double()
        want = (label if transform.same_labels(figshare)
                else figshare.units_per_mm * transform.height_mm(label) + figshare.plane_offset).numpy()
    return compare_outputs(got, want)

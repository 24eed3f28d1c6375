"""The settings files a generation run reads beside its rig: scene ranges (``--scenes``) and optics overrides
(``--optics-file``), each checked, with a :class:`~fppsim.errors.ConfigError` naming the file. Re-exported by
:mod:`fppsim.generation`."""

from __future__ import annotations

import json
import os
from pathlib import Path

from fppsim.errors import ConfigError, InputError
from fppsim.geometry.rig_files import read_rig_file
from fppsim.rendering.optics import OpticsRanges
from fppsim.rendering.scene import SceneRanges

__all__ = ["SCENE_FIELDS", "resolve_scenes", "read_optics_file"]


SCENE_FIELDS = ("footprint", "max_relief", "pedestal_height")
"""The scene ranges a rig's frames set (``fppsim.fitting.frame_scenes``); the rest of :class:`SceneRanges` stays."""


def _scene_mapping(doc, where: str) -> dict:
    fields = {}
    for k in SCENE_FIELDS:
        if k in doc:
            v = doc[k]
            if not (isinstance(v, (list, tuple)) and len(v) == 2
                    and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)):
                raise ConfigError(f"{where}: {k} must be [lo, hi] in mm, got {v!r}")
            fields[k] = (float(v[0]), float(v[1]))
    if not fields:
        raise ConfigError(f"{where}: no scene ranges ({', '.join(SCENE_FIELDS)})")
    try:
        SceneRanges(**fields)
    except InputError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    return fields


def resolve_scenes(scenes, rig_path=None) -> tuple[dict, str]:
    """The scene ranges of ``scenes`` (:data:`SCENE_FIELDS` -> (lo, hi) mm; ``{}``: the defaults) and where
    they came from, in words: ``"default"``; ``"auto"``: the ``scenes`` section of the rig file ``rig_path``
    (``fppsim fit-rig`` writes it to follow the frames), else the defaults; a mapping; or a JSON/YAML file
    holding a rig with ``scenes`` or the mapping itself. :class:`ConfigError` naming the file otherwise."""
    if isinstance(scenes, dict):
        return _scene_mapping(scenes, "scenes"), "given"
    if scenes in ("default", None):
        return {}, "the default scenes"
    if scenes == "auto":
        if rig_path is None:
            return {}, "the default scenes"
        doc = read_rig_file(rig_path)
        if not isinstance(doc, dict) or doc.get("scenes") is None:
            return {}, f"the default scenes ({rig_path} has no scenes)"
        return _scene_mapping(doc["scenes"], f"{rig_path}: scenes"), f"the rig file's scenes ({rig_path})"
    p = Path(scenes)
    doc = _mapping_file(p, f"--scenes: file not found: {p} (or 'auto' / 'default')",
                        f"a mapping of {', '.join(SCENE_FIELDS)} -> [lo, hi] mm (or a rig with scenes)")
    inner = doc.get("scenes", doc)
    if not isinstance(inner, dict):
        raise ConfigError(f"{p}: scenes must be a mapping, got {type(inner).__name__}")
    return _scene_mapping(inner, str(p)), f"{p}"


def _mapping_file(p: Path, not_found: str, expected: str) -> dict:
    """The mapping a JSON / YAML (by extension) file ``p`` holds; :class:`ConfigError` with ``not_found`` when
    it is missing, naming the file when it does not parse or is not ``expected`` (a mapping)."""
    import yaml

    if not p.is_file():
        raise ConfigError(not_found)
    try:
        doc = yaml.safe_load(p.read_text()) if p.suffix.lower() in (".yaml", ".yml") else json.loads(p.read_text())
    except Exception as exc:
        raise ConfigError(f"{p}: not valid JSON/YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"{p}: expected {expected}")
    return doc


def read_optics_file(path: str | os.PathLike) -> dict:
    """Optics range overrides from a JSON/YAML mapping ``{name: value or [lo, hi]}``, checked
    (:class:`ConfigError` naming the file)."""
    p = Path(path)
    doc = _mapping_file(p, f"file not found: {p}", "a mapping of name -> value or [lo, hi]")
    try:
        OpticsRanges.from_dict(doc)
    except ValueError as exc:
        raise ConfigError(f"{p}: {exc}") from None
    return doc

"""fppsim.owned.remove_own: a tool deletes only files its record says it wrote (and nobody changed since)."""

from fppsim.owned import claim, owners, remove_own, stamp


def test_remove_own_deletes_only_the_tools_unchanged_files(tmp_path):
    claim(tmp_path, "a", ["old.npy", "stamped.npy", "gone.npy"])
    claim(tmp_path, "b", ["other.npy"])
    for name in ("old.npy", "stamped.npy", "other.npy", "user.npy"):
        (tmp_path / name).write_text(name)
    stamp(tmp_path, ["stamped.npy"])
    (tmp_path / "stamped.npy").write_text("changed by someone, size and all")
    assert remove_own(tmp_path, "a", ["old.npy", "stamped.npy", "gone.npy", "other.npy", "user.npy"]) == ["old.npy"]
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".")) == [
        "other.npy", "stamped.npy", "user.npy"]
    assert owners(tmp_path) == {"stamped.npy": "a", "other.npy": "b"}  # gone.npy (never written) is forgotten too


def test_a_tools_files_from_before_its_record_are_its_own_also_in_a_folder_another_tool_records(tmp_path):
    """Review: `evaluate` refused its own older report once `evaluate-phase` had started a record in the folder
    (legacy was asked only where no record existed)."""
    import pytest

    from fppsim.owned import ForeignFiles

    for name in ("results.md", "notes.md"):
        (tmp_path / name).write_text(name)
    claim(tmp_path, "other", ["phase.md"])
    claim(tmp_path, "mine", ["results.md"], legacy=lambda: ["results.md"])
    assert owners(tmp_path) == {"phase.md": "other", "results.md": "mine"}
    with pytest.raises(ForeignFiles, match="notes.md exists and was not written by mine"):
        claim(tmp_path, "mine", ["notes.md"], legacy=lambda: ["results.md"])
    (tmp_path / "phase.md").write_text("x")
    with pytest.raises(ForeignFiles, match="phase.md was written by other, not mine"):  # a record's word stands
        claim(tmp_path, "mine", ["phase.md"], legacy=lambda: ["phase.md"])

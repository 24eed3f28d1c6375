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

"""Issue 11, second round: shader programs compiled once per renderer, the PSP decode moved to the
writer thread. Same bits as before; errors of the moved decode surface as they did."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
import trimesh

from fppsim import synth
from fppsim.cli import main as fppsim_main
from fppsim.formats import read_manifest, write_sample_folder
from fppsim.generation import load_assets
from fppsim.pipeline import BackgroundWriter, write_sample
from fppsim.render import DepthRenderer, Instance
from fppsim.rig import Rig


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    d = tmp_path_factory.mktemp("overlap_mesh")
    trimesh.creation.box(extents=(60.0, 40.0, 25.0)).export(d / "box.ply")
    return d / "box.ply"


def _config(psp_freqs=(1, 8)):
    return synth.SynthConfig(rig=Rig.default(), psp_freqs=psp_freqs, psp_steps=3, min_object_fraction=0.0)


def test_shader_programs_are_compiled_once_and_give_pyrender_s_depth():
    from pyrender.shader_program import ShaderProgramCache

    rig = Rig.default()
    s = trimesh.creation.icosphere(3, radius=20.0)
    b = trimesh.creation.box(extents=(30.0, 20.0, 10.0))
    T = np.eye(4)
    T[:3, 3] = (40.0, 10.0, 20.0)
    inst = [Instance(s.vertices, s.faces, np.eye(4), "s"), Instance(b.vertices, b.faces, T)]
    r = DepthRenderer()
    first = r.depth(rig.camera, inst)
    (offscreen, _, _), = r._slots.values()
    cache = offscreen._renderer._program_cache
    compiled = len(cache._program_cache)
    assert compiled == 1  # one depth program serves every mesh
    for _ in range(3):
        assert np.array_equal(r.depth(rig.camera, inst), first)
    assert len(cache._program_cache) == compiled  # pyrender alone added one program per draw call
    # pyrender's own cache (a fresh program per draw) renders the very same depth
    plain = DepthRenderer()
    plain.depth(rig.camera, inst)
    (po, _, _), = plain._slots.values()
    po._renderer._program_cache.clear()
    po._renderer._program_cache = ShaderProgramCache()
    assert np.array_equal(plain.depth(rig.camera, inst), first)
    plain.close()
    r.close()  # frees the kept programs
    assert cache._program_cache == {} and cache._by_source == {}


def test_deferred_decode_completes_to_synthesize_s_arrays(box):
    assets, _ = load_assets([str(box)])
    r = DepthRenderer()
    for config in (_config(), _config(psp_freqs=())):
        images, arrays, meta = synth.synthesize(2, 4, assets, config, r)
        images2, arrays2, meta2, decode = synth.synthesize_deferred(2, 4, assets, config, r)
        if config.psp_freqs:
            assert "phase_psp" not in arrays2
            arrays2 = decode.complete(arrays2)
        else:
            assert decode is None
        assert list(arrays) == list(arrays2)  # same keys in the same order (the npz order)
        assert all(a.dtype == arrays2[k].dtype and np.array_equal(a, arrays2[k], equal_nan=True)
                   for k, a in arrays.items())
        assert images.keys() == images2.keys() and all(np.array_equal(images[k], images2[k]) for k in images)
        assert meta == meta2
    r.close()


def test_writer_thread_decodes_before_writing_in_order_and_reraises(box, tmp_path, monkeypatch):
    """The decode of sample k runs on the writer thread right before its folder is written; a failing
    decode re-raises from the writer with its own message, leaves no folder (nor temporary folder)
    and later samples are not written."""
    import fppsim.pipeline as pipeline

    assets, _ = load_assets([str(box)])
    config = _config()
    r = DepthRenderer()
    samples = {i: synth.synthesize_deferred(i, 4, assets, config, r) for i in range(3)}
    reference = tmp_path / "ref"
    for i in range(3):
        images, arrays, meta = synth.synthesize(i, 4, assets, config, r)
        write_sample_folder(reference, f"{i:06d}", images, arrays, meta)
    r.close()

    events = []
    decode = synth.psp_decode

    def watched_decode(stacks, rig, freqs, *a, **k):
        events.append(("decode", threading.current_thread().name))
        if sum(e[0] == "decode" for e in events) == 2:
            raise ValueError("decode broke")
        return decode(stacks, rig, freqs, *a, **k)

    write = pipeline.write_sample_folder

    def watched_write(root, sid, images, arrays, meta):
        events.append(("write", sid, "height_psp" in arrays))
        return write(root, sid, images, arrays, meta)

    monkeypatch.setattr(synth, "psp_decode", watched_decode)
    monkeypatch.setattr(pipeline, "write_sample_folder", watched_write)
    out = tmp_path / "out"
    w = BackgroundWriter()
    with pytest.raises(ValueError, match="^decode broke$"):
        for i, (images, arrays, meta, dec) in samples.items():
            w.submit(write_sample, out, f"{i:06d}", images, arrays, meta, dec)
        w.flush()
    w.close()
    assert events == [("decode", "fppsim-writer"), ("write", "000000", True), ("decode", "fppsim-writer")]
    assert sorted(p.name for p in out.iterdir()) == ["000000"]  # no 000001, no temporary folder
    for name in ("fringe.png", "psp/f8_s2.png", "arrays.npz", "meta.json"):
        assert (out / "000000" / name).read_bytes() == (reference / "000000" / name).read_bytes()


def test_generate_reports_a_failed_decode_in_one_line_and_resumes_exactly(box, tmp_path, monkeypatch, capsys):
    from fppsim.errors import DatasetError

    calls = []
    decode = synth.psp_decode

    def failing(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise DatasetError("decode broke")
        return decode(*a, **k)

    args = ["generate", "-q", "--no-preview", "--meshes", str(box), "--count", "3", "--seed", "5",
            "--psp-steps", "3"]
    out, ref = tmp_path / "out", tmp_path / "ref"
    monkeypatch.setattr(synth, "psp_decode", failing)
    assert fppsim_main(args + ["--out", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["fppsim generate: error: decode broke"]
    assert not (out / "000001").exists() and not list(out.glob(".fppsim-tmp-*"))
    monkeypatch.setattr(synth, "psp_decode", decode)
    assert fppsim_main(args + ["--out", str(out)]) == 0
    assert fppsim_main(args + ["--out", str(ref)]) == 0
    ids = [f"{i:06d}" for i in range(3)]
    assert [r["id"] for r in read_manifest(out)] == ids
    for sid in ids:
        for name in ("fringe.png", "psp/f8_s1.png", "arrays.npz", "meta.json"):
            assert (out / sid / name).read_bytes() == (ref / sid / name).read_bytes(), (sid, name)

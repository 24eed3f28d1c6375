"""Issue 11, second round: shader programs compiled once per renderer. Same bits as before."""

from __future__ import annotations

import numpy as np
import trimesh

from fppsim.rendering.render import DepthRenderer, Instance
from fppsim.geometry.rig import Rig


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

"""Meshes as users have them (QA pass 68c): wound inside out, open scans, stray vertices, symlinked folders.

The depth renders draw only front faces (pyrender culls back faces in DEPTH_ONLY mode whatever the flags),
so a mesh wound inside out or an open surface seen from behind used to be rendered see-through: the
"exact" height was the far side of the object, or the plane under it.
"""

import os

import numpy as np
import pytest
import trimesh

from fppsim.errors import MeshError
from fppsim.geometry.rig import Rig
from fppsim.rendering.render import DepthRenderer
from fppsim.rendering.scene import PlacedObject, asset_from_arrays, find_meshes, load_mesh, render_faces


@pytest.fixture(scope="module")
def renderer():
    r = DepthRenderer()
    yield r
    r.close()


def _capsule():
    return trimesh.creation.capsule(height=60.0, radius=18.0, count=[16, 16])


def _depth(renderer, asset, lift=5.0, flip=False):
    T = np.eye(4)
    if flip:  # upside down (about x), the lowest point still at z = lift
        T[:3, :3] = np.diag([1.0, -1.0, -1.0])
        lift += asset.extents[2]
    T[2, 3] = lift
    obj = PlacedObject(mesh=asset.path, scale=1.0, pose=T, asset=asset, transform=T)
    return renderer.depth(Rig.default().camera, [obj.instance()])  # as a scene draws it


def test_a_mesh_wound_inside_out_renders_its_near_surface(renderer):
    m = _capsule()
    good = asset_from_arrays(m.vertices, m.faces, "good.obj")
    inverted = asset_from_arrays(m.vertices, m.faces[:, ::-1], "inverted.obj")
    a, b = _depth(renderer, good), _depth(renderer, inverted)
    assert np.array_equal(np.isfinite(a), np.isfinite(b))
    seen = np.isfinite(a)
    assert np.abs(a[seen] - b[seen]).max() < 1e-3  # was 35.9 mm: the far side of the capsule


def test_an_open_surface_seen_from_behind_is_not_see_through(renderer):
    # a bowl (lower half of a sphere, normals outward) seen from above: the camera looks at its inside
    s = trimesh.creation.icosphere(subdivisions=3, radius=30.0)
    keep = s.triangles_center[:, 2] < 0
    bowl = trimesh.Trimesh(s.vertices, s.faces[keep], process=False)
    asset = asset_from_arrays(bowl.vertices, bowl.faces, "bowl.ply")
    pole = asset.vertices[np.argmin(bowl.vertices[:, 2])]
    # opening up, its bottom 10 mm above the plane (the canonical frame may have turned it over)
    d = _depth(renderer, asset, lift=10.0, flip=pole[2] > 1.0)
    cam = Rig.default().camera
    centre = d[cam.height // 2 - 5: cam.height // 2 + 5, cam.width // 2 - 5: cam.width // 2 + 5]
    assert np.isfinite(centre).all()  # was inf: seen through the bowl to the plane
    assert np.allclose(centre, 490.0, atol=1.0)


def test_a_closed_outward_mesh_keeps_its_faces():
    m = _capsule()
    asset = asset_from_arrays(m.vertices, m.faces, "good.obj")
    assert np.array_equal(asset.render_faces, asset.faces)  # the renders of well-made meshes stay as they were


def test_a_closed_mesh_split_at_seams_keeps_its_faces():
    """Vertices split at one point (a texture seam of an OBJ read unprocessed, as spot.obj; an STL's triangle soup)
    do not open the mesh: it is drawn as before, one winding (both windings moved a few silhouette pixels)."""
    m = _capsule()
    soup = m.vertices[m.faces].reshape(-1, 3)
    faces = np.arange(len(soup), dtype=np.int32).reshape(-1, 3)
    assert np.array_equal(render_faces(soup, faces), faces)
    assert len(render_faces(soup, faces[:, ::-1])) == 2 * len(faces)  # inside out all the same


def test_a_small_part_wound_inside_out_beside_a_larger_one_is_not_see_through(renderer):
    """Closed parts are judged one by one: the volume summed over a box (outward) and a smaller ball (inside out)
    is positive, and the ball was drawn culled, its far side as its height (29.7 mm off)."""
    box = trimesh.creation.box(extents=[80.0, 60.0, 30.0])
    box.apply_translation([-50.0, 0.0, 15.0])
    ball = trimesh.creation.icosphere(subdivisions=3, radius=15.0)
    ball.apply_translation([40.0, 0.0, 15.0])
    v, n = np.vstack([box.vertices, ball.vertices]), len(box.vertices)
    good = asset_from_arrays(v, np.vstack([box.faces, ball.faces + n]), "parts_good.obj")
    bad = asset_from_arrays(v, np.vstack([box.faces, ball.faces[:, ::-1] + n]), "parts_bad.obj")
    assert len(bad.render_faces) == 2 * len(bad.faces) and np.array_equal(good.render_faces, good.faces)
    a, b = _depth(renderer, good), _depth(renderer, bad)
    assert np.array_equal(np.isfinite(a), np.isfinite(b))
    seen = np.isfinite(a)
    assert np.abs(a[seen] - b[seen]).max() < 1e-3

def test_unreferenced_vertices_do_not_change_the_object(tmp_path):
    m = _capsule()
    stray = np.vstack([m.vertices, [[5000.0, 3000.0, 100.0]]])
    trimesh.Trimesh(stray, m.faces, process=False).export(tmp_path / "stray.ply")
    scan = np.vstack([m.vertices, np.full((10, 3), np.nan)])  # an organised scan: NaN where nothing was seen
    trimesh.Trimesh(scan, m.faces, process=False).export(tmp_path / "scan.ply")
    ref = load_mesh(_write(m, tmp_path / "ref.ply"))
    for name in ("stray.ply", "scan.ply"):
        a = load_mesh(tmp_path / name)  # stray: 5018 units across (the object drawn 50x too small); scan: refused
        np.testing.assert_allclose(a.extents, ref.extents)
        np.testing.assert_allclose(a.hull.max(0) - a.hull.min(0), ref.extents)
    nan_used = m.vertices.copy()
    nan_used[0] = np.nan
    with pytest.raises(MeshError, match="NaN or inf"):
        asset_from_arrays(nan_used, m.faces, "bad.ply")


def _write(mesh, path):
    mesh.export(path)
    return path


def test_symlinked_folders_are_followed_once_and_broken_links_named(tmp_path):
    scans = tmp_path / "scans"
    scans.mkdir()
    _write(_capsule(), scans / "a.obj")
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    _write(_capsule(), meshes / "b.obj")
    os.symlink(scans, meshes / "linked")          # a folder of scans linked in: was ignored without a word
    os.symlink(meshes, meshes / "loop")           # a link back up: must not recurse forever
    os.symlink(tmp_path / "gone.obj", meshes / "gone.obj")  # a broken link: reported, not silently dropped
    found = find_meshes([meshes])
    assert sorted(os.path.basename(p) for p in found) == ["a.obj", "b.obj", "gone.obj"]
    with pytest.raises(MeshError) as e:
        load_mesh(next(p for p in found if p.endswith("gone.obj")))
    assert "gone.obj" in str(e.value) and "\n" not in str(e.value)


def test_a_link_into_the_folders_own_tree_changes_no_name_nor_order(tmp_path):
    """A linked folder the tree already holds is read under its own path: the meshes' names and their order (the
    generator's draws follow it) are those of the tree without the link (it once renamed them after the link,
    and sorted them there)."""
    meshes = tmp_path / "meshes"
    (meshes / "sub").mkdir(parents=True)
    _write(_capsule(), meshes / "sub" / "x.obj")
    _write(_capsule(), meshes / "b.obj")
    before = find_meshes([meshes])
    os.symlink(meshes / "sub", meshes / "0link")
    assert find_meshes([meshes]) == before == [str(meshes / "b.obj"), str(meshes / "sub" / "x.obj")]


@pytest.mark.parametrize("name", ["empty.glb", "empty.obj", "empty.ply", "empty.stl", "empty.off"])
def test_a_zero_byte_mesh_is_named_as_empty(tmp_path, name, capsys):
    """A 0-byte mesh file is named as empty, not by its reader's own IndexError or parse error."""
    from fppsim.cli import main

    p = tmp_path / name
    p.write_bytes(b"")
    assert os.path.getsize(p) == 0
    if name == "empty.glb":  # the truth behind the old message: trimesh's own reason is an IndexError
        with pytest.raises(IndexError):
            trimesh.load(str(p), force="mesh", process=False)
    with pytest.raises(MeshError, match=rf"^{p}: an empty file \(0 bytes\), not a mesh$"):
        load_mesh(p)
    argv = ["generate", "-q", "--no-preview", "--meshes", str(p), "--out", str(tmp_path / "o"), "--count", "1"]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"fppsim generate: error: no usable mesh ({p}: an empty file (0 bytes), not a mesh)"


def test_an_unparsable_mesh_says_it_is_not_a_readable_file_of_its_format(tmp_path):
    cases = {"bad.glb": b"glTF\x02\x00\x00\x00garbage!", "bad.ply": b"ply\nformat ascii 1.0\nelement vertex 3\n"
             b"end_header\n1 2\n", "bad.off": b"nonsense\n"}
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(MeshError) as e:
            load_mesh(tmp_path / name)
        kind = name.split(".")[1].upper()
        assert str(e.value).startswith(f"{tmp_path / name}: not a readable {kind} file (the reader stopped with ")
        assert "\n" not in str(e.value)


GARBAGE = {"bytes": np.random.default_rng(5).bytes(4096), "text": b"hello, this is not a mesh\nsecond line 1 2 3\n"}


@pytest.mark.parametrize("ext", ["stl", "gltf", "glb", "ply", "obj"])
@pytest.mark.parametrize("what", list(GARBAGE))
def test_a_garbage_mesh_file_is_one_line_naming_the_file_and_its_format(tmp_path, ext, what, capsys):
    """Random bytes or text that is not a mesh, under a mesh's name: `fppsim generate` exits 1 with one error line
    naming the file and its format, whatever the reader raised. Text in an .stl / .obj read as a mesh of no triangle
    ('empty mesh (no faces)', no format named); any .gltf that is not JSON as trimesh's search for a 'model.gltf'
    inside it ('FileNotFoundError: model.gltf', naming a file the user never gave)."""
    from fppsim.cli import main

    p = tmp_path / f"bad.{ext}"
    p.write_bytes(GARBAGE[what])
    argv = ["generate", "-q", "--no-preview", "--meshes", str(p), "--out", str(tmp_path / "o"), "--count", "1"]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"fppsim generate: error: no usable mesh ({p}: not a readable {ext.upper()} file (")
    assert "model.gltf" not in err[-1] and not any("Traceback" in line for line in err)
    assert not (tmp_path / "o").exists()


def test_a_mesh_read_from_garbage_names_its_format_with_what_is_wrong(tmp_path):
    """Bytes a reader takes for a mesh whose vertices are NaN, or whose faces point past its vertices."""
    nan = tmp_path / "nan.stl"  # a binary STL: 80-byte header, 3 triangles of 0xff bytes (NaN floats)
    nan.write_bytes(bytes(80) + (3).to_bytes(4, "little") + b"\xff" * 150)
    with pytest.raises(MeshError, match=rf"^{nan}: unusable mesh in this STL file: vertices contain NaN or inf$"):
        load_mesh(nan)
    far = tmp_path / "far.ply"
    far.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                   "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 9\n")
    with pytest.raises(MeshError, match=rf"^{far}: unusable mesh in this PLY file: face indices out of range$"):
        load_mesh(far)


def test_a_folders_mesh_in_a_format_not_read_is_named_not_dropped(tmp_path, capsys):
    """A .fbx / .3mf beside the meshes was left out of a --meshes folder without a word; it is now a skipped mesh
    with its reason, and a folder holding only such files says why nothing can be drawn."""
    from fppsim.cli import main
    from fppsim.generation import load_assets

    only = tmp_path / "only"
    only.mkdir()
    for name in ("statue.fbx", "bust.3mf"):
        (only / name).write_bytes(b"not read here")
    (only / "notes.txt").write_text("a note")  # not a mesh: never mentioned
    assets, skipped = load_assets([only])
    assert assets == []
    assert [os.path.basename(p) for p, _ in skipped] == ["bust.3mf", "statue.fbx"]
    assert all(".obj .ply .stl .off .glb .gltf" in r and "not a mesh format read here" in r for _, r in skipped)
    argv = ["generate", "-q", "--no-preview", "--meshes", str(only), "--out", str(tmp_path / "o"), "--count", "1"]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("fppsim generate: error: no usable mesh (") and "statue.fbx: .fbx is not a mesh format" in err
    assert not (tmp_path / "o").exists()
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    trimesh.creation.box((10.0, 10.0, 10.0)).export(mixed / "box.obj")
    (mixed / "statue.fbx").write_bytes(b"not read here")
    assets, skipped = load_assets([mixed])
    assert len(assets) == 1 and [os.path.basename(p) for p, _ in skipped] == ["statue.fbx"]
    assert find_meshes([mixed]) == [str(mixed / "box.obj")]  # what is drawn is unchanged

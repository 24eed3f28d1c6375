"""fppsim.phase.unwrap: regions, spatial unwrapping, step conflicts and shadow bridges on analytic phases."""

import numpy as np

from fppsim.phase.unwrap import phase_quality, phase_regions, shadow_bridges, step_conflicts


def wrap(x):
    return (x + np.pi) % (2 * np.pi) - np.pi


def test_regions_unwrap_each_part_exactly_up_to_its_order():
    y, x = np.mgrid[0:60, 0:120].astype(float)
    phi = 0.55 * x + 0.02 * y + 0.3 * np.sin(y / 9.0)
    usable = np.ones(phi.shape, bool)
    usable[:, 58:62] = False  # two regions
    reg = phase_regions(wrap(phi), usable)
    assert reg.count == 2
    for k in (1, 2):
        m = reg.labels == k
        d = reg.unwrapped[m] - phi[m]
        assert np.ptp(d) < 1e-9  # exact inside the region ...
        assert abs(d[0] / (2 * np.pi) - round(d[0] / (2 * np.pi))) < 1e-9  # ... up to whole periods
    assert np.isnan(reg.unwrapped[~usable]).all()


def test_step_conflicts_mark_an_aliasing_wall_and_nothing_on_smooth_relief():
    y, x = np.mgrid[0:40, 0:100].astype(float)
    wall = np.where(x >= 50, -31.0, 0.0)  # about 5 periods lost in one pixel: the fringes alias
    phi = 0.55 * x + 0.3 * np.sin(x / 7) + wall
    expected = 0.55 * x + 0.3 * np.sin(x / 7) + np.where(x >= 50, -31.0, 0.0) + 0.2 * np.cos(y / 5)
    c = step_conflicts(wrap(phi), expected, max_step=1.0)
    assert c[:, 49:51].all() and not c[:, :48].any() and not c[:, 52:].any()
    # a wall the estimate does not know about is invisible to this test by construction: no conflict
    assert not step_conflicts(wrap(phi), 0.55 * x + 0.3 * np.sin(x / 7), 1.0)[:, 52:].any()


def test_phase_quality_is_small_on_fringes_and_large_on_a_step():
    y, x = np.mgrid[0:30, 0:60].astype(float)
    phi = 0.6 * x + np.where(x >= 30, 2.0, 0.0)
    q = phase_quality(wrap(phi))
    assert q[:, 5:25].max() < 1e-9 and q[:, 29:32].max() > 0.3


def test_shadow_bridge_recovers_the_order_difference_across_a_shadow():
    # along each row the plane's phase runs up to the shadow; the object after the shadow starts with
    # the phase the grazing projector ray carried (the plane's phase at the shadow's start)
    H, W = 40, 200
    x = np.arange(W, dtype=float)
    phi = np.empty((H, W))
    start, stop = 80, 110
    for r in range(H):
        phi[r] = 0.52 * x + 0.01 * r
        phi[r, stop:] = phi[r, start - 1] + 0.52 + 0.45 * (x[stop:] - stop)  # surface seen after the shadow
    shadow = np.zeros((H, W), bool)
    shadow[:, start:stop] = True
    reg = phase_regions(wrap(phi), ~shadow)
    bridges = shadow_bridges(reg, shadow, step=1)
    assert len(bridges) == 1
    b = bridges[0]
    ma = (phi - reg.unwrapped)[reg.labels == b.a][0] / (2 * np.pi)
    mb = (phi - reg.unwrapped)[reg.labels == b.b][0] / (2 * np.pi)
    assert round(mb - ma) == b.periods and b.votes == H and b.agreement == 1.0


def test_shadow_bridge_needs_agreeing_votes():
    rng = np.random.default_rng(0)
    H, W = 40, 200
    x = np.arange(W, dtype=float)
    phi = np.tile(0.52 * x, (H, 1))
    phi[:, 110:] += rng.uniform(0, 2 * np.pi * 6, size=(H, 1))  # every row a different order: no bridge
    shadow = np.zeros((H, W), bool)
    shadow[:, 80:110] = True
    reg = phase_regions(wrap(phi), ~shadow)
    # rows after the shadow carry unrelated orders: whatever regions they form, no bridge is trusted
    assert shadow_bridges(reg, shadow) == []


def _box_scene(rig, box=(-25.0, 25.0, -20.0, 20.0, 30.0)):
    """A box standing on the reference plane, seen through ``rig`` at the camera's pixel centres, by ray
    casting written here: each pixel's absolute projector phase (rad) and whether projector light reaches it."""
    x0, x1, y0, y1, h = box
    lo, hi = np.array([x0, y0, 0.0]), np.array([x1, y1, h])

    def slab(o, d):  # entry / exit parameters of rays o + t d through the box
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - o) / d, (hi - o) / d
        tn = np.nanmax(np.minimum(t1, t2), axis=-1)
        tx = np.nanmin(np.maximum(t1, t2), axis=-1)
        return tn, tx

    cam = rig.camera
    origin, d = cam.pixel_rays(cam.pixel_grid())
    t_plane = -origin[2] / d[..., 2]
    tn, tx = slab(origin, d)
    t = np.where((tn <= tx) & (tn > 0) & (tn < t_plane), tn, t_plane)
    X = origin + t[..., None] * d
    to_proj = rig.projector.center - X
    tn, tx = slab(X + 1e-6 * to_proj, to_proj)
    lit = ~((tn <= tx) & (tx > 0) & (tn < 1))
    uv_p, _ = rig.projector.project(X)
    return rig.phase_of_column(uv_p[..., 0]), lit


def test_shadow_bridge_across_a_box_shadow_finds_the_true_order():
    """The shadow a box casts on the plane links the plane to the box's top at their true order difference
    (ray-cast geometry through the default rig, exact phases at the pixel centres)."""
    from fppsim.geometry.rig import Rig

    phase, lit = _box_scene(Rig.default())
    shadow = ~lit
    assert 2000 < shadow.sum() < 20000
    reg = phase_regions(wrap(phase), lit)
    offsets = np.round((phase - reg.unwrapped) / (2 * np.pi))  # each region's true order
    bridges = shadow_bridges(reg, shadow)
    assert bridges, "no bridge across the box's shadow"
    for b in bridges:
        ka = offsets[reg.labels == b.a][0]
        kb = offsets[reg.labels == b.b][0]
        assert kb - ka == b.periods and b.agreement >= 0.9
    # the plane (largest region) is linked to the box top
    assert any(1 in (b.a, b.b) and b.votes >= 20 for b in bridges)


def test_shadow_bridge_removes_the_images_common_vote_offset():
    """Votes a common fraction of a period off their orders (the single-shot phase beside a shadow is biased), one
    shadow's further than the bridge margin: ``about="image"`` removes the image's offset and finds both orders;
    the median rule with the same margin loses that one."""
    H, W = 60, 300
    x = np.arange(W, dtype=float)
    phi = np.tile(0.6 * x, (H, 1)) + 0.01 * np.arange(H)[:, None]
    shadow = np.zeros((H, W), bool)
    built = {}
    for start, stop, end, k, off in ((60, 90, 180, 2, 0.40), (180, 210, W, -3, 0.27)):
        shadow[:, start:stop] = True
        # read one pixel inside each side (step -1): there the far side's phase is the near side's minus k + off
        ref = phi[:, start - 2] - 2 * np.pi * (k + off)
        phi[:, stop:end] = ref[:, None] + 0.5 * (x[stop:end] - (stop + 1))
        built[start] = k
    reg = phase_regions(wrap(phi), ~shadow)
    assert reg.count == 3
    m = np.round((phi - reg.unwrapped) / (2 * np.pi))  # each region's own multiple of 2 pi
    found = shadow_bridges(reg, shadow, about="image", max_offset=0.35)
    assert len(found) == 2
    for b in found:
        start = 60 if (reg.labels[:, 30] == b.a).all() else 180
        ka, kb = m[reg.labels == b.a][0], m[reg.labels == b.b][0]
        assert b.periods == built[start] + kb - ka and b.agreement == 1.0
    assert len(shadow_bridges(reg, shadow, about="median", max_offset=0.35)) == 1


def test_shadow_runs_finds_every_crossing_as_a_plain_row_walk_does():
    """shadow_runs against a per-pixel walk written here: every run of shadow with a lit pixel on both sides."""
    from fppsim.phase.unwrap import shadow_runs

    rng = np.random.default_rng(4)
    for density in (0.1, 0.5, 0.9):
        sh = rng.random((17, 40)) < density
        sh[3] = True  # a row all in shadow: no crossing
        sh[5, :6] = True  # a run from the left border: not a crossing
        want = []
        for r in range(sh.shape[0]):
            x = 0
            while x < sh.shape[1]:
                if sh[r, x]:
                    e = x
                    while e < sh.shape[1] and sh[r, e]:
                        e += 1
                    if x > 0 and e < sh.shape[1]:
                        want.append((r, x - 1, e))
                    x = e
                else:
                    x += 1
        got = shadow_runs(sh)
        assert got.dtype == np.int64 and got.shape[1] == 3
        assert [tuple(map(int, g)) for g in got] == want
    assert shadow_runs(np.zeros((4, 5), bool)).shape == (0, 3)

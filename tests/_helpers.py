"""Shared test helpers: the ../shared paths (computed once here) and tiny on-disk datasets.

The fringe encodes the height in a way a tiny CNN learns in a few epochs: vertical fringes whose
brightness envelope grows with the height (plus a phase shift), on a dark plane, with a projector
shadow (invalid pixels) beside each object. Label transform: the figshare preset
(label = 6 * height_mm - 97, invalid = -105 with fringe -1 there).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"  # third-party test data beside the checkout; tests skip cleanly without it
SHARED_MESHES = SHARED / "meshes"
REAL_SAMPLE = SHARED / "real-sample"


def one_line(capsys, *parts) -> str:
    """The captured stderr: one line, no traceback, naming every one of ``parts``."""
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    for p in parts:
        assert p in err, err
    return err


def unreadable(monkeypatch, folder) -> None:
    """``folder`` as the file system shows another user's folder of mode 700 (``lost+found`` on a disk's root):
    listed in its parent, but nothing in it can be listed or looked at (PermissionError). Simulated, since root,
    running these tests, ignores permission bits."""
    import errno
    import os

    folder = os.path.abspath(folder)

    def denied(real, inside: bool):
        def call(path=".", *args, **kwargs):
            p = os.path.abspath(os.fsdecode(path)) if isinstance(path, (str, bytes, os.PathLike)) else ""
            if p.startswith(folder + os.sep) if inside else p == folder:
                raise PermissionError(errno.EACCES, "Permission denied", p)
            return real(path, *args, **kwargs)
        return call

    monkeypatch.setattr(os, "stat", denied(os.stat, True))
    monkeypatch.setattr(os, "listdir", denied(os.listdir, False))
    monkeypatch.setattr(os, "scandir", denied(os.scandir, False))


def wrap_phase(x):
    """Wrap rad into (-pi, pi] (independent of the code under test)."""
    return np.angle(np.exp(1j * np.asarray(x, dtype=np.float64)))


def figurine_on_black(period: float, noise: float = 0.0, seed: int = 0, H: int = 448, W: int = 640):
    """A figurine on black as FP672/541 with its plane blacked out shows it (measured there: 14 % of the view; the
    side facing the projector at gray 49 with fringes of amplitude 11, the side turned away at 17 with about 1):
    ``(image uint8, absolute phase, body mask, lit-side period px)``. The lit side's fringes run 0.9 x the plane's
    ``period`` apart (vertical, bent down the rows), the dark side's 3 x; both sides shaded slowly. ``noise``: a
    camera's gray noise, and a 0-3 gray background instead of exact black."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:H, 0:W].astype(np.float64)
    body = ((c - 0.52 * W) / (0.11 * W)) ** 2 + ((r - 0.71 * H) / (0.31 * H)) ** 2 <= 1
    lit = body & (c >= 0.52 * W)
    c0 = 0.52 * W  # the sides meet here, their phase continuous (as a scan's absolute phase)
    phase = 2 * np.pi * c0 / (0.9 * period) + 2 * np.pi * (c - c0) / np.where(lit, 0.9 * period, 3.0 * period)
    phase += np.where(lit, 3.0 * np.sin(r / 25.0), 0.0)
    shade = 12 * np.sin(r / 23.0) * np.cos(c / 31.0)  # the surface's slow shading: the outline's spectrum
    img = np.where(lit, 50 + shade + 11 * np.cos(phase), 17 + shade / 2 + np.cos(phase))
    img = img + noise * rng.standard_normal(img.shape)
    img = np.where(body, img, rng.integers(0, 4, img.shape) if noise else 0.0)
    # the lit side's period: 2 pi over the median gradient of its phase (columns 2 pi / 0.9 P, rows the bend)
    g = np.hypot(2 * np.pi / (0.9 * period), 3.0 / 25.0 * np.cos(r[lit] / 25.0))
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), phase, body, float(2 * np.pi / np.median(g))


def disc_shadow(obj: np.ndarray, phase: np.ndarray, plane_phase: np.ndarray) -> np.ndarray:
    """The projector shadow beside an object standing on the plane, from the phases alone (fppsim's rigs: the
    phase grows along +columns): a plane pixel left of a row's first object pixel is dark when that edge carries a
    smaller phase, since the ray that would light it hits the object first. (H, W) bool; ``obj``, ``phase``
    (the scene's), ``plane_phase`` (the bare plane's) are (H, W)."""
    shadow = np.zeros(obj.shape, bool)
    for r in np.nonzero(obj.any(axis=1))[0]:
        xe = int(np.argmax(obj[r]))
        shadow[r, :xe] = plane_phase[r, :xe] > phase[r, xe]
    return shadow


def synthesize_stack(phase: np.ndarray, background=0.5, modulation=0.5, n_steps: int = 4,
                     shifts: np.ndarray | None = None) -> np.ndarray:
    """Analytic phase-shifting stack ``I_n = A + B cos(phase + delta_n)``, float64 of shape (N, *phase.shape)
    (fppsim.phase.psp's convention); ``background`` and ``modulation`` broadcast against ``phase``;
    ``shifts`` default ``delta_n = 2 pi n / N``."""
    p = np.asarray(phase, dtype=np.float64)
    d = 2.0 * np.pi * np.arange(n_steps) / n_steps if shifts is None else np.asarray(shifts, dtype=np.float64).ravel()
    d = d.reshape((-1,) + (1,) * p.ndim)
    return np.asarray(background, np.float64) + np.asarray(modulation, np.float64) * np.cos(p + d)


def scene(rng: np.random.Generator, h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(fringe8 uint8, height_mm float32, valid bool) of one random scene of 1-2 blobs."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    height = np.zeros((h, w))
    valid = np.ones((h, w), bool)
    for _ in range(int(rng.integers(1, 3))):
        cy, cx = rng.uniform(0.25, 0.75) * h, rng.uniform(0.2, 0.7) * w
        r = rng.uniform(0.12, 0.25) * min(h, w)
        peak = rng.uniform(10, 40)
        blob = peak * np.clip(1 - ((yy - cy) ** 2 + (xx - cx) ** 2) / r**2, 0, None) ** 0.5
        height = np.maximum(height, blob)
        shadow = ((yy - cy) ** 2 + (xx - cx - r - 2) ** 2 < (0.35 * r) ** 2) & (blob == 0)
        valid &= ~shadow
    envelope = 0.25 + 0.6 * height / 40.0
    fringe = 255 * envelope * (0.5 + 0.5 * np.cos(2 * np.pi * xx / 11.6 + 0.2 * height))
    fringe += rng.normal(0, 2.0, (h, w))
    fringe8 = np.clip(np.round(fringe), 0, 255).astype(np.uint8)
    fringe8[~valid] = 0
    return fringe8, height.astype(np.float32), valid


def write_figshare(folder, n: int = 8, h: int = 32, w: int = 64, seed: int = 0, squeeze: bool = False,
                   fringe_name: str = "f1_80.npy", label_name: str = "Z.npy") -> tuple[np.ndarray, np.ndarray]:
    """f1_80.npy + Z.npy, float32 (N, H, W, 1), figshare encoding. Returns (fringes, labels)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    fr = np.empty((n, h, w, 1), np.float32)
    z = np.empty((n, h, w, 1), np.float32)
    for i in range(n):
        f8, hmm, valid = scene(rng, h, w)
        fr[i, ..., 0] = f8.astype(np.float32) / 127.5 - 1
        lab = (hmm * 6.0 - 97.0).astype(np.float32)
        lab[~valid] = -105.0
        fr[i, ..., 0][~valid] = -1.0
        z[i, ..., 0] = lab
    if squeeze:
        fr, z = fr[..., 0], z[..., 0]
    np.save(folder / fringe_name, fr)
    np.save(folder / label_name, z)
    return fr, z


def write_native(folder, n: int = 8, h: int = 32, w: int = 64, seed: int = 0, psp: bool = False) -> list[str]:
    """fppsim native layout written by fppsim's own writer (write_sample_folder + reconcile)."""
    from fppsim.dataio.formats import reconcile, sample_id
    from fppsim.dataio.writers import write_sample_folder

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    ids = []
    for i in range(n):
        sid = sample_id(i)
        f8, hmm, valid = scene(rng, h, w)
        arrays = {"height": hmm, "depth": (500.0 - hmm).astype(np.float32),
                  "phase_true": np.zeros_like(hmm), "mask": valid.astype(np.float32)}
        if psp:
            arrays.update(height_psp=hmm + np.float32(0.01), mask_psp=valid.astype(np.float32),
                          phase_psp=np.zeros_like(hmm))
        meta = {"index": i, "seed": i, "version": "test", "rig": {}, "objects": [],
                "stats": {"valid_fraction": float(valid.mean())}}
        write_sample_folder(folder, sid, {"fringe.png": f8}, arrays, meta)
        ids.append(sid)
    reconcile(folder)
    return ids


def train_tiny(out, *data_args, model: str = "unet", epochs: int = 1, extra=()) -> Path:
    """Train a tiny model through the CLI (base 4 channels); returns the run folder."""
    from uhrnet.cli import main

    rc = main(["train", *map(str, data_args), "--model", model, "--base-channels", "4", "--epochs", str(epochs),
               "--loss", "l2", "--lr", "1e-3", "--out", str(out), "--no-progress", *map(str, extra)])
    assert rc == 0
    return Path(out)


def tiny_rig(width: int = 64, height: int = 32):
    """A window of the default rig's camera (same focal length, centred): ``width`` x ``height`` px with
    the default fringe period (about 11.6 px) and phase sensitivity (about 0.87 rad/mm), for tiny
    physics-head, adaptation and refinement tests."""
    from fppsim.geometry.rig import Device, Rig, make_default_rig

    r = make_default_rig()
    c = r.camera
    K = c.K.copy()
    K[0, 2] -= (c.width - width) / 2
    K[1, 2] -= (c.height - height) / 2
    cam = Device(K=K, R=c.R, t=c.t, width=width, height=height, dist=c.dist)
    return Rig(cam, r.projector, periods=r.periods)


def distorted_rig():
    """The default rig with strong lens distortion on both devices (OpenCV k1, k2, p1, p2, k3), for
    checks that every projection and ray goes through the distortion model."""
    from fppsim.geometry.rig import Device, Rig, make_default_rig

    def with_dist(dev, dist):
        return Device(K=dev.K, R=dev.R, t=dev.t, width=dev.width, height=dev.height, dist=dist)

    r = make_default_rig()
    return Rig(with_dist(r.camera, [-0.08, 0.05, 1e-3, -5e-4, 0.01]),
               with_dist(r.projector, [0.06, -0.03, -8e-4, 6e-4, 0.002]), periods=80.0, name="distorted")


def rig_fringe(rig, height_mm: np.ndarray, valid: np.ndarray | None = None, offset: float = 0.0) -> np.ndarray:
    """8-bit single-shot image ``120 + 100 cos(phase_true + offset)`` of a height map seen by ``rig``
    (fppsim's forward model, :func:`fppsim.fitting.height_sensitivity.surface_phase`); 0 where not ``valid``."""
    from fppsim.fitting.height_sensitivity import surface_phase

    f8 = np.round(120 + 100 * np.cos(surface_phase(rig, height_mm) + offset)).astype(np.uint8)
    if valid is not None:
        f8[~valid] = 0
    return f8


#: three boxes in the default rig's view (world mm: x0, x1, y0, y1, height), each casting a shadow onto the plane
BOXES = [(-80, -30, -30, 30, 25.0), (20, 70, -45, 5, 35.0), (-5, 25, 30, 55, 15.0)]


def box_scene(rig, boxes=BOXES) -> tuple[np.ndarray, np.ndarray]:
    """``(height_mm, lit)`` of upright boxes standing on the reference plane seen through ``rig``, ray traced: each
    camera ray meets the highest box top over its cut, else the plane, unless a box wall comes first (unlit); a
    surface point is lit when its segment to the projector centre misses every box (a shadow otherwise).
    ``boxes``: ``(x0, x1, y0, y1, height)`` mm in the world frame."""
    cam = rig.camera
    uv = cam.pixel_grid()
    height, top = np.zeros(uv.shape[:2]), np.zeros(uv.shape[:2], bool)
    for x0, x1, y0, y1, h in sorted(boxes, key=lambda b: -b[4]):
        X = cam.ray_cut(uv, float(h))[1]
        on = ~top & (X[..., 0] >= x0) & (X[..., 0] <= x1) & (X[..., 1] >= y0) & (X[..., 1] <= y1)
        height[on], top = h, top | on
    X0 = cam.ray_cut(uv, 0.0)[1]
    lit = ~top & ~np.any([(X0[..., 0] >= b[0]) & (X0[..., 0] <= b[1]) & (X0[..., 1] >= b[2]) & (X0[..., 1] <= b[3])
                          for b in boxes], axis=0) | top
    P = cam.ray_cut(uv, height)[1]
    d = rig.projector.center - P
    for x0, x1, y0, y1, h in boxes:  # slab test of the segment P + t d, 0 < t <= 1
        with np.errstate(divide="ignore", invalid="ignore"):
            t = [((lo - P[..., k]) / d[..., k], (hi - P[..., k]) / d[..., k]) for k, lo, hi in
                 ((0, x0, x1), (1, y0, y1), (2, 0.0, float(h)))]
        enter = np.max([np.minimum(a, b) for a, b in t], axis=0)
        leave = np.min([np.maximum(a, b) for a, b in t], axis=0)
        lit &= ~((enter < leave) & (leave > 1e-6) & (enter < 1.0))
    return height, lit


def write_native_rig(folder, rig, n: int = 6, seed: int = 0) -> list[str]:
    """Native samples of ``rig``'s camera size whose fringe, ``phase_true`` and ``meta.json`` rig are
    consistent (the image is :func:`rig_fringe` of the sample's height): data ``--head phase`` trains on."""
    from fppsim.dataio.formats import reconcile, sample_id
    from fppsim.fitting.height_sensitivity import surface_phase
    from fppsim.dataio.writers import write_sample_folder

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    h, w = rig.camera.height, rig.camera.width
    ids = []
    for i in range(n):
        sid = sample_id(i)
        _, hmm, valid = scene(rng, h, w)
        hmm = (hmm / 4.0).astype(np.float32)  # 2.5-10 mm blobs: a few fringe periods of relief
        arrays = {"height": hmm, "depth": (500.0 - hmm).astype(np.float32),
                  "phase_true": surface_phase(rig, hmm).astype(np.float32), "mask": valid.astype(np.float32)}
        meta = {"index": i, "seed": i, "version": "test", "rig": rig.to_dict(), "objects": [],
                "stats": {"valid_fraction": float(valid.mean())}}
        write_sample_folder(folder, sid, {"fringe.png": rig_fringe(rig, hmm, valid)}, arrays, meta)
        ids.append(sid)
    reconcile(folder)
    return ids


def reference_plane_height(dphi, L, d, f0):
    """Classic reference-plane phase-to-height formula ``h = L dphi / (dphi + 2 pi f0 d)``.

    Parameters
    ----------
    dphi : phase difference (rad) between the reference plane and the object at the same camera pixel,
        ``dphi = Phi_reference - Phi_object``; positive for points above the plane when ``d > 0``.
    L : distance (mm) from the camera (and projector) centre to the reference plane.
    d : baseline (mm) between camera and projector centres, measured along the direction in which the
        projected phase increases on the plane (signed: negative if the projector sits on the other side).
    f0 : fringe frequency on the reference plane (periods per mm).

    Returns
    -------
    height (mm) above the plane, float64, broadcast over the inputs.

    Exact for the geometry it assumes: camera and projector centres at the same height ``L``, both
    optical axes perpendicular to the plane, fringes uniform on the plane (a parallel-axis rig with projector lens shift such as :func:`fppsim.geometry.rig.make_parallel_rig`). Derivation:
    a camera ray meets the plane at ``x`` and the object at height ``h`` at ``x (L-h)/L``; the projector
    column of that point differs from the plane's by ``-fx_p d h / (L (L-h))``, so
    ``dphi = 2 pi f0 d h/(L - h)``, which solves to the formula.
    """
    dphi = np.asarray(dphi, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return L * dphi / (dphi + 2.0 * np.pi * np.asarray(f0, np.float64) * np.asarray(d, np.float64))


def reference_plane_parameters(rig, periods: float | None = None, atol: float = 1e-9) -> tuple[float, float, float]:
    """``(L, d, f0)`` of a parallel-axis rig for :func:`reference_plane_height`.

    ``L`` = camera height above the plane (mm), ``d`` = signed baseline along world x (mm),
    ``f0 = f fx_p / (W_p L)`` periods per mm on the plane. Raises ValueError unless both optical axes
    point straight down, the projector columns run along world x without skew, and both centres are
    at the same height (where the formula is exact).
    """
    cam, proj = rig.camera, rig.projector
    f = rig.periods if periods is None else float(periods)
    down = np.array([0.0, 0.0, -1.0])
    if not (np.allclose(cam.R[2], down, atol=atol) and np.allclose(proj.R[2], down, atol=atol)):
        raise ValueError("reference-plane formula needs both optical axes perpendicular to the plane")
    if abs(proj.K[0, 1]) > atol or abs(abs(proj.R[0, 0]) - 1.0) > atol:
        raise ValueError("reference-plane formula needs projector columns along world x (no skew or rotation)")
    L, Lp = cam.center[2], proj.center[2]
    if abs(L - Lp) > atol * max(1.0, L):
        raise ValueError(f"reference-plane formula needs camera and projector at one height ({L} vs {Lp} mm)")
    sx = np.sign(proj.R[0, 0])  # +1 when projector columns increase with world x
    d = float(sx * (proj.center[0] - cam.center[0]))
    f0 = float(f * proj.K[0, 0] / (proj.width * L))
    return float(L), d, f0


def load_pipeline(name: str):
    """The module of ``pipelines/<name>.py`` (pipelines are scripts, not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, Path(__file__).resolve().parents[1] / "pipelines" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def adapt_setup(tmp_path):
    """A tiny trained run, the rig file and two unlabelled real fringes of bumps through that rig, as the
    adapt tests use them: ``(source run, rig path, real folder)``."""
    write_figshare(tmp_path / "syn", n=6, h=32, w=64, seed=1)
    source = train_tiny(tmp_path / "src", "--real", tmp_path / "syn", "--real-split", "train")
    rig = tiny_rig()
    rig.save(tmp_path / "rig.json")
    yy, xx = np.mgrid[0:32, 0:64].astype(float)
    bumps = [peak * np.exp(-((xx - cx) ** 2 + (yy - 15) ** 2) / 128) for peak, cx in ((6.0, 30.0), (4.0, 40.0))]
    real = tmp_path / "real"
    real.mkdir()
    np.save(real / "f1_80.npy", (np.stack([rig_fringe(rig, b) for b in bumps]) / 127.5 - 1)[..., None].astype(np.float32))
    return source, tmp_path / "rig.json", real


def tiny_psp_root(root, n: int = 1):
    """A tiny scan folder in the public layout (PSin/ PCos/ Fringe/ iPattern/) at ``root``: ``n`` frames of 64 x 32
    px (:func:`scene`, vertical fringes 11.6 px apart), ids ``0``..``n-1``. Returns ``root``."""
    from fppsim.dataio.writers import save_psp_folder_sample, sums_from_phase

    rng = np.random.default_rng(7)
    xx = np.arange(64)[None, :] * np.ones((32, 1))
    for i in range(n):
        img, height, valid = scene(rng, 32, 64)
        save_psp_folder_sample(root, f"{i}", *sums_from_phase(1.0 + 2 * np.pi * xx / 11.6 - 0.45 * height, valid, 30.0),
                               img)
    return root

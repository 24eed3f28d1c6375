"""The reference code's UHRNet weights (fead1/UHRNet) <-> ours: `uhrnet.inference.reference_weights`, `uhrnet
import-weights`, `uhrnet export --format reference`.

The truth here does not come from the code under test: this file describes the reference network's
state-dict layout (module names, shapes, order) and its forward pass on its own, from the paper's
architecture and the reference's published module names (no reference code is copied; the real code was
checked outside the repository, see the commit message), at any base width so the forward runs small.
"""

from __future__ import annotations

import argparse

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from fppsim.dataio.formats import PRESETS
from uhrnet.checkpoint import FORMAT, VERSION, load_checkpoint, model_from_checkpoint
from uhrnet.cli import main
from uhrnet.errors import CheckpointError
from uhrnet.models import build_model
from uhrnet.inference.reference_weights import (
    from_reference_state_dict,
    key_table,
    read_reference_file,
    reference_output_affine,
    to_reference_state_dict,
)

@pytest.fixture(autouse=True)
def _one_thread(one_thread):
    """Single-threaded torch: the forwards here are small, and other processes share the CPUs."""


# ------------------------------------------------------------------------------------- the reference, described
BN_KEYS = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")


def resb(name: str, cin: int, cout: int) -> list[tuple[str, tuple]]:
    """The reference's Multi-Level conv Block ``ResB``: ``branch0`` (1x1 conv ``conv0`` + ``bt0``, the
    shortcut), ``branch1`` (``conv1``/``bt1``), ``branchK`` for K = 2..4 (``convK_1 .. convK_K`` with
    ``btK_j``), each branch ``cout / 4`` wide. Rows ``(key, shape)``."""
    q = cout // 4

    def conv(m, o, i, k):
        return [(f"{m}.weight", (o, i, k, k)), (f"{m}.bias", (o,))]

    def bn(m, c):
        return [(f"{m}.{p}", () if p == "num_batches_tracked" else (c,)) for p in BN_KEYS]

    rows = conv(f"{name}.branch0.conv0", cout, cin, 1) + bn(f"{name}.branch0.bt0", cout)
    rows += conv(f"{name}.branch1.conv1", q, cin, 3) + bn(f"{name}.branch1.bt1", q)
    for k in (2, 3, 4):
        for j in range(1, k + 1):
            rows += conv(f"{name}.branch{k}.conv{k}_{j}", q, cin if j == 1 else q, 3) + bn(f"{name}.branch{k}.bt{k}_{j}", q)
    return rows


def reference_layout(b: int = 64) -> list[tuple[str, tuple]]:
    """Every state-dict entry of the reference ``UHRNet`` (at base width ``b``; the real one is 64), in its
    registration order: down1-4, res, up1-4 (transposed conv ``up`` then ``res``), outc, then the fusion
    layers of levels 1, 2, 3 (resampling layers, ``covN`` mixing, ``covN_`` merging)."""
    def conv(m, o, i, k):
        return [(f"{m}.weight", (o, i, k, k)), (f"{m}.bias", (o,))]

    def tconv(m, i, o):  # ConvTranspose2d weights are (in, out, k, k)
        return [(f"{m}.weight", (i, o, 3, 3)), (f"{m}.bias", (o,))]

    def cbl(m, o, i):
        return conv(f"{m}.conv", o, i, 3) + [(f"{m}.bt.{p}", () if p == "num_batches_tracked" else (o,)) for p in BN_KEYS]

    w = [b, 2 * b, 4 * b, 8 * b, 16 * b]
    rows = []
    for i, (cin, cout) in enumerate(zip([1, *w[:3]], w[:4])):
        rows += resb(f"down{i + 1}.res", cin, cout)
    rows += resb("res", w[3], w[4])
    for i in range(4):
        rows += tconv(f"up{i + 1}.up", w[4 - i], w[3 - i]) + resb(f"up{i + 1}.res", 2 * w[3 - i], w[3 - i])
    rows += conv("outc.conv", 1, b, 1)
    h = [c // 2 for c in w]  # fusion branch widths: half of the level's own
    rows += tconv("up1_", w[1], h[0]) + tconv("up2_", w[2], h[0]) + tconv("up3_", w[3], h[0])
    rows += cbl("cov1", w[0], 3 * h[0]) + cbl("cov1_", w[0], 2 * w[0])
    rows += conv("down0_", h[1], w[0], 2) + tconv("up2__", w[2], h[1]) + tconv("up3__", w[3], h[1])
    rows += cbl("cov2", w[1], 3 * h[1]) + cbl("cov2_", w[1], 2 * w[1])
    rows += conv("down0__", h[2], w[0], 4) + conv("down1_", h[2], w[1], 2) + tconv("up3___", w[3], h[2])
    rows += cbl("cov3", w[2], 3 * h[2]) + cbl("cov3_", w[2], 2 * w[2])
    return rows


def random_reference_state(b: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random weights and batch-norm statistics in the reference layout (eval-mode BNs not the identity)."""
    g = torch.Generator().manual_seed(seed)
    state = {}
    for key, shape in reference_layout(b):
        if key.endswith("num_batches_tracked"):
            state[key] = torch.tensor(7)
        elif key.endswith("running_var"):
            state[key] = torch.rand(shape, generator=g) + 0.5
        elif ".bt" in key and key.endswith("weight"):
            state[key] = torch.rand(shape, generator=g) + 0.5
        else:
            fan = int(np.prod(shape[1:])) if len(shape) > 1 else 4
            state[key] = (torch.rand(shape, generator=g) * 2 - 1) / fan ** 0.5
    return state


def reference_forward(s: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """The reference network in eval mode, written from its description: LeakyReLU(0.01) inside branches
    and after the block sum; decoder ``cat(upsampled, skip)``; fusion at level 1 concatenates the maps from
    levels 4, 3, 2 (coarsest first), at levels 2 and 3 finest first; ``cat(own map, mixed)`` then merge."""
    def conv(m, t, stride=1, padding=0, dilation=1):
        return F.conv2d(t, s[f"{m}.weight"], s[f"{m}.bias"], stride, padding, dilation)

    def tconv(m, t, stride, padding, output_padding):
        return F.conv_transpose2d(t, s[f"{m}.weight"], s[f"{m}.bias"], stride, padding, output_padding)

    def bn(m, t):
        return F.batch_norm(t, s[f"{m}.running_mean"], s[f"{m}.running_var"], s[f"{m}.weight"], s[f"{m}.bias"],
                            False, 0.0, 1e-5)

    act = lambda t: F.leaky_relu(t, 0.01)  # noqa: E731

    def block(n, t):
        outs = [bn(f"{n}.branch1.bt1", conv(f"{n}.branch1.conv1", t, padding=1))]
        for k, dils in ((2, (1, 1)), (3, (1, 1, 2)), (4, (1, 1, 2, 5))):
            y = t
            for j, d in enumerate(dils, 1):
                y = bn(f"{n}.branch{k}.bt{k}_{j}", conv(f"{n}.branch{k}.conv{k}_{j}", y, padding=d, dilation=d))
                y = act(y) if j < len(dils) else y
            outs.append(y)
        return act(bn(f"{n}.branch0.bt0", conv(f"{n}.branch0.conv0", t)) + torch.cat(outs, 1))

    def cbl(m, t):
        return act(bn(f"{m}.bt", conv(f"{m}.conv", t, padding=1)))

    skips = []
    for i in range(4):
        x = block(f"down{i + 1}.res", x)
        skips.append(x)
        x = F.max_pool2d(x, 2)
    x1, x2, x3, x4 = skips
    x = block("res", x)  # dropout: identity in eval mode
    f3 = cbl("cov3_", torch.cat([x3, cbl("cov3", torch.cat([conv("down0__", x1, 4), conv("down1_", x2, 2),
                                                             tconv("up3___", x4, 2, 1, 1)], 1))], 1))
    f2 = cbl("cov2_", torch.cat([x2, cbl("cov2", torch.cat([conv("down0_", x1, 2), tconv("up2__", x3, 2, 1, 1),
                                                             tconv("up3__", x4, 4, 0, 1)], 1))], 1))
    f1 = cbl("cov1_", torch.cat([x1, cbl("cov1", torch.cat([tconv("up3_", x4, 8, 0, 5), tconv("up2_", x3, 4, 0, 1),
                                                             tconv("up1_", x2, 2, 1, 1)], 1))], 1))
    for i, skip in enumerate((x4, f3, f2, f1)):
        x = block(f"up{i + 1}.res", torch.cat([tconv(f"up{i + 1}.up", x, 2, 1, 1), skip], 1))
    return conv("outc.conv", x)


def ours_from(ref_state: dict, b: int) -> torch.nn.Module:
    net = build_model("uhrnet", base_channels=b)
    net.load_state_dict(from_reference_state_dict(ref_state, base_channels=b))
    return net.eval()


def save_reference(path, state, wrap=True):
    torch.save({"state_dict": state} if wrap else state, path)
    return path


@pytest.fixture(scope="module")
def reference_file(tmp_path_factory):
    """A full-size (base 64) reference weights file ``{'state_dict': ...}``, random weights."""
    path = tmp_path_factory.mktemp("ref") / "UHRNet_weight.pth"
    return save_reference(path, random_reference_state(64, seed=3))


# ------------------------------------------------------------------------------------- the mapping
def test_layout_matches_the_reference_description():
    ours = build_model("uhrnet").state_dict()
    ref = to_reference_state_dict(ours)
    layout = reference_layout(64)
    assert [k for k, _ in layout] == list(ref)  # names and the reference's order
    assert [s for _, s in layout] == [tuple(v.shape) for v in ref.values()]
    assert len(ref) == len(ours) == len(key_table()) == 763
    assert sum(int(np.prod(s)) for k, s in layout if not k.endswith(("running_mean", "running_var", "num_batches_tracked"))) == 30_330_977


def test_round_trips_are_exact():
    torch.manual_seed(0)
    ours = build_model("uhrnet").state_dict()
    back = from_reference_state_dict(to_reference_state_dict(ours))
    assert list(back) == list(ours) and all(torch.equal(back[k], v) for k, v in ours.items())
    ref = random_reference_state(8, seed=1)
    again = to_reference_state_dict(from_reference_state_dict(ref, base_channels=8), base_channels=8)
    assert list(again) == list(ref) and all(torch.equal(again[k], v) for k, v in ref.items())


def test_imported_weights_compute_the_reference_function_and_need_the_permutation():
    ref = random_reference_state(8, seed=2)
    x = torch.rand(1, 1, 32, 32, generator=torch.Generator().manual_seed(0)) * 2 - 1
    with torch.no_grad():
        want = reference_forward(ref, x)
        got = ours_from(ref, 8)(x)
        # the same weights renamed only (level 1's mixing inputs left in the reference's order)
        plain = build_model("uhrnet", base_channels=8).eval()
        plain.load_state_dict({ours: ref[k] for k, ours in key_table()})
        unpermuted = plain(x)
    span = float(want.max() - want.min())
    assert float((got - want).abs().max()) <= 1e-5 * span
    assert float((unpermuted - want).abs().max()) > 1e-2 * span  # so the check above would catch a dropped permutation
    # the permuted entry is exactly level 1's mixing convolution, its input channels in three blocks reversed
    mine = from_reference_state_dict(ref, base_channels=8)["fusion.0.mix.0.weight"]
    blocks = ref["cov1.conv.weight"].chunk(3, dim=1)
    assert torch.equal(mine, torch.cat(blocks[::-1], 1))
    for level, name in ((1, "cov2"), (2, "cov3")):  # the other levels keep the order
        assert torch.equal(from_reference_state_dict(ref, base_channels=8)[f"fusion.{level}.mix.0.weight"],
                           ref[f"{name}.conv.weight"])


def test_library_errors_name_the_first_bad_key():
    ref = random_reference_state(8)
    bad = dict(ref)
    del bad["cov1.conv.bias"]
    with pytest.raises(CheckpointError, match=r"missing key 'cov1.conv.bias'$"):
        from_reference_state_dict(bad, base_channels=8)
    with pytest.raises(CheckpointError, match=r"unexpected key 'extra.weight'"):
        from_reference_state_dict({**ref, "extra.weight": torch.zeros(1)}, base_channels=8)
    bad = {**ref, "up2__.weight": torch.zeros(3, 3)}
    with pytest.raises(CheckpointError, match=r"'up2__.weight' has shape \(3, 3\), expected \(32, 8, 3, 3\)"):
        from_reference_state_dict(bad, base_channels=8)
    with pytest.raises(CheckpointError, match="uhrnet's own layout"):
        from_reference_state_dict(build_model("uhrnet", base_channels=8).state_dict(), base_channels=8)
    with pytest.raises(CheckpointError, match="missing key"):
        to_reference_state_dict(ref, base_channels=8)


def test_label_head_and_transform_become_figshare_labels():
    figshare = PRESETS["figshare"].to_dict()
    ckpt = {"output": {"scale": 60.0, "shift": -97.0}, "label_transform": figshare}
    assert reference_output_affine(ckpt) == (60.0, -97.0)  # uhrnet train's head, already figshare labels
    # labels of 10 units per mm with the plane at 0: Z = 6 * (label / 10) - 97
    other = {**figshare, "name": "mine", "units_per_mm": 10.0, "plane_offset": 0.0}
    a, b = reference_output_affine({"output": {"scale": 1.0, "shift": 0.0}, "label_transform": other})
    assert a == pytest.approx(0.6, rel=1e-12) and b == pytest.approx(-97.0, rel=1e-12)


def test_reads_bare_wrapped_and_dataparallel_files(tmp_path):
    ref = random_reference_state(8)
    for wrap, prefix in ((True, ""), (False, ""), (True, "module.")):
        path = save_reference(tmp_path / f"w{wrap}{prefix}.pth", {prefix + k: v for k, v in ref.items()}, wrap)
        state, info = read_reference_file(path)
        assert info["wrapped"] is wrap and info["module_prefix"] is bool(prefix)
        back = from_reference_state_dict(state, base_channels=8)
        assert all(torch.equal(back[ours], ref[k]) for k, ours in key_table() if ours != "fusion.0.mix.0.weight")


# ------------------------------------------------------------------------------------- the commands
@pytest.mark.slow
def test_import_weights_then_predict_gives_the_reference_heights(tmp_path, reference_file, capsys):
    run = tmp_path / "run"
    assert main(["import-weights", str(reference_file), "--out", str(run)]) == 0
    assert "763 entries, 30,330,977 parameters" in capsys.readouterr().out
    ckpt = load_checkpoint(run)
    assert ckpt["path"].endswith("best.pt") and (run / "last.pt").is_file() and (run / "config.json").is_file()
    # figshare labels read with the figshare preset's plane (-97): heights above the reference plane
    assert ckpt["label_transform"] == PRESETS["figshare"].to_dict()
    assert ckpt["output"] == {"scale": 1.0, "shift": 0.0}
    g = torch.Generator().manual_seed(0)
    fringe = (torch.rand(64, 64, generator=g) * 2 - 1).numpy().astype(np.float32)
    np.save(tmp_path / "img.npy", fringe)
    assert main(["predict", str(run), str(tmp_path / "img.npy"), "--out", str(tmp_path / "pred"), "--keep-all",
                 "--no-ply", "--device", "cpu", "--no-progress"]) == 0
    mm97 = np.load(tmp_path / "pred" / "img_height.npy")
    with torch.no_grad():
        z = reference_forward(torch.load(reference_file)["state_dict"], torch.from_numpy(fringe)[None, None])[0, 0]
    # heights above the figshare plane, as uhrnet's own runs report them: (Z + 97) / 6
    np.testing.assert_allclose(mm97, (z.numpy().astype(np.float64) + 97.0) / 6.0, rtol=0, atol=1e-4)
    # --plane-offset 0: the reference evaluation's millimetres, Z / 6
    assert main(["import-weights", str(reference_file), "--out", str(tmp_path / "run0"), "--plane-offset", "0"]) == 0
    assert main(["predict", str(tmp_path / "run0"), str(tmp_path / "img.npy"), "--out", str(tmp_path / "pred0"),
                 "--keep-all", "--no-ply", "--device", "cpu", "--no-progress"]) == 0
    mm = np.load(tmp_path / "pred0" / "img_height.npy")
    np.testing.assert_allclose(mm, z.numpy().astype(np.float64) / 6.0, rtol=0, atol=1e-4)
    # either way the exported file is the reference's own weights again
    for r in ("run", "run0"):
        out = tmp_path / f"{r}.pth"
        assert main(["export", str(tmp_path / r), "--format", "reference", "--out", str(out)]) == 0
        back = torch.load(out)["state_dict"]
        ref = torch.load(reference_file)["state_dict"]
        assert all(torch.equal(back[k], ref[k]) for k in ref)
    assert main(["import-weights", str(reference_file), "--out", str(tmp_path / "bad"), "--plane-offset", "-101"]) == 2


@pytest.mark.slow
def test_import_weights_keeps_existing_runs(tmp_path, reference_file, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "notes.txt").write_text("mine")  # a folder with other files is fine; they are left alone
    assert main(["import-weights", str(reference_file), "--out", str(run)]) == 0
    before = (run / "best.pt").stat().st_mtime_ns
    capsys.readouterr()
    assert main(["import-weights", str(reference_file), "--out", str(run)]) == 1
    err = capsys.readouterr().err
    assert "already holds imported weights" in err and "--overwrite" in err and len(err.strip().splitlines()) == 1
    assert "--resume" not in err  # import-weights has no --resume to suggest
    assert (run / "best.pt").stat().st_mtime_ns == before
    assert main(["import-weights", str(reference_file), "--out", str(run), "--overwrite"]) == 0  # its own: replaced
    assert (run / "best.pt").stat().st_mtime_ns != before
    # a history.csv nobody recorded is someone else's: refused, not deleted, --overwrite or not
    (run / "history.csv").write_text("epoch\n1\n")
    before = (run / "best.pt").stat().st_mtime_ns
    assert main(["import-weights", str(reference_file), "--out", str(run), "--overwrite"]) == 1
    err = capsys.readouterr().err
    assert "history.csv exists and was not written by uhrnet import-weights" in err, err
    assert (run / "history.csv").read_text() == "epoch\n1\n" and (run / "best.pt").stat().st_mtime_ns == before
    assert (run / "notes.txt").read_text() == "mine"


@pytest.mark.slow
def test_import_weights_bad_files_one_line(tmp_path, reference_file, capsys):
    ref = torch.load(reference_file)["state_dict"]
    cases = {
        "missing.pth": ({k: v for k, v in ref.items() if k != "cov2_.bt.running_var"}, "missing key 'cov2_.bt.running_var'"),
        "extra.pth": ({**ref, "head.weight": torch.zeros(1, 64, 1, 1)}, "unexpected key 'head.weight'"),
        "shape.pth": ({**ref, "outc.conv.weight": torch.zeros(2, 64, 1, 1)},
                      "'outc.conv.weight' has shape (2, 64, 1, 1), expected (1, 64, 1, 1)"),
    }
    for name, (state, message) in cases.items():
        path = save_reference(tmp_path / name, state)
        assert main(["import-weights", str(path), "--out", str(tmp_path / name.replace(".pth", ""))]) == 1
        err = capsys.readouterr().err
        assert message in err and str(path) in err and "Traceback" not in err, err
        assert len(err.strip().splitlines()) == 1
        assert not (tmp_path / name.replace(".pth", "") / "best.pt").exists()
    (tmp_path / "junk.pth").write_bytes(b"not a torch file")
    torch.save({"format": FORMAT, "state_dict": {}}, tmp_path / "ours.pt")
    torch.save({"epoch": 3, "model": "x"}, tmp_path / "nostate.pth")
    torch.save({"state_dict": ref, "args": argparse.Namespace(lr=1)}, tmp_path / "pickled.pth")
    for name, message in (("junk.pth", "cannot load: not a PyTorch weights file"),
                          ("pickled.pth", "holds a Python object (argparse.Namespace)"),
                          ("ours.pt", "already a uhrnet checkpoint"),
                          ("nostate.pth", "neither a state dict"), ("absent.pth", "not found")):
        assert main(["import-weights", str(tmp_path / name), "--out", str(tmp_path / "o")]) == 1
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    with pytest.raises(SystemExit) as exit_info:  # argparse's own refusal of a choice
        main(["import-weights", str(reference_file), "--out", str(tmp_path / "o"), "--format", "onnx"])
    assert exit_info.value.code == 2 and "invalid choice" in capsys.readouterr().err


@pytest.mark.slow
def test_export_reference_round_trip_and_label_head_folding(tmp_path, reference_file, capsys):
    run = tmp_path / "run"
    assert main(["import-weights", str(reference_file), "--out", str(run)]) == 0
    out = tmp_path / "exported.pth"
    assert main(["export", str(run), "--format", "reference", "--out", str(out), "--check",
                 "--height", "32", "--width", "32"]) == 0
    assert "check passed" in capsys.readouterr().out
    original, exported = torch.load(reference_file)["state_dict"], torch.load(out, weights_only=True)
    assert set(exported) == {"state_dict"} and list(exported["state_dict"]) == list(original)
    assert all(torch.equal(exported["state_dict"][k], v) for k, v in original.items())

    # a checkpoint as uhrnet train writes it: its label head (x 60, -97) goes into the reference's outc
    net = build_model("uhrnet").eval()
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_var.uniform_(0.5, 1.5)
                m.running_mean.uniform_(-0.5, 0.5)
    trained = tmp_path / "trained.pt"
    torch.save({"format": FORMAT, "version": VERSION, "model": {"name": "model_c", "config": {**net.config, "name": "model_c"}},
                "state_dict": net.state_dict(), "output": {"scale": 60.0, "shift": -97.0},
                "label_transform": PRESETS["figshare"].to_dict(), "epoch": 3}, trained)
    assert main(["export", str(trained), "--format", "reference", "--out", str(tmp_path / "t.pth")]) == 0
    x = torch.rand(1, 1, 32, 32, generator=torch.Generator().manual_seed(4)) * 2 - 1
    model, _ = model_from_checkpoint(load_checkpoint(trained))
    with torch.no_grad():
        want = model(x)
        got = reference_forward(torch.load(tmp_path / "t.pth")["state_dict"], x)
    assert float((got - want).abs().max()) <= 1e-4 * float(want.max() - want.min())


@pytest.mark.slow
def test_export_reference_refuses_other_models(tmp_path, capsys):
    def write(name, **config):
        net = build_model(name, **config)
        path = tmp_path / f"{name}{len(list(tmp_path.iterdir()))}.pt"
        torch.save({"format": FORMAT, "version": VERSION, "model": {"name": name, "config": dict(net.config)},
                    "state_dict": net.state_dict(), "output": {"scale": 1.0, "shift": 0.0},
                    "label_transform": PRESETS["figshare"].to_dict(), "epoch": 1}, path)
        return path

    cases = [(write("unet", base_channels=4), "holds only UHRNet; this checkpoint is unet"),
             (write("uhrnet", base_channels=8), "base_channels=64; this checkpoint has base_channels=8"),
             (write("uhrnet", base_channels=8, in_channels=2), "in_channels=1; this checkpoint has in_channels=2")]
    for name, config, message in (  # refused before any weight is read, so no weights needed
            ("model_b", {"fusion": False}, "fusion=True; this checkpoint has fusion=False"),
            ("uhrnet", {"head": "phase"}, "only the plain height head; this checkpoint has the phase head")):
        path = tmp_path / f"{name}-fake.pt"
        torch.save({"format": FORMAT, "version": VERSION,
                    "model": {"name": name, "config": {"name": name, "base_channels": 64, **config}},
                    "state_dict": {}, "label_transform": PRESETS["figshare"].to_dict()}, path)
        cases.append((path, message))
    for path, message in cases:
        out = tmp_path / "x.pth"
        assert main(["export", str(path), "--format", "reference", "--out", str(out)]) == 1
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
        assert not out.exists()


# ------------------------------------------------------------------------------------- nothing lost, nothing silent
def _sha(path):
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.slow
def test_export_never_replaces_a_file_it_did_not_write(tmp_path, reference_file, capsys):
    """The README's sequence: import the authors' file, export over it -> refused, the file and the imported
    run's record intact; an export replaces only its own earlier export; --out a folder is one clear line."""
    import shutil

    authors = tmp_path / "UHRNet_weight.pth"
    shutil.copyfile(reference_file, authors)
    sha = _sha(authors)
    run = tmp_path / "runs" / "uhrnet-ref"
    assert main(["import-weights", str(authors), "--out", str(run)]) == 0
    capsys.readouterr()
    for fmt in ("reference", "torchscript"):  # (onnx under a .pth name is a usage error before any file is read)
        assert main(["export", str(run), "--format", fmt, "--out", str(authors),
                     "--height", "32", "--width", "32"]) == 1, fmt
        err = capsys.readouterr().err
        assert f"{authors} exists and was not written by uhrnet export" in err and len(err.strip().splitlines()) == 1
        assert _sha(authors) == sha
    assert main(["export", str(run), "--format", "onnx", "--out", str(authors)]) == 2  # ONNX under a .pth name
    assert "a .pth name for --format onnx" in capsys.readouterr().err and _sha(authors) == sha
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")
    assert main(["export", str(run), "--format", "reference", "--out", str(notes)]) == 1
    assert notes.read_text() == "mine"
    capsys.readouterr()
    out = tmp_path / "exported.pth"
    assert main(["export", str(run), "--format", "reference", "--out", str(out)]) == 0
    first = out.stat().st_mtime_ns
    assert main(["export", str(run), "--format", "reference", "--out", str(out)]) == 0  # its own: replaced
    assert out.stat().st_mtime_ns != first
    capsys.readouterr()
    assert main(["export", str(run), "--format", "reference", "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert f"--out {tmp_path}: is a folder" in err and ".tmp" not in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow
def test_import_weights_respects_other_tools_files(tmp_path, reference_file, capsys):
    """A foreign config.json, and a folder train wrote, are refused in one line; nothing there changes."""
    from tests._helpers import write_figshare

    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "config.json").write_text('{"mine": true}')
    assert main(["import-weights", str(reference_file), "--out", str(foreign)]) == 1
    err = capsys.readouterr().err
    assert "config.json exists and was not written by uhrnet import-weights" in err and len(err.strip().splitlines()) == 1
    assert (foreign / "config.json").read_text() == '{"mine": true}' and not (foreign / "best.pt").exists()

    write_figshare(tmp_path / "real", n=6, h=32, w=64, seed=1)
    trained = tmp_path / "trained"
    assert main(["train", "--real", str(tmp_path / "real"), "--out", str(trained), "--model", "unet",
                 "--base-channels", "4", "--epochs", "1", "--batch-size", "2", "--device", "cpu", "--no-progress"]) == 0
    files = {p.name: _sha(p) for p in trained.iterdir() if p.is_file()}
    capsys.readouterr()
    for flags in ([], ["--overwrite"]):
        assert main(["import-weights", str(reference_file), "--out", str(trained), *flags]) == 1
        err = capsys.readouterr().err
        assert "was written by uhrnet train, not uhrnet import-weights" in err and len(err.strip().splitlines()) == 1
    assert {p.name: _sha(p) for p in trained.iterdir() if p.is_file()} == files


@pytest.mark.slow
def test_imported_run_fine_tunes_and_refuses_resume(tmp_path, reference_file, capsys):
    """The documented fine-tune works on an imported run by default; `train --resume` into it is one line,
    no traceback, and leaves its files and ownership record as they were."""
    from tests._helpers import write_figshare

    run = tmp_path / "uhrnet-ref"
    assert main(["import-weights", str(reference_file), "--out", str(run)]) == 0
    write_figshare(tmp_path / "labelled", n=6, h=32, w=64, seed=2)
    files = {p.name: _sha(p) for p in run.iterdir() if p.is_file()}
    capsys.readouterr()
    assert main(["train", "--out", str(run), "--resume", "--real", str(tmp_path / "labelled"), "--device", "cpu",
                 "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert {p.name: _sha(p) for p in run.iterdir() if p.is_file()} == files
    assert main(["train", "--init-from", str(run), "--raw-output", "--real", str(tmp_path / "labelled"),
                 "--out", str(tmp_path / "ft"), "--epochs", "1", "--batch-size", "2", "--device", "cpu",
                 "--no-progress"]) == 0, capsys.readouterr().err
    assert (tmp_path / "ft" / "last.pt").is_file()


def test_import_weights_bounds_and_whole_messages(tmp_path, capsys):
    """--plane-offset out of range is a usage error (exit 2); a truncated file and a text file give a whole
    sentence naming the file."""
    ref = random_reference_state(8)
    good = save_reference(tmp_path / "good.pth", ref)
    for value in ("1e300", "inf", "nan", "-100", "5000"):
        assert main(["import-weights", str(good), "--out", str(tmp_path / "o"), "--plane-offset", value]) == 2
        err = capsys.readouterr().err
        assert "--plane-offset must be a label above the invalid threshold -100 and at most 1000" in err, err
    data = good.read_bytes()
    (tmp_path / "cut.pth").write_bytes(data[: len(data) // 2])
    (tmp_path / "text.pth").write_text("e" * 200 + "\n")
    for name in ("cut.pth", "text.pth"):
        assert main(["import-weights", str(tmp_path / name), "--out", str(tmp_path / "o")]) == 1
        err = capsys.readouterr().err.strip()
        assert err.endswith(")") and str(tmp_path / name) in err and "cannot load" in err, err
        assert "KeyError: 101" not in err and len(err.splitlines()) == 1
    assert not (tmp_path / "o").exists()

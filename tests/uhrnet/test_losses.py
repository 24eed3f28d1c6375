"""uhrnet.training.losses: chunked L2 (hand-computed values, rank weights, dynamic reordering), SSIM, compound."""

from __future__ import annotations

import pytest
import torch

from uhrnet.training.losses import ChunkedL2Loss, CompoundLoss, L2Loss, SSIMLoss, build_loss, patch_sums
from uhrnet.scoring.metrics import ssim

# Patch L2 values 1..16 placed in a shuffled order over the 4 x 4 grid (row-major patch index).
LAYOUT = torch.tensor([7, 2, 16, 11, 1, 14, 5, 9, 12, 3, 15, 8, 4, 13, 10, 6], dtype=torch.float32)


def patchwise(values: torch.Tensor, size: int = 2) -> torch.Tensor:
    """A (1, 1, 4 size, 4 size) image that is constant ``values[p]`` on patch ``p`` of a 4 x 4 grid."""
    return values.view(4, 4).repeat_interleave(size, 0).repeat_interleave(size, 1)[None, None]


def toy(values: torch.Tensor = LAYOUT, requires_grad: bool = True):
    """pred = 0, target = sqrt(values) per patch, so patch p has L2 (mean squared error) = values[p]."""
    target = patchwise(values.sqrt())
    pred = torch.zeros_like(target, requires_grad=requires_grad)
    return pred, target


def test_default_weights():
    loss = ChunkedL2Loss()
    assert torch.allclose(loss.weights, torch.tensor([0.2 * i - 0.1 for i in range(1, 17)]))


def test_hand_computed_value_and_weights_follow_ranks():
    loss = ChunkedL2Loss()
    pred, target = toy()
    value = loss(pred, target)
    # L2 of the patch with rank i is i, weight 0.2 i - 0.1: sum_i i (0.2 i - 0.1) / 16 = (0.2*1496 - 0.1*136)/16
    assert value.item() == pytest.approx(17.85, rel=1e-6)
    assert torch.allclose(loss.patch_weights(), (0.2 * LAYOUT - 0.1).view(4, 4))
    assert torch.equal(loss.ranks, LAYOUT.long())


def test_patch_losses_are_mean_squared_error_over_valid_pixels():
    loss = ChunkedL2Loss()
    pred, target = toy(requires_grad=False)
    pred[..., 0, 0] = 10.0  # one bad pixel in patch 0 (L2 7 elsewhere) ...
    mask = torch.ones_like(pred, dtype=torch.bool)
    mask[..., 0, 0] = False  # ... that the mask removes
    l2, count = loss.patch_losses(pred, target, mask)
    assert torch.allclose(l2, LAYOUT)
    assert count[0] == 3 and torch.all(count[1:] == 4)
    unmasked, _ = loss.patch_losses(pred, target)
    assert unmasked[0].item() == pytest.approx((3 * 7 + (10 - 7**0.5) ** 2) / 4)


def test_patches_of_uneven_sizes_cover_the_image():
    x = torch.ones(2, 3, 10, 9)
    sums = patch_sums(x, (4, 4))
    assert sums.sum() == x.numel() and sums.min() >= 2 * 3 * 2 * 2


def test_first_epoch_keeps_ranks_of_first_batch_and_end_epoch_reorders():
    loss = ChunkedL2Loss()
    loss(*toy(LAYOUT))
    reversed_layout = 17 - LAYOUT
    pred, target = toy(reversed_layout)
    for _ in range(3):  # the order changes during the epoch ...
        value = loss(pred, target)
    assert torch.equal(loss.ranks, LAYOUT.long())  # ... but the weights keep the first batch's ranks
    # epoch losses: (LAYOUT + 3 * (17 - LAYOUT)) / 4 = (51 - 2 LAYOUT) / 4, i.e. reversed order
    loss.end_epoch()
    assert torch.equal(loss.ranks, reversed_layout.long())
    assert torch.all(loss.epoch_count == 0) and torch.all(loss.epoch_sse == 0)
    assert loss(pred, target).item() == pytest.approx(17.85, rel=1e-6)
    assert value.item() < 17.85  # the mis-ranked weights gave a smaller value


def test_ranks_follow_the_whole_epoch_not_the_last_batch():
    loss = ChunkedL2Loss()
    loss(*toy(LAYOUT))
    loss(*toy(LAYOUT))
    loss(*toy((17 - LAYOUT) * 0.1))  # different order but small: the epoch order stays LAYOUT's
    loss.end_epoch()
    assert torch.equal(loss.ranks, LAYOUT.long())


def test_no_grad_calls_do_not_touch_the_state():
    loss = ChunkedL2Loss()
    with torch.no_grad():
        value = loss(*toy(requires_grad=False))
    assert value.item() == pytest.approx(17.85, rel=1e-6)  # ranks its own batch ...
    assert not loss.has_ranks and torch.all(loss.epoch_count == 0)  # ... without fixing them
    loss(*toy(requires_grad=False), update=True)
    assert loss.has_ranks


def test_state_dict_round_trip_resumes_exactly():
    loss = ChunkedL2Loss()
    loss(*toy(LAYOUT))
    loss(*toy(17 - LAYOUT))
    resumed = ChunkedL2Loss()
    resumed.load_state_dict(loss.state_dict())
    for other in (loss, resumed):
        other.end_epoch()
    assert torch.equal(resumed.ranks, loss.ranks)
    pred, target = toy(LAYOUT)
    assert resumed(pred, target).item() == loss(pred, target).item()


def test_gradient_flows_and_skips_invalid_pixels():
    pred = torch.randn(2, 1, 16, 16, requires_grad=True)
    target = torch.randn(2, 1, 16, 16)
    mask = torch.rand(2, 1, 16, 16) > 0.3
    for loss in (ChunkedL2Loss(), L2Loss(), SSIMLoss(data_range=8.0), CompoundLoss(data_range=8.0)):
        pred.grad = None
        loss(pred, target, mask).backward()
        assert torch.isfinite(pred.grad).all()
        assert pred.grad[mask].abs().sum() > 0
        assert torch.all(pred.grad[~mask] == 0)


def test_custom_weights_and_grid():
    loss = ChunkedL2Loss(grid=(1, 2), weights=[1.0, 0.0])  # only the easier half counts
    target = torch.cat([torch.ones(1, 1, 4, 4), 2 * torch.ones(1, 1, 4, 4)], dim=-1)
    assert loss(torch.zeros_like(target, requires_grad=True), target).item() == pytest.approx(0.5)
    with pytest.raises(ValueError, match="need 2 weights"):
        ChunkedL2Loss(grid=(1, 2), weights=[1.0])


def test_l2_loss_is_masked_mse():
    pred, target = torch.zeros(1, 1, 2, 2), torch.tensor([[[[1.0, 2.0], [3.0, 100.0]]]])
    mask = torch.tensor([[[[1, 1], [1, 0]]]])
    assert L2Loss()(pred, target, mask).item() == pytest.approx(14 / 3)
    assert L2Loss()(pred, target).item() == pytest.approx(10014 / 4)


def test_ssim_loss_is_one_minus_ssim_and_ignores_invalid_pixels():
    torch.manual_seed(0)
    target = torch.rand(2, 1, 24, 24)
    pred = target + 0.05 * torch.randn_like(target)
    loss = SSIMLoss(data_range=1.0)
    assert loss(target, target).item() == pytest.approx(0.0, abs=1e-6)
    assert loss(pred, target).item() == pytest.approx(1 - ssim(pred, target, 1.0).item(), abs=1e-7)
    mask = torch.ones_like(target, dtype=torch.bool)
    mask[..., :5, :] = False
    changed = pred.clone()
    changed[..., :5, :] = 50.0
    assert loss(changed, target, mask).item() == pytest.approx(loss(pred, target, mask).item(), abs=1e-7)
    with pytest.raises(ValueError, match="data_range"):
        SSIMLoss(data_range=None)


def test_compound_loss_combines_and_forwards_epoch_state():
    torch.manual_seed(0)
    pred = torch.rand(1, 1, 16, 16, requires_grad=True)
    target = torch.rand(1, 1, 16, 16)
    loss = CompoundLoss(data_range=1.0)
    value = loss(pred, target)
    expected = ChunkedL2Loss()(pred, target) + 1000 * SSIMLoss(1.0)(pred, target)
    assert value.item() == pytest.approx(expected.item(), rel=1e-6)
    assert loss.chunked.has_ranks and loss.chunked.epoch_count.sum() > 0
    loss.end_epoch()
    assert loss.chunked.epoch_count.sum() == 0
    assert {"chunked.ranks", "chunked.epoch_sse", "chunked.epoch_count"} <= set(loss.state_dict())


def test_build_loss():
    assert isinstance(build_loss("l2"), L2Loss)
    assert isinstance(build_loss("chunked", grid=(2, 2)), ChunkedL2Loss)
    assert isinstance(build_loss("ssim", data_range=2.0), SSIMLoss)
    compound = build_loss("Compound", data_range=2.0, alpha=10.0)
    assert isinstance(compound, CompoundLoss) and compound.alpha == 10.0
    for loss in (build_loss("l2"), build_loss("ssim", data_range=1.0)):
        loss.end_epoch()  # a no-op everywhere but the chunked loss
    with pytest.raises(ValueError, match="data_range"):
        build_loss("compound")
    with pytest.raises(ValueError, match="known losses"):
        build_loss("l1")


def test_stateful_losses_declare_their_distributed_reduction():
    """reduce_state hands exactly the per-epoch accumulators to the all-reduce (composites recurse)."""
    for name, n in (("chunked", 2), ("compound", 2), ("l2", 0), ("ssim", 0)):
        loss = build_loss(name, data_range=286.0)
        seen = []
        loss.reduce_state(seen.append)
        assert len(seen) == n, name
        chunked = loss if name == "chunked" else getattr(loss, "chunked", None)
        if n:
            assert seen[0] is chunked.epoch_sse and seen[1] is chunked.epoch_count


def test_a_registered_loss_gets_what_its_entry_asks_for(tmp_path, monkeypatch):
    """Adding a loss is one registration: an entry asking for an extra batch field (the true phase) and the rig
    is built with the run's rig and called with ``(pred, target, mask, phase)``; nothing else is edited."""
    from _helpers import tiny_rig, write_native_rig
    from uhrnet.training import losses
    from uhrnet.training.train_config import TrainConfig
    from uhrnet.training.trainer import train

    seen = {"rigs": [], "phases": []}

    class PhaseAware(losses.Loss):
        def __init__(self, rig):
            super().__init__()
            seen["rigs"].append(rig)

        def forward(self, pred, target, mask, phase):
            seen["phases"].append(phase)
            return losses.L2Loss()(pred, target, mask)

    monkeypatch.setitem(losses.LOSSES, "toy", losses.LossEntry(lambda c: PhaseAware(c.rig), "test loss",
                                                                batch=(losses.PHASE_FIELD,), needs_rig=True))
    rig = tiny_rig()
    write_native_rig(tmp_path / "syn", rig, n=4, seed=3)
    torch.set_num_threads(1)
    train(TrainConfig(synthetic=[str(tmp_path / "syn")], synthetic_split="train", model="unet", base_channels=4,
                      loss="toy", epochs=1, batch_size=2, augment="off", out=str(tmp_path / "run"), progress=False))
    assert [r["camera"]["width"] for r in seen["rigs"]] == [rig.camera.width]  # the synthetic data's rig
    assert len(seen["phases"]) == 2 and all(p is not None and p.shape == (2, 1, 32, 64) for p in seen["phases"])
    assert all(torch.isfinite(p).all() for p in seen["phases"])  # synthetic samples carry their exact phase


def test_a_head_loss_wraps_only_a_plain_loss():
    from uhrnet.training.losses import HEAD_LOSSES, LOSSES

    assert all(entry.plain for entry in LOSSES.values())  # every run loss can sit under a head's loss
    assert HEAD_LOSSES["phase_head"].parts and HEAD_LOSSES["phase_head"].phase_targets

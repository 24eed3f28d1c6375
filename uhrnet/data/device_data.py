"""Samples that live on the training device (``uhrnet train --device-data``): a set decoded once (resized as the
run asks) into device tensors, and a loader that cuts the epoch's batches out of them there, with the
random crops and the photometric augmentation of :class:`uhrnet.data.datasets.Prepared` drawn from the same
seeds (:mod:`uhrnet.data.device_augment`). No per-step decoding, no DataLoader, no host copy in the loop.

Fringes are held as float16 (8-bit intensities: float16's spacing in [-1, 1] is below an 8-bit level),
labels as float32 and masks as booleans: 352 x 640 costs 1.35 MB a sample, 400 samples 0.54 GB.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import DataLoader

from uhrnet.data.datasets import Prepared, crop_sample
from uhrnet.data.device_augment import augment_fringes, draw

__all__ = ["BYTES_PER_PIXEL", "DeviceSet", "DeviceLoader", "device_bytes"]

BYTES_PER_PIXEL = 2 + 4 + 1  # float16 fringe, float32 label, bool mask


def device_bytes(prepared: Prepared, shape) -> int:
    """What :class:`DeviceSet` of ``prepared`` holds on the device, samples of ``shape`` (H, W) before any crop."""
    return len(prepared) * int(shape[0]) * int(shape[1]) * BYTES_PER_PIXEL


class DeviceSet:
    """The samples of ``prepared`` on ``device``, as :class:`Prepared` gives them for a plain index but before
    the crop when ``crop_later`` (the loader crops each batch: random crops for training); decoded once
    through a DataLoader of ``workers`` processes."""

    def __init__(self, prepared: Prepared, device: torch.device, workers: int = 0, crop_later: bool = True):
        self.prepared, self.crop_later = prepared, crop_later and prepared.crop is not None
        base = Prepared(prepared.dataset, None, prepared.resize, random_crop=False) if self.crop_later else \
            Prepared(prepared.dataset, prepared.crop, prepared.resize, random_crop=False)
        parts = {"fringe": [], "height": [], "mask": []}
        self.synthetic = np.zeros(len(base), bool)
        loader = DataLoader(base, batch_size=16, num_workers=workers, shuffle=False)
        k = 0
        for batch in loader:
            parts["fringe"].append(batch["fringe"].to(device, torch.float16))
            parts["height"].append(batch["height"].to(device, torch.float32))
            parts["mask"].append(batch["mask"].to(device) > 0.5)
            n = len(batch["source"])
            self.synthetic[k:k + n] = [s == "synthetic" for s in batch["source"]]
            k += n
        self.tensors = {f: torch.cat(v) if v else torch.empty(0, device=device) for f, v in parts.items()}
        self.device = device

    def __len__(self) -> int:
        return len(self.synthetic)

    def batch(self, index: np.ndarray, seeds, augment, generator) -> dict:
        """The samples ``index`` (their augmentation ``seeds``, None: none) as a training batch on the device."""
        idx = torch.from_numpy(np.asarray(index, np.int64))
        if self.device.type == "cuda":
            idx = idx.pin_memory().to(self.device, non_blocking=True)
        t = self.tensors
        out = {"fringe": t["fringe"].index_select(0, idx).float(), "height": t["height"].index_select(0, idx),
               "mask": t["mask"].index_select(0, idx)}
        if augment is not None and seeds is not None:
            shape = out["fringe"].shape[-2:]
            draws = [draw(s, shape, augment) if self.synthetic[i] else "keep" for i, s in zip(index, seeds)]
            out["fringe"] = augment_fringes(out["fringe"], out["mask"], draws, generator)
        out["mask"] = out["mask"].float()
        if self.crop_later:
            out = self._crop(out, seeds)
        out["source"] = ["synthetic" if self.synthetic[i] else "real" for i in index]
        return out

    def _crop(self, batch: dict, seeds) -> dict:
        """The crop of :class:`Prepared`: from each sample's seed (training), else the centre."""
        H, W = batch["fringe"].shape[-2:]
        h, w = self.prepared.crop
        rows = []
        for b in range(len(batch["fringe"])):
            if self.prepared.random_crop and seeds is not None:
                g = np.random.default_rng(int(seeds[b]))
                top, left = int(g.integers(0, H - h + 1)), int(g.integers(0, W - w + 1))
            else:
                top, left = (H - h) // 2, (W - w) // 2
            rows.append(crop_sample({k: batch[k][b] for k in ("fringe", "height", "mask")}, (h, w), top, left))
        return {k: torch.stack([r[k] for r in rows]) for k in ("fringe", "height", "mask")}


class DeviceLoader:
    """The epoch's batches of a :class:`DeviceSet`: the order of ``sampler`` (``(index, seed)`` pairs of
    :class:`uhrnet.data.datasets.MixedSampler`, or plain indices for validation), ``batch_size`` a batch, the
    last one short; ``augment`` (an :class:`~uhrnet.data.augment.AugmentConfig` or None) on synthetic samples.
    ``generator``: the device's noise stream, set by the trainer per epoch."""

    def __init__(self, data: DeviceSet, sampler, batch_size: int, augment=None):
        self.data, self.sampler, self.batch_size, self.augment = data, sampler, int(batch_size), augment
        self.noise = None

    @property
    def generator(self):
        return self.noise

    @generator.setter
    def generator(self, g) -> None:
        """The trainer's per-epoch generator (a DataLoader's, on the host): the device's noise stream from its seed."""
        self.noise = None if g is None else torch.Generator(self.data.device).manual_seed(g.initial_seed())

    def __len__(self) -> int:
        return -(-len(self.sampler) // self.batch_size)

    def __iter__(self):
        keys = list(self.sampler)
        paired = bool(keys) and isinstance(keys[0], tuple)
        index = np.array([k[0] if paired else k for k in keys], np.int64)
        seeds = np.array([k[1] for k in keys], np.int64) if paired else None
        noise = self.noise
        for s in range(0, len(index), self.batch_size):
            yield self.data.batch(index[s:s + self.batch_size], None if seeds is None else seeds[s:s + self.batch_size],
                                  self.augment, noise)

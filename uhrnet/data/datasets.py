"""Datasets for uhrnet: the real figshare arrays, fppsim's native format, and mixtures of both.

Every dataset returns the same sample dict (``torch`` tensors)::

    fringe       (1, H, W) float32 in [-1, 1]   (8-bit intensity / 127.5 - 1, as in f1_80.npy)
    height       (1, H, W) float32, label units  (as in Z.npy; millimetres = label * mm_per_unit)
    mask         (1, H, W) float32, 1 = valid pixel (label > invalid threshold)
    mm_per_unit  float
    id, source   str (sample id and "real"/"synthetic")

Label units are those of the public figshare dataset: Z = 6 * height_mm + plane offset, invalid
(shadow) pixels exactly -105, and the reference evaluation counts Z <= -100 as invalid.
:class:`fppsim.dataio.formats.LabelTransform` holds that preset and makes it configurable; fppsim's native
heights (mm above the reference plane) are mapped through the same transform so real and synthetic
samples mix. Files are read through :mod:`fppsim.dataio.formats` (the dataset contract) by the numpy
readers of :mod:`fppsim.dataio.readers`; splits come from :mod:`uhrnet.data.splits`; this module only adapts them
to torch (datasets, mixtures, the sampler, crops/resizing/augmentation, train/val/test sources).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import Dataset, Sampler

from fppsim.dataio.formats import PRESETS, LabelTransform, figshare_pair_paths
from fppsim.dataio.readers import (LABEL_SOURCES, check_export_labels, check_figshare_arrays, open_figshare_pair,
                                   open_source, read_fringe_image)
from uhrnet.errors import DataError, InputError
from uhrnet.data.splits import MIN_REFERENCE_SPLIT, SPLIT_MODES, reference_split, split_indices
from uhrnet.data.augment import augment_sample

__all__ = [
    "FigshareArrays", "FppsimDataset", "open_dataset", "DatasetSubset", "MixedDataset", "MixedSampler", "Prepared",
    "parse_size", "resize_sample", "crop_sample", "Sources", "load_sources",
    # re-exported: reading (numpy) and splits, which the torch datasets above are built on
    "LABEL_SOURCES", "read_fringe_image", "SPLIT_MODES", "MIN_REFERENCE_SPLIT", "reference_split", "split_indices",
    "DataError", "LabelTransform", "PRESETS",
]


# --------------------------------------------------------------------------------------------------
# Datasets


def _sample(fringe: np.ndarray, label: np.ndarray, transform: LabelTransform, sid: str, source: str) -> dict:
    fringe = np.array(fringe, dtype=np.float32, order="C", copy=True)  # off the memory map
    label = np.array(label, dtype=np.float32, order="C", copy=True)
    mask = transform.valid(label).astype(np.float32)
    return {
        "fringe": torch.from_numpy(fringe)[None],
        "height": torch.from_numpy(label)[None],
        "mask": torch.from_numpy(mask)[None],
        "mm_per_unit": float(transform.mm_per_unit),
        "id": sid,
        "source": source,
    }


class FigshareArrays(Dataset):
    """The figshare layout: ``f1_80.npy`` (fringes) and ``Z.npy`` (labels), memory-mapped.

    ``FigshareArrays("data/")`` opens ``data/f1_80.npy`` and ``data/Z.npy`` (or the single-sample pair
    ``fringe_pattern.npy``/``height_map.npy``); ``FigshareArrays(fringe=path, label=path)`` opens any pair.
    Arrays may be (N, H, W, 1), (N, H, W) or (H, W) of any float dtype; samples are converted to
    float32 one at a time, so the full set (about 2.7 GB) is never copied into memory.
    ``check=True`` scans the arrays once for NaN/inf and for fringes outside [-1, 1].
    """

    def __init__(self, root: str | os.PathLike | None = None, fringe: str | os.PathLike | None = None,
                 label: str | os.PathLike | None = None, transform: LabelTransform | str | dict | None = None,
                 check: bool = True, source: str = "real"):
        self.transform = LabelTransform.resolve(transform)
        self.source = source
        if root is not None:
            root = Path(root)
            if not root.exists():
                raise DataError(f"{root}: folder not found")
            if not root.is_dir():
                raise DataError(f"{root}: not a folder")
            pair = figshare_pair_paths(root)
            fringe = root / fringe if fringe is not None else pair[0]
            label = root / label if label is not None else pair[1]
            if not Path(fringe).exists() and not Path(label).exists() and not any(root.iterdir()):
                raise DataError(f"{root}: empty folder (expected f1_80.npy and Z.npy)")
        elif fringe is None or label is None:
            raise TypeError("FigshareArrays needs root or both fringe= and label=")
        self.fringe_path, self.label_path = Path(fringe), Path(label)
        self.fringes, self.labels = open_figshare_pair(self.fringe_path, self.label_path)
        self.ids = [f"{i:06d}" for i in range(len(self))]
        if check:
            self.check()

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    def __getstate__(self):  # loader workers started by spawn re-open the memory maps, never copy them
        state = dict(self.__dict__)
        state.pop("fringes"), state.pop("labels")
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self.fringes, self.labels = open_figshare_pair(self.fringe_path, self.label_path)

    @property
    def image_shape(self) -> tuple[int, int]:
        return tuple(self.labels.shape[1:])

    def check(self, chunk_bytes: int = 256 << 20) -> None:
        """Scan for NaN/inf (labels and fringes) and fringe values outside [-1, 1]."""
        check_figshare_arrays(self.fringes, self.labels, self.fringe_path, self.label_path, chunk_bytes)

    def __getitem__(self, i: int) -> dict:
        i = int(i)
        return _sample(self.fringes[i], self.labels[i], self.transform, self.ids[i], self.source)


class FppsimDataset(Dataset):
    """Any labelled layout through its reader (:func:`fppsim.dataio.readers.open_source`): fppsim's native
    format (``manifest.jsonl``, ``<id>/fringe.png``, ``<id>/arrays.npz``), a figshare-format export (its
    ``f1_80.npy`` and ``Z.npy``, memory-mapped), or a layout registered since, as the same sample dict.

    Heights are mapped to labels with ``transform`` (figshare preset by default). ``label="psp"`` trains
    on the phase-shifting height (``height_psp``/``mask_psp``) instead of the exact one. ``mask_fringe``
    sets the fringe to -1 on invalid pixels, as the figshare data and ``fppsim generate --format figshare``
    do. ``phase=True`` adds ``phase`` (1, H, W) float32, the exact projector phase (rad, ``phase_true``)
    for the physics head, read from fppsim's native samples behind the folder (a figshare export's
    ``native/`` folder, :meth:`~fppsim.dataio.readers.Source.fppsim_samples`).
    """

    def __init__(self, folder: str | os.PathLike, transform: LabelTransform | str | dict | None = None,
                 label: str = "true", mask_fringe: bool = True, check: bool = True, source: str = "synthetic",
                 phase: bool = False):
        self.root = Path(folder)
        self.phase = bool(phase)
        self.transform = LabelTransform.resolve(transform)
        self.source = source
        self.label = label
        self.mask_fringe = mask_fringe
        self.arrays: FigshareArrays | None = None
        if label not in LABEL_SOURCES:
            raise InputError(f"label must be 'true' or 'psp', got {label!r}")
        if not self.root.exists():
            raise DataError(f"{self.root}: folder not found")
        if not self.root.is_dir():
            raise DataError(f"{self.root}: not a folder")
        self.reader = open_source(self.root)
        if self.phase:
            samples = self.reader.fppsim_samples()
            if samples is None:
                raise DataError(f"{self.root}: --head phase needs fppsim's native samples (phase_true); "
                                + ("this figshare export has no native/ folder beside it" if self.reader.array_files
                                   else f"this folder holds {self.reader.kind} data"))
            self.reader, self.root = samples, samples.path
        if self.reader.array_files is not None:
            self.reader.check_samples(self.transform)
            self.arrays = FigshareArrays(self.root, transform=self.transform, check=check, source=source)
            self.ids = self.arrays.ids
            return
        if not self.reader.labelled:
            raise DataError(
                f"{self.root}: no samples (expected manifest.jsonl with <id>/arrays.npz, or f1_80.npy and Z.npy)"
            )
        self.reader.check_samples(self.transform, label)
        self.ids = self.reader.ids()

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, i: int) -> dict:
        if self.arrays is not None:
            return self.arrays[i]
        i = int(i)
        fringe, label = self.reader.sample(i, self.transform, self.label, self.mask_fringe)
        sample = _sample(fringe, label, self.transform, self.ids[i], self.source)
        if self.phase:
            sample["phase"] = torch.from_numpy(self.reader.exact_phase(i, fringe.shape))[None]
        return sample


def open_dataset(folder: str | os.PathLike, transform=None, source: str = "synthetic", **kw) -> Dataset:
    """Whatever labelled layout ``folder`` holds (:func:`fppsim.dataio.readers.open_source` tells): stacks
    stored as arrays memory-mapped (:class:`FigshareArrays`), any other through its reader."""
    if open_source(folder).array_files is not None and not kw.get("phase"):
        check_export_labels(Path(folder), LabelTransform.resolve(transform))  # an export's recorded label units
        return FigshareArrays(folder, transform=transform, source=source, check=kw.get("check", True))
    return FppsimDataset(folder, transform=transform, source=source, **kw)


# --------------------------------------------------------------------------------------------------
# Subsets, mixtures, sampling, crops


class DatasetSubset(Dataset):
    """A subset by index that keeps ``transform``, ``ids`` and ``source`` of its parent."""

    def __init__(self, dataset: Dataset, indices: Sequence[int]):
        self.dataset = dataset
        self.indices = np.asarray(indices, dtype=np.int64)
        self.transform = dataset.transform
        self.source = dataset.source
        self.ids = [dataset.ids[i] for i in self.indices]

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int) -> dict:
        return self.dataset[int(self.indices[int(i)])]


class MixedDataset(Dataset):
    """Real and synthetic datasets side by side: indices [0, n_real) are real, the rest synthetic."""

    def __init__(self, real: Iterable[Dataset] = (), synthetic: Iterable[Dataset] = ()):
        self.real = [d for d in real if len(d)]
        self.synthetic = [d for d in synthetic if len(d)]
        self.parts = self.real + self.synthetic
        self.offsets = np.cumsum([0] + [len(d) for d in self.parts])
        self.n_real = int(sum(len(d) for d in self.real))
        self.n_synthetic = int(sum(len(d) for d in self.synthetic))
        transforms = {d.transform for d in self.parts}
        if len(transforms) > 1:
            raise DataError(f"datasets use different label transforms: {sorted(t.name for t in transforms)}")
        self.transform = next(iter(transforms)) if transforms else PRESETS["figshare"]
        self.ids = [sid for d in self.parts for sid in d.ids]
        self.source = "mixed"

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def __getitem__(self, i: int) -> dict:
        i = int(i)
        if not 0 <= i < len(self):
            raise IndexError(i)
        k = int(np.searchsorted(self.offsets, i, side="right")) - 1
        return self.parts[k][i - int(self.offsets[k])]


class MixedSampler(Sampler):
    """Epoch order over a :class:`MixedDataset`, optionally with a fixed synthetic share.

    ``synthetic_ratio=None`` shuffles all samples (each seen once per epoch). With a ratio r, every draw
    is synthetic with probability r (so a batch is r synthetic in expectation) and takes the next sample
    of that group's own shuffled order (reshuffled when exhausted). ``num_samples`` draws per epoch
    (default: all samples). Under DDP each rank takes every ``world_size``-th draw of the same order
    (padded so all ranks step equally). Yields ``(index, augmentation_seed)``; the order depends only on
    ``(seed, epoch)``, so resumed runs and any number of loader workers see the same data.
    """

    def __init__(self, n_real: int, n_synthetic: int, synthetic_ratio: float | None = None,
                 num_samples: int | None = None, seed: int = 0, rank: int = 0, world_size: int = 1,
                 shuffle: bool = True, pad: bool = True):
        if synthetic_ratio is not None and not 0.0 <= synthetic_ratio <= 1.0:
            raise InputError(f"synthetic_ratio must be in [0, 1], got {synthetic_ratio}")
        self.n_real, self.n_synthetic = int(n_real), int(n_synthetic)
        self.total = self.n_real + self.n_synthetic
        if self.total == 0:
            raise DataError("no samples to draw from")
        self.ratio = synthetic_ratio if (self.n_real and self.n_synthetic) else None
        if synthetic_ratio == 0.0 and self.n_real:
            self.ratio = 0.0
        if synthetic_ratio == 1.0 and self.n_synthetic:
            self.ratio = 1.0
        self.num_samples = int(num_samples) if num_samples else self.total
        self.seed, self.rank, self.world_size = int(seed), int(rank), int(world_size)
        self.shuffle, self.pad = shuffle, pad
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def order(self) -> np.ndarray:
        """The full (all-rank) list of dataset indices for the current epoch."""
        g = np.random.default_rng([self.seed, self.epoch, 0x5EED])
        if not self.shuffle:
            base = np.arange(self.total)
            return np.resize(base, self.num_samples)
        if self.ratio is None:
            reps = -(-self.num_samples // self.total)
            return np.concatenate([g.permutation(self.total) for _ in range(reps)])[: self.num_samples]
        groups = [(0, self.n_real), (self.n_real, self.n_synthetic)]
        queues = [[], []]
        out = np.empty(self.num_samples, dtype=np.int64)
        pick = g.random(self.num_samples) < self.ratio
        for k in range(self.num_samples):
            gi = int(pick[k])
            if groups[gi][1] == 0:
                gi = 1 - gi
            if not queues[gi]:
                start, n = groups[gi]
                queues[gi] = list(start + g.permutation(n))[::-1]
            out[k] = queues[gi].pop()
        return out

    def _local(self) -> tuple[np.ndarray, np.ndarray]:
        order = self.order()
        aug = np.random.default_rng([self.seed, self.epoch, 0xA06]).integers(0, 2**31 - 1, len(order))
        if self.world_size > 1:
            per = -(-len(order) // self.world_size) if self.pad else None
            if per is not None and per * self.world_size > len(order):
                extra = per * self.world_size - len(order)
                order = np.concatenate([order, order[:extra]])
                aug = np.concatenate([aug, aug[:extra]])
            order, aug = order[self.rank::self.world_size], aug[self.rank::self.world_size]
        return order, aug

    def __iter__(self):
        order, aug = self._local()
        return iter([(int(i), int(s)) for i, s in zip(order, aug)])

    def __len__(self) -> int:
        if self.world_size == 1:
            return self.num_samples
        if self.pad:
            return -(-self.num_samples // self.world_size)
        return len(range(self.rank, self.num_samples, self.world_size))


def parse_size(text: str | None) -> tuple[int, int] | None:
    """'352x640' -> (352, 640) (height x width)."""
    if text is None or text == "":
        return None
    try:
        h, w = (int(v) for v in str(text).lower().replace("×", "x").split("x"))
    except ValueError:
        raise InputError(f"expected HxW (e.g. 176x320), got {text!r}") from None
    if h <= 0 or w <= 0:
        raise InputError(f"expected positive HxW, got {text!r}")
    return h, w


def resize_sample(sample: dict, size: tuple[int, int], invalid_value: float = -105.0) -> dict:
    """Resize a sample: fringe by area averaging, labels by mask-weighted area averaging."""
    h, w = size
    if tuple(sample["fringe"].shape[-2:]) == (h, w):
        return sample
    out = dict(sample)
    fr = sample["fringe"][None]
    out["fringe"] = F.interpolate(fr, size=(h, w), mode="area")[0]
    m = sample["mask"][None]
    num = F.interpolate(sample["height"][None] * m, size=(h, w), mode="area")[0]
    den = F.interpolate(m, size=(h, w), mode="area")[0]
    valid = den > 0.5
    height = torch.where(valid, num / den.clamp_min(1e-6), torch.zeros_like(num))
    out["height"] = torch.where(valid, height, torch.full_like(height, invalid_value))
    out["mask"] = valid.float()
    return out


def crop_sample(sample: dict, size: tuple[int, int], top: int, left: int) -> dict:
    h, w = size
    out = dict(sample)
    for k in ("fringe", "height", "mask"):
        out[k] = sample[k][..., top:top + h, left:left + w].contiguous()
    return out


class Prepared(Dataset):
    """Resize and/or crop samples (``--resize HxW`` then ``--crop HxW``) for training and evaluation.

    Keys may be ``(index, seed)`` pairs from :class:`MixedSampler`: the random crop position then
    follows from the seed, so it is reproducible whatever the number of loader workers. Plain integer
    keys (and ``random_crop=False``) take the centre crop.
    """

    def __init__(self, dataset: Dataset, crop: tuple[int, int] | None = None,
                 resize: tuple[int, int] | None = None, random_crop: bool = True, augment=None, phase: bool = False):
        self.dataset, self.crop, self.resize, self.random_crop = dataset, crop, resize, random_crop
        self.phase = phase  # every sample carries "phase" (NaN where unknown, e.g. real samples) so batches collate
        self.augment = augment  # uhrnet.data.augment.AugmentConfig: photometric jitter of synthetic samples
        self.transform = getattr(dataset, "transform", None)
        self.ids = getattr(dataset, "ids", None)

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, key) -> dict:
        index, seed = (key if isinstance(key, tuple) else (key, None))
        sample = self.dataset[index]
        if self.phase and "phase" not in sample:
            sample = {**sample, "phase": torch.full_like(sample["height"], float("nan"))}
        if self.resize is not None:
            sample = resize_sample(sample, self.resize, self.transform.invalid_value if self.transform else -105.0)
        if self.augment is not None and seed is not None and sample.get("source") == "synthetic":
            sample = augment_sample(sample, seed, self.augment)
        if self.crop is not None:
            H, W = sample["fringe"].shape[-2:]
            h, w = self.crop
            if h > H or w > W:
                raise DataError(f"crop {h}x{w} is larger than sample {sample['id']} ({H}x{W})")
            if self.random_crop and seed is not None:
                g = np.random.default_rng(seed)
                top, left = int(g.integers(0, H - h + 1)), int(g.integers(0, W - w + 1))
            else:
                top, left = (H - h) // 2, (W - w) // 2
            sample = crop_sample(sample, (h, w), top, left)
        return sample


# --------------------------------------------------------------------------------------------------
# Sources -> splits


@dataclass
class Sources:
    """Train/val/test datasets assembled from ``--real`` and ``--synthetic`` folders."""

    train: MixedDataset
    val: MixedDataset
    test: MixedDataset
    transform: LabelTransform
    description: dict


def load_sources(real: Sequence[str] = (), synthetic: Sequence[str] = (), transform=None,
                 real_split: str = "reference", synthetic_split: str = "reference",
                 synthetic_label: str = "true", check: bool = True, phase: bool = False) -> Sources:
    """Open every folder and split each one on its own (so a real test sample never reaches training).
    ``phase``: synthetic samples carry their exact phase (:class:`FppsimDataset`, for ``--head phase``)."""
    transform = LabelTransform.resolve(transform)
    parts = {"train": ([], []), "val": ([], []), "test": ([], [])}
    desc = {"real": [], "synthetic": [], "transform": transform.to_dict()}
    for group, folders, mode in ((0, real, real_split), (1, synthetic, synthetic_split)):
        for folder in folders:
            source = "real" if group == 0 else "synthetic"
            if group == 1 and phase:
                ds = FppsimDataset(folder, transform=transform, source=source, check=check, label=synthetic_label,
                                   phase=True)
            else:
                kw = {"check": check}
                if group == 1:
                    if open_source(folder).array_files is not None and synthetic_label == "psp":
                        open_source(folder).check_samples(transform, synthetic_label)  # says why not
                    kw["label"] = synthetic_label
                ds = open_dataset(folder, transform=transform, source=source, **kw)
            try:
                idx = {p: split_indices(len(ds), p, mode) for p in ("train", "val", "test")}
            except DataError as exc:
                raise DataError(f"{folder}: {exc}") from None
            for p in parts:
                parts[p][group].append(DatasetSubset(ds, idx[p]))
            desc[source].append({"path": str(Path(folder).resolve()), "n": len(ds), "split": mode,
                                 **{f"n_{p}": int(len(idx[p])) for p in parts}})
    splits = {p: MixedDataset(real=parts[p][0], synthetic=parts[p][1]) for p in parts}
    return Sources(splits["train"], splits["val"], splits["test"], transform, desc)

"""Train/val/test splits of a dataset's sample indices (numpy only).

The reference 80/10/10 split of the figshare data is reproduced index for index from the reference
code's two ``sklearn.model_selection.train_test_split`` calls (without needing scikit-learn).
"""

from __future__ import annotations

import math

import numpy as np

from uhrnet.errors import DataError, InputError

__all__ = ["MIN_REFERENCE_SPLIT", "SPLIT_MODES", "reference_split", "split_indices"]


def _shuffle_split(n: int, test_size: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """sklearn ``train_test_split(range(n), test_size=..., random_state=seed)`` index for index."""
    n_test = math.ceil(test_size * n)  # same float expression as sklearn's _validate_shuffle_split
    n_train = n - n_test
    if n_train <= 0 or n_test <= 0:
        raise DataError(f"cannot split {n} samples with test_size={test_size}")
    perm = np.random.RandomState(seed).permutation(n)
    return perm[n_test:n_test + n_train], perm[:n_test]


MIN_REFERENCE_SPLIT = 6


def reference_split(n: int, test_size: float = 0.2, seeds: tuple[int, int] = (0, 1)) -> dict[str, np.ndarray]:
    """The reference 80/10/10 split of the figshare data, reproduced index for index.

    ``train, rest = train_test_split(idx, test_size=0.2, random_state=0)`` then
    ``val, test = train_test_split(rest, test_size=0.5, random_state=1)``.
    """
    if n < MIN_REFERENCE_SPLIT:
        raise DataError(
            f"the reference 80/10/10 split needs at least {MIN_REFERENCE_SPLIT} samples, got {n} "
            "(for tiny sets use --real-split/--synthetic-split train, val or test)"
        )
    train, rest = _shuffle_split(n, test_size, seeds[0])
    val_pos, test_pos = _shuffle_split(len(rest), 0.5, seeds[1])
    return {"train": train, "val": rest[val_pos], "test": rest[test_pos]}


SPLIT_MODES = ("reference", "train", "val", "test")


def split_indices(n: int, part: str, mode: str = "reference") -> np.ndarray:
    """Indices of split ``part`` (train/val/test/all) of ``n`` samples.

    mode ``reference``: the 80/10/10 reference split; ``train``/``val``/``test``: every sample belongs
    to that one split (e.g. a single real sample used only for testing).
    """
    if part == "all":
        return np.arange(n)
    if part not in ("train", "val", "test"):
        raise InputError(f"unknown split {part!r}")
    if mode == "reference":
        return reference_split(n)[part]
    if mode in ("train", "val", "test"):
        return np.arange(n) if part == mode else np.zeros(0, dtype=np.int64)
    raise InputError(f"unknown split mode {mode!r} (known: {', '.join(SPLIT_MODES)})")

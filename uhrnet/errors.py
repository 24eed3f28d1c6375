"""Exceptions of the uhrnet library; the command line prints each as one line and exits 1.

``DataError`` is the dataset contract's :class:`fppsim.errors.DatasetError` under uhrnet's name, so a
problem found while reading files is one exception type in both packages.
"""

from __future__ import annotations

from fppsim.errors import DatasetError as DataError

__all__ = ["UhrnetError", "DataError", "CheckpointError", "ConfigError", "TrainingDiverged"]


class UhrnetError(Exception):
    """Base class of the errors uhrnet raises on purpose (besides :class:`DataError`)."""


class CheckpointError(UhrnetError, ValueError):
    """A checkpoint that cannot be used; the message names the file."""


class ConfigError(UhrnetError, ValueError):
    """Options that are invalid or do not fit together (the message names the option)."""


class TrainingDiverged(UhrnetError, RuntimeError):
    """The training loss became NaN/inf; the message says where and what to try."""

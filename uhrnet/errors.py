"""Exceptions of the uhrnet library; the command line prints each as one line and exits 1
(:class:`UsageError`, an option value that is wrong on its own: exit 2, like argparse's own errors).

``DataError`` is the dataset contract's :class:`fppsim.errors.DatasetError` under uhrnet's name, so a
problem found while reading files is one exception type in both packages. No library module imports
the CLI.
"""

from __future__ import annotations

from fppsim.errors import DatasetError as DataError, FolderBusy, InputError

__all__ = ["UhrnetError", "InputError", "DataError", "CheckpointError", "ConfigError", "UsageError", "TrainingDiverged",
           "ExportError", "Sim2RealError", "FolderBusy"]


class UhrnetError(Exception):
    """Base class of the errors uhrnet raises on purpose (besides :class:`DataError`)."""


class CheckpointError(UhrnetError, ValueError):
    """A checkpoint that cannot be used; the message names the file."""


class ConfigError(UhrnetError, ValueError):
    """Options that are invalid or do not fit together (the message names the option)."""


class UsageError(ConfigError):
    """An option value that is invalid on its own (e.g. ``--lr nan``): exit 2 on the command line."""


class TrainingDiverged(UhrnetError, RuntimeError):
    """The training loss became NaN/inf; the message says where and what to try."""


class ExportError(UhrnetError, ValueError):
    """A model that cannot be exported, or an export that does not match its checkpoint."""


class Sim2RealError(UhrnetError, ValueError):
    """A sim-to-real experiment that cannot run as configured (one line naming the culprit)."""

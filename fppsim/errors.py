"""Exceptions of the fppsim library, one module so callers (and the CLI) can catch them by kind.

Every message is one line that names the culprit (a file, a flag value, a sample). The command line
maps :class:`UsageError` (an option value that is wrong on its own) to exit status 2, like argparse's
own errors, and every other :class:`FppsimError` to exit status 1. No library module imports the CLI.
:func:`check_seed` lives here, below every stage, because both packages' configs check ``--seed`` with it.
"""

from __future__ import annotations

import numbers

__all__ = ["FppsimError", "InputError", "DatasetError", "RigError", "MeshError", "PlyError", "GenerateError", "SampleError",
           "ValidateError", "ValidateUsageError", "ConfigError", "UsageError", "PSPMatError", "BackendError", "FolderBusy",
           "ForeignFiles", "check_seed"]


class FppsimError(Exception):
    """Base class of every error fppsim raises on purpose."""


class InputError(FppsimError, ValueError):
    """An argument a library function cannot use (a shape, a range, a value out of its domain): bad input, not a
    bug; the message names it. Both packages raise it where they used to raise a bare ValueError."""


class DatasetError(FppsimError, ValueError):
    """A dataset folder or file that cannot be read or written as asked (the message names it)."""


class ConfigError(FppsimError, ValueError):
    """Settings that do not fit together (e.g. a PSP ladder that does not end at the rig's frequency)."""


class UsageError(ConfigError):
    """An option value that is invalid on its own (e.g. a non-finite label offset): exit 2 on the command line."""


class RigError(FppsimError, ValueError):
    """A rig calibration that cannot be loaded or is inconsistent."""


class MeshError(FppsimError, ValueError):
    """A mesh file that cannot be used."""


class PlyError(FppsimError, ValueError):
    """A PLY file fppsim's own reader cannot parse (:mod:`fppsim.rendering.meshio`)."""


class GenerateError(FppsimError, RuntimeError):
    """A generation run that cannot produce anything (one-line reason)."""


class SampleError(FppsimError, RuntimeError):
    """A sample that cannot be produced (e.g. nothing lands in view after all attempts)."""


class ValidateError(FppsimError, ValueError):
    """Input that cannot be validated (one-line reason)."""


class ValidateUsageError(UsageError, ValidateError):
    """A ``validate-psp`` option value wrong on its own, or flags that contradict each other (exit 2); still a
    :class:`ValidateError` for callers that catch those."""


class PSPMatError(FppsimError, ValueError):
    """A .mat phase-shifting file (or folder of them) that does not hold what the reader expects."""


class NoPhaseError(PSPMatError):
    """A phase-shifting frame read right whose every pixel is invalid (PSin = PCos = 0, or NaN): a frame with
    nothing to score, which a tool scoring several frames skips, not a broken file."""


class BackendError(FppsimError, RuntimeError):
    """The requested off-screen GL backend cannot be used (one line saying what to install or set)."""


class FolderBusy(FppsimError, RuntimeError):
    """Another process holds the output folder's lock (one line naming the folder)."""


class ForeignFiles(DatasetError):
    """An output path a tool would write already holds a file it did not write (:mod:`fppsim.owned`)."""


def check_seed(seed, what: str = "--seed", error: type[Exception] = InputError, most: int | None = None) -> int:
    """``seed`` as an int when it is a whole number >= 0 (at most ``most`` where given), else ``error``, one line (a
    command's config passes its usage error). numpy's ``SeedSequence`` takes any integer >= 0 and refuses a negative
    one deep inside a run; torch's generators take at most 2**64 - 1 (``most``). bool and float are refused."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or int(seed) < 0 \
            or (most is not None and int(seed) > most):
        bound = ">= 0" if most is None else f"from 0 to {most}"
        raise error(f"{what} must be an integer {bound}, got {seed!r}")
    return int(seed)

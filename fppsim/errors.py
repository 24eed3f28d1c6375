"""Exceptions of the fppsim library, one module so callers (and the CLI) can catch them by kind.

Every message is one line that names the culprit (a file, a flag value, a sample). The command line
maps them to exit status 1; usage errors (bad flags) exit 2 before any of these are raised.
"""

from __future__ import annotations

__all__ = ["FppsimError", "DatasetError", "RigError", "MeshError", "GenerateError", "SampleError",
           "ValidateError", "ConfigError", "PSPMatError"]


class FppsimError(Exception):
    """Base class of every error fppsim raises on purpose."""


class DatasetError(FppsimError, ValueError):
    """A dataset folder or file that cannot be read or written as asked (the message names it)."""


class ConfigError(FppsimError, ValueError):
    """Settings that do not fit together (e.g. a PSP ladder that does not end at the rig's frequency)."""


class RigError(FppsimError, ValueError):
    """A rig calibration that cannot be loaded or is inconsistent."""


class MeshError(FppsimError, ValueError):
    """A mesh file that cannot be used."""


class GenerateError(FppsimError, RuntimeError):
    """A generation run that cannot produce anything (one-line reason)."""


class SampleError(FppsimError, RuntimeError):
    """A sample that cannot be produced (e.g. nothing lands in view after all attempts)."""


class ValidateError(FppsimError, ValueError):
    """Input that cannot be validated (one-line reason)."""


class PSPMatError(FppsimError, ValueError):
    """A .mat phase-shifting file that does not hold what the reader expects."""

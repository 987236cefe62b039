"""Exceptions raised by forestreg.

Every error the engine raises on purpose derives from :class:`ForestregError`, so a caller (CLI,
GUI, script) can catch one class and show its message, which always says what was wrong and what
to do about it.
"""

from __future__ import annotations


class ForestregError(Exception):
    """Root of every error forestreg raises on purpose."""


class ScanReadError(ForestregError):
    """A scan file cannot be read: missing, unreadable, corrupt, empty or of an unknown format."""


class ScanDataError(ForestregError):
    """A scan's contents are unusable: NaN or infinite coordinates, absurd units, too few points."""


class ScanWriteError(ForestregError):
    """An output file cannot be written."""


class ParameterError(ForestregError):
    """A parameter is out of range or a parameter file cannot be read."""


class Cancelled(ForestregError):
    """The user cancelled a long-running operation."""


class TargetError(ForestregError):
    """Targets (tie points) are missing, unreadable or inconsistent."""


class ProjectFileError(ForestregError):
    """A project file cannot be read: missing, damaged, or of an unsupported version."""


class OutputPathError(ForestregError):
    """An output path would overwrite an input or a user's file, or cannot be written."""


class UsageError(ForestregError):
    """An argument is missing, out of range or contradicts another (bad input: CLI exit 2)."""


class DataError(ForestregError, ValueError):
    """The data do not allow the result (honest failure: CLI exit 1). Also a ``ValueError`` for
    callers written before it existed."""


class InvalidArgumentError(ForestregError, ValueError):
    """A function was called with an unusable argument (bad input: CLI exit 2). Also a
    ``ValueError`` for callers written before it existed."""


class UnknownNameError(ForestregError, KeyError):
    """A name (scan, tree, target) that does not exist. Also a ``KeyError`` for callers written
    before it existed; its text is the plain message."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else "unknown name"


class TransformError(ForestregError):
    """A 4x4 matrix is unreadable, not finite, or not a proper rigid transform (scale, reflection)."""

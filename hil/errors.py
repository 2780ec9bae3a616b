"""The core's typed errors.

Every error a user can cause (a bad file, a malformed config, degenerate geometry) is one of
these, carries what and where, and is turned by the CLI into one clear line on stderr and a
non-zero exit — never a traceback. Driver errors live in :mod:`drivers.interfaces.errors`.
"""

from __future__ import annotations


class HilError(Exception):
    """Base of every error the project raises on purpose."""


class InputFileError(HilError, ValueError):
    """A file given by the user cannot be read or does not hold what it should.

    Attributes:
        path: the file, as the user named it.
        reason: what is wrong, in plain words.
    """

    def __init__(self, path: str, reason: str) -> None:
        self.path = path
        self.reason = reason
        super().__init__(f"{path}: {reason}")


class ConfigError(HilError, ValueError):
    """A setup config is invalid. ``problems`` holds one line per problem (file, key path, reason)."""

    def __init__(self, path: str, problems: list[str]) -> None:
        self.path = path
        self.problems = problems
        super().__init__("\n".join(f"{path}: {p}" for p in problems))


class GeometryError(HilError, ValueError):
    """Geometry input that has no meaningful answer (too few points, NaN, degenerate layout)."""


class DegenerateConfigurationError(GeometryError):
    """The points are collinear, coincident or otherwise do not fix a rigid transform."""


class AmbiguousMatchError(GeometryError):
    """Correspondence-free matching found two or more equally good assignments.

    Raised instead of silently picking one when the marker layout is near-symmetric.
    """


class CalibrationError(HilError, ValueError):
    """A calibration cannot be computed or a calibration file is invalid."""


class VisionError(HilError, ValueError):
    """An image cannot be processed (empty, wrong size, wrong type)."""

"""The orthowarp error tree.

Every error orthowarp raises on purpose derives from :class:`OrthowarpError`. Each subclass
also derives from the built-in exception a Python user would expect, so ``except ValueError``
and ``except OSError`` keep working.
"""

__all__ = [
    "OrthowarpError",
    "ParamError",
    "CrsError",
    "RasterIOError",
    "GeometryError",
    "DeviceError",
    "Cancelled",
    "OrthowarpWarning",
]


class OrthowarpError(Exception):
    """Root of all errors raised by orthowarp."""


class ParamError(OrthowarpError, ValueError):
    """An argument or a parameter read from a file is invalid."""


class CrsError(OrthowarpError, ValueError):
    """A coordinate reference system is missing, unknown or unsuitable."""


class RasterIOError(OrthowarpError, OSError):
    """A raster could not be opened, read or written."""


class GeometryError(OrthowarpError, ValueError):
    """A sensor geometry is degenerate (e.g. distortion not invertible over the image)."""


class DeviceError(OrthowarpError, RuntimeError):
    """A Warp device is unknown or unusable."""


class Cancelled(OrthowarpError):
    """A run was stopped through its ``cancel`` event; it wrote nothing."""


class OrthowarpWarning(UserWarning):
    """Something the user should know about a result that is still written (values clipped,
    say)."""

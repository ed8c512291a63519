"""The vocabulary of orthowarp's options: one definition of each set of choices, for the library
(which validates its arguments against them) and the CLI (whose choices are built from them).

Each is a ``str`` enumeration, so its members compare equal to their plain strings: a caller
passes ``resampling="bicubic"`` or ``resampling=Resampling.BICUBIC`` alike.
"""

from __future__ import annotations

import enum

from .errors import ParamError

__all__ = ["Resampling", "Method", "Compress", "BlockCodec", "SourceReads", "Seams", "Blend", "AccuracyMeasure",
           "choice", "values"]


class _Choice(str, enum.Enum):
    def __str__(self) -> str:  # the plain value in messages and f-strings
        return self.value


class Resampling(_Choice):
    """How source pixels are interpolated at the output pixels' source positions."""

    NEAREST = "nearest"
    BILINEAR = "bilinear"
    BICUBIC = "bicubic"  # Keys (1981), a = -0.5
    LANCZOS = "lanczos"  # Lanczos-3


class Method(_Choice):
    """Orthorectification method: each output pixel projected into the source (backward), or
    each source pixel geolocated onto the output (forward, the direct method)."""

    BACKWARD = "backward"
    FORWARD = "forward"


class Compress(_Choice):
    """Output compression."""

    DEFLATE = "deflate"
    ZSTD = "zstd"
    LZW = "lzw"
    JPEG = "jpeg"
    WEBP = "webp"
    NONE = "none"


class BlockCodec(_Choice):
    """Who compresses a COG's blocks: chosen for the device (auto), the host's cores (host),
    nvCOMP on the GPU (nvcomp), nvCOMP and the host together (hybrid), orthowarp's own Warp
    kernels (warp: deflate or JPEG)."""

    AUTO = "auto"
    HOST = "host"
    NVCOMP = "nvcomp"
    HYBRID = "hybrid"
    WARP = "warp"


class SourceReads(_Choice):
    """How a source image reaches the device: whole (read once), tiles (a window per output
    tile), or auto (whole on a GPU where it fits)."""

    AUTO = "auto"
    WHOLE = "whole"
    TILES = "tiles"


class Seams(_Choice):
    """Mosaic seams: least-cost paths where the images agree, or the nadir-nearest image."""

    LEAST_COST = "least-cost"
    NADIR = "nadir"


class Blend(_Choice):
    """Blending across mosaic seams."""

    FEATHER = "feather"
    MULTIBAND = "multiband"
    NONE = "none"


class AccuracyMeasure(_Choice):
    """What an accuracy raster holds: standard deviations, or CE90 / LE90."""

    SIGMA = "sigma"
    CE90 = "ce90"


def values(kind: type[_Choice]) -> tuple[str, ...]:
    """The plain strings of an option's choices, in their order (for the CLI's choices)."""
    return tuple(m.value for m in kind)


def choice(name: str, value: object, kind: type[_Choice]) -> _Choice:
    """``value`` (a string or a member) as a member of ``kind``, or a :class:`ParamError` naming
    the argument ``name`` and the choices."""
    try:
        return kind(value)
    except ValueError:
        raise ParamError(f"{name} must be one of {', '.join(values(kind))}; got {value!r}") from None

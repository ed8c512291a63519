"""orthowarp.options: one vocabulary of choices for the library and the CLI."""

import click
import pytest

import orthowarp as ow
from orthowarp.cli import main
from orthowarp.options import (AccuracyMeasure, Blend, BlockCodec, Compress, Method, Resampling, Seams, SourceReads,
                               choice, values)

KINDS = [Resampling, Method, Compress, BlockCodec, SourceReads, Seams, Blend, AccuracyMeasure]


@pytest.mark.parametrize("kind", KINDS)
def test_members_are_their_strings(kind):
    for m in kind:
        assert m == m.value and str(m) == m.value and f"{m}" == m.value
        assert choice("x", m.value, kind) is m and choice("x", m, kind) is m
    assert values(kind) == tuple(m.value for m in kind)


def test_a_refused_choice_names_the_argument_and_the_choices():
    with pytest.raises(ow.ParamError, match=r"resampling must be one of nearest, bilinear, bicubic, lanczos; got 'cubic'"):
        choice("resampling", "cubic", Resampling)
    with pytest.raises(ValueError):  # ParamError is a ValueError too
        choice("blend", None, Blend)


def _choices(command, option):
    for p in main.commands[command].params:
        if option in getattr(p, "opts", ()):
            assert isinstance(p.type, click.Choice)
            return tuple(p.type.choices)
    raise AssertionError(f"{command} has no {option}")


@pytest.mark.parametrize("command, option, kind", [
    ("ortho", "--resampling", Resampling), ("mosaic", "--resampling", Resampling), ("ortho", "--method", Method),
    ("ortho", "--compress", Compress), ("ortho", "--block-codec", BlockCodec), ("mosaic", "--block-codec", BlockCodec),
    ("ortho", "--source-reads", SourceReads), ("mosaic", "--seams", Seams), ("mosaic", "--blend", Blend),
    ("ortho", "--accuracy-measure", AccuracyMeasure), ("mosaic", "--accuracy-measure", AccuracyMeasure),
])
def test_the_cli_offers_the_library_s_choices(command, option, kind):
    assert _choices(command, option) == values(kind)


def test_the_mosaic_offers_its_compressions():
    """orthowarp mosaic --compress: the library's mosaic compressions, a subset of Compress."""
    from orthowarp.pipeline.mosaic import MOSAIC_COMPRESS

    assert _choices("mosaic", "--compress") == MOSAIC_COMPRESS == ("deflate", "zstd", "jpeg", "webp")
    assert set(MOSAIC_COMPRESS) <= set(values(Compress))


@pytest.mark.parametrize("kwargs, match", [
    (dict(resampling="cubic"), "resampling must be one of"),
    (dict(method="direct"), "method must be one of backward, forward"),
    (dict(compress="lzma"), "compress must be one of"),
    (dict(block_codec="gpu"), "block_codec must be one of"),
    (dict(source_reads="all"), "source_reads must be one of"),
])
def test_orthorectify_refuses_an_unknown_choice_before_reading_anything(tmp_path, kwargs, match):
    cam = ow.FrameCamera(focal_length=100.0, pixel_size=0.01, image_size=(100, 80))
    pose = ow.Pose.from_ins(47.0, 8.0, 2500.0, roll=0.0, pitch=0.0, yaw=0.0)
    with pytest.raises(ow.ParamError, match=match):
        ow.orthorectify(str(tmp_path / "missing.tif"), ow.FrameSensor(cam, pose), str(tmp_path / "o.tif"), dem=400.0,
                        device="cpu", **kwargs)
    assert not list(tmp_path.iterdir())


"""One table of option values, parsed by both command lines: ``shadowcorr`` (the library's CLI)
and ``shadowcorr-client`` (which must stay installable alone, so it keeps its own parsers).
Both must accept the same values, read them the same way and refuse the rest with the same message."""

from __future__ import annotations

import argparse

import pytest

from shadowcorr.cli import build_parser as library_parser
from shadowcorr.convert.rosbag import BagCamera
from shadowcorr_client.cli import build_parser as client_parser

REFUSED = object()

CASES = [
    # --cameras: Unreal-layout cameras
    ("--cameras", "0,2,4,6", [0, 2, 4, 6]),
    ("--cameras", " 1 , 3 ", [1, 3]),
    ("--cameras", "0,,2,", [0, 2]),
    ("--cameras", "7", [7]),
    ("--cameras", "", REFUSED),
    ("--cameras", ",", REFUSED),
    ("--cameras", "-1", REFUSED),
    ("--cameras", "0,-2", REFUSED),
    ("--cameras", "a,b", REFUSED),
    ("--cameras", "1.5", REFUSED),
    # --every / --max-views: whole numbers >= 1
    ("--every", "3", 3),
    ("--every", "1", 1),
    ("--every", "0", REFUSED),
    ("--every", "-2", REFUSED),
    ("--every", "2.0", REFUSED),
    ("--every", "x", REFUSED),
    ("--max-views", "12", 12),
    ("--max-views", "0", REFUSED),
    # --sync-tolerance: finite seconds >= 0
    ("--sync-tolerance", "0.05", 0.05),
    ("--sync-tolerance", "0", 0.0),
    ("--sync-tolerance", "1e-3", 0.001),
    ("--sync-tolerance", "-0.1", REFUSED),
    ("--sync-tolerance", "nan", REFUSED),
    ("--sync-tolerance", "inf", REFUSED),
    ("--sync-tolerance", "soon", REFUSED),
    # --camera: NAME=DEPTH_TOPIC,MASK_TOPIC[,INFO_TOPIC]
    ("--camera", "left=/a/depth,/a/mask", ("left", "/a/depth", "/a/mask", "")),
    ("--camera", " left = /a/depth , /a/mask , /a/info ", ("left", "/a/depth", "/a/mask", "/a/info")),
    ("--camera", "left", REFUSED),
    ("--camera", "left=/a", REFUSED),
    ("--camera", "=/a,/b", REFUSED),
    ("--camera", "left=/a,,/c", REFUSED),
    ("--camera", "left=/a,/b,", REFUSED),
    ("--camera", "left=/a,/b,/c,/d", REFUSED),
    ("--camera", "my cam=/a,/b", REFUSED),
    ("--camera", "left=/a b,/c", REFUSED),
    ("--camera", "a,b=/a,/b", REFUSED),
    ("--camera", "left=/a=b,/c", REFUSED),
]

BAG_OPTIONS = {"--every", "--max-views", "--sync-tolerance", "--camera"}


def _library_argv(option: str, value: str) -> list[str]:
    if option in BAG_OPTIONS:
        return ["convert", "rosbag", "bag_dir", "--out", "out", f"{option}={value}"]
    return ["correspond", "bundle", f"{option}={value}"]


def _client_argv(option: str, value: str) -> list[str]:
    return ["correspond", "bundle", f"{option}={value}"]


def _parse(parser: argparse.ArgumentParser, argv: list[str], option: str, capsys) -> object:
    """The option's parsed value (a camera spec as its four parts), or the error message."""
    try:
        args = parser.parse_args(argv)
    except SystemExit as exit_:
        assert exit_.code == 2
        return capsys.readouterr().err.strip().splitlines()[-1].split("error: ", 1)[1]
    value = getattr(args, option.lstrip("-").replace("-", "_"))
    if option == "--camera":
        (camera,) = value
        camera = camera if isinstance(camera, BagCamera) else BagCamera.parse(camera)
        return camera.name, camera.depth_topic, camera.mask_topic, camera.info_topic
    return value


@pytest.mark.parametrize(("option", "value", "expected"), CASES, ids=[f"{o}={v!r}" for o, v, _ in CASES])
def test_both_command_lines_parse_the_option_alike(option, value, expected, capsys):
    library = _parse(library_parser(), _library_argv(option, value), option, capsys)
    client = _parse(client_parser(), _client_argv(option, value), option, capsys)
    if expected is REFUSED:
        assert isinstance(library, str) and library.startswith(f"argument {option}: "), library
        assert repr(value) in library
    else:
        assert library == expected
    assert client == library

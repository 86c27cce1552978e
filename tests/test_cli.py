"""Both command lines as a new user meets them: start-up imports, global options anywhere, plain help,
clear errors for mistyped input, and the server's own code while it warms up."""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import threading

import pytest

from shadowcorr_client.cli import build_parser as client_parser
from shadowcorr_client.cli import main as client_main
from .harness import ServerProcess
from shadowcorr.cli import EVAL_COLUMNS, build_parser, main
from shadowcorr.io import write_bundle

from .paths import REPO, SAMPLE_DIR
from .scenes import sphere_scene

PROBE = """
import json, sys
from shadowcorr.cli import main
try:
    code = main(sys.argv[1:])
except SystemExit as exc:
    code = exc.code
print(json.dumps({"code": code, "heavy": sorted(m for m in ("torch", "numpy", "pydantic_settings", "fastapi")
                                                 if m in sys.modules)}))
"""


def imports_of(*args: str) -> dict:
    out = subprocess.run([sys.executable, "-c", PROBE, *args], cwd=REPO, capture_output=True, text=True, timeout=120)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("args", [["--version"], ["--help"], ["correspond", "--help"], ["serve", "--help"]])
def test_version_and_help_do_not_import_torch(args) -> None:
    probe = imports_of(*args)
    assert probe["code"] == 0
    assert "torch" not in probe["heavy"]
    if args != ["serve", "--help"]:  # serve's flags come from the settings model
        assert probe["heavy"] == []


def test_converting_does_not_import_torch(tmp_path) -> None:
    probe = imports_of("convert", "ue", str(tmp_path / "nowhere"), "--set", "2001", "--out", str(tmp_path / "B"))
    assert probe["code"] == 2 and "torch" not in probe["heavy"]


def _all_parsers(parser: argparse.ArgumentParser):
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):
                yield from _all_parsers(sub)


@pytest.mark.parametrize("make", [build_parser, client_parser])
def test_help_texts_have_no_markup(make) -> None:
    for parser in _all_parsers(make()):
        text = parser.format_help()
        assert not re.search(r"``|::|:func:|:mod:|:class:", text), f"{parser.prog}:\n{text}"


def test_log_level_help_says_what_it_does() -> None:
    for parser in _all_parsers(build_parser()):
        text = " ".join(parser.format_help().split())
        assert "--log-level" in text and "least severe" in text, parser.prog


def test_global_options_before_and_after_the_command() -> None:
    parser = build_parser()
    args = parser.parse_args(["correspond", "B", "-v", "--log-level", "debug"])
    assert args.verbose and args.log_level == "debug"
    args = parser.parse_args(["-v", "--log-level", "INFO", "correspond", "B"])
    assert args.verbose and args.log_level == "info"  # not overwritten by the command's parser
    args = parser.parse_args(["--log-level", "error", "convert", "rosbag", "bag", "--out", "o", "-v"])
    assert args.log_level == "error" and args.verbose
    args = parser.parse_args(["serve", "--log-level", "debug"])  # serve's own flag: the server's log level
    assert args.log_level == "debug"

    client = client_parser()
    args = client.parse_args(["--server", "http://a:1", "--token", "t", "health"])
    assert (args.server, args.token) == ("http://a:1", "t")
    args = client.parse_args(["health", "--server", "http://b:2"])
    assert args.server == "http://b:2"
    args = client.parse_args(["--server", "http://a:1", "-v", "correspond", "X", "--retries", "0"])
    assert (args.server, args.verbose, args.retries) == ("http://a:1", True, 0)
    args = client.parse_args(["--server", "http://a:1", "upload-dataset", "D", "--out", "r", "--server", "http://c:3"])
    assert args.server == "http://c:3"  # the later one wins


def test_convert_ue_mistyped_folder_and_missing_set(tmp_path, capsys) -> None:
    assert main(["convert", "ue", str(tmp_path / "exampels"), "--set", "2001", "--out", str(tmp_path / "B")]) == 2
    err = capsys.readouterr().err
    assert "no such directory" in err and "missing file" not in err
    if (SAMPLE_DIR / "Set2001_Depth_0.exr").is_file():
        assert main(["convert", "ue", str(SAMPLE_DIR), "--set", "2002", "--out", str(tmp_path / "B")]) == 2
        err = capsys.readouterr().err
        assert "sets present: 2001" in err and "missing file" not in err


@pytest.fixture(scope="module")
def small_bundle(tmp_path_factory):
    scene = sphere_scene([[0.0, 0.0, 45.0], [160.0, 30.0, 45.0]], [44.0, 40.0], width=160, height_px=90)
    scene.ground_truth = "instance"  # mask ids are the spheres in every view
    return write_bundle(scene, tmp_path_factory.mktemp("cli") / "spheres")


def test_cameras_on_a_bundle_is_an_error(small_bundle, capsys) -> None:
    assert main(["correspond", str(small_bundle), "--cameras", "0,2"]) == 2
    err = capsys.readouterr().err
    assert "--cameras" in err and "is a bundle" in err


def test_threads_option_gives_the_same_labels_and_refuses_negative_counts(small_bundle, tmp_path, capsys) -> None:
    import json

    import torch

    before = torch.get_num_threads()
    try:
        for threads in ("1", "2"):
            assert main(["correspond", str(small_bundle), "--threads", threads, "--out", str(tmp_path / threads)]) == 0
            assert torch.get_num_threads() == int(threads)
    finally:
        torch.set_num_threads(before)
    one, two = (json.loads((tmp_path / t).read_text()) for t in ("1", "2"))
    assert [s["object"] for s in one["segments"]] == [s["object"] for s in two["segments"]]
    assert (one["config"]["num_threads"], two["config"]["num_threads"]) == (1, 2)
    with pytest.raises(SystemExit):
        main(["correspond", str(small_bundle), "--threads", "-1"])
    assert "expected a thread count" in capsys.readouterr().err


def test_eval_table_shows_each_metric_under_its_uncut_header(small_bundle, capsys) -> None:
    # A bandwidth that merges the two spheres: metrics that differ from column to column.
    options = ["--method", "meanshift", "--bandwidth", "2"]
    assert main(["eval", str(small_bundle), "--quiet", *options]) == 0
    header, row = capsys.readouterr().out.splitlines()[:2]
    assert main(["correspond", str(small_bundle), *options]) == 0
    metrics = json.loads(capsys.readouterr().out)["metrics"]
    assert metrics["rock_purity"] != metrics["cluster_purity"]
    # Each column is 18 characters wide after the 24 of the scene name, label and value alike.
    for i, (key, label) in enumerate(EVAL_COLUMNS.items()):
        column = slice(24 + 18 * i, 24 + 18 * (i + 1))
        assert header[column].strip() == label
        assert float(row[column]) == pytest.approx(metrics[key], abs=1e-4), key


@pytest.mark.slow
def test_client_shows_the_servers_code_while_it_warms_up(capsys) -> None:
    server = ServerProcess(env={"SHADOWCORR_WORKERS": "1", "SHADOWCORR_LOG_LEVEL": "warning"})
    starter = threading.Thread(target=server.start, daemon=True)
    starter.start()  # returns once /health is 200; meanwhile the client probes it
    seen: list[str] = []
    try:
        while starter.is_alive():
            code = client_main(["--server", server.url, "--retries", "0", "health"])
            seen.append(capsys.readouterr().err)
            if code == 0:
                break
        starter.join(timeout=300)
        assert client_main(["health", "--server", server.url]) == 0
    finally:
        server.stop()
    warming = [e for e in seen if e.startswith("not ready")]
    assert warming, f"never saw the server warming up: {seen[-3:]}"
    assert all("not_ready: the server is starting" in e and "http_503" not in e for e in warming), warming[:2]

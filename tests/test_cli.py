"""The CLI as a user meets it: help, version, not-yet-built stages, validate, and one-line errors."""

from __future__ import annotations

import json

import pytest

from igavatar import __version__
from igavatar_cli.main import app


def test_help_lists_every_stage(cli_runner):
    result = cli_runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    for command in ("synth", "preprocess", "train", "export", "animate", "eval", "demo", "validate"):
        assert command in result.output


@pytest.mark.parametrize("command, default", [("preprocess", "[default: RUN_DIR/capture]"),
                                              ("train", "[default: the preset's]"),
                                              ("preprocess", "[default: 15 for a body model's template")])
def test_help_shows_the_defaults_written_in_brackets(cli_runner, command, default):
    """Rich reads [..] as markup: an unescaped "[default: ...]" vanished from --help."""
    result = cli_runner.invoke(app, [command, "--help"], env={"COLUMNS": "250"})
    assert result.exit_code == 0 and default in " ".join(result.output.replace("│", " ").split()), result.output


def test_version(cli_runner):
    result = cli_runner.invoke(app, ["--version"])
    assert result.exit_code == 0 and __version__ in result.output


@pytest.mark.parametrize("command", ["train", "export", "animate", "eval"])
def test_stages_without_their_input_artifact_say_which_and_fail(cli_runner, command, tmp_path):
    result = cli_runner.invoke(app, [command, "--run-dir", str(tmp_path)])
    assert result.exit_code != 0
    assert "error:" in result.output and "Traceback" not in result.output
    assert not any(p.name in ("model", "mesh", "animation", "report") for p in tmp_path.iterdir())


def test_validate_accepts_a_capture_and_reports_json(cli_runner, tiny_skeleton_capture):
    result = cli_runner.invoke(app, ["validate", str(tiny_skeleton_capture), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["kind"].startswith("capture") and summary["files_checked"] == 3


def test_validate_on_a_non_artifact_is_one_clear_line(cli_runner, tmp_path):
    result = cli_runner.invoke(app, ["validate", str(tmp_path)])
    assert result.exit_code == 3
    assert "not an igavatar artifact" in result.output
    assert "Traceback" not in result.output


def test_preprocess_on_missing_directory(cli_runner, tmp_path):
    result = cli_runner.invoke(app, ["preprocess", "--capture", str(tmp_path / "missing"), "--out", str(tmp_path / "ds")])
    assert result.exit_code == 2
    assert "no such capture directory" in result.output
    assert not (tmp_path / "ds").exists()

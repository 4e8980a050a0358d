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


@pytest.mark.parametrize("args, message", [
    (["animate", "walk", "--motion", "squat"], "disagree"),
    (["preprocess", "--poses-from", "wham_output.pkl"], "needs --video"),
])
def test_contradicting_options_are_one_line_before_any_work(cli_runner, tmp_path, args, message):
    """Checks the command functions make themselves (not a stage's): one line, exit 2, nothing written."""
    result = cli_runner.invoke(app, [*args, "--run-dir", str(tmp_path / "run")])
    assert result.exit_code == 2, result.output
    assert message in result.output and "Traceback" not in result.output
    assert not (tmp_path / "run").exists()


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


def _commands():
    import typer.main

    group = typer.main.get_command(app)
    return {name: command for name, command in group.commands.items()}


def _rendered_help(cli_runner, name: str) -> str:
    result = cli_runner.invoke(app, [name, "--help"], env={"COLUMNS": "400", "TERMINAL_WIDTH": "400"})
    assert result.exit_code == 0, result.output
    return result.output


@pytest.mark.parametrize("name", sorted(_commands()))
def test_every_option_shows_its_default_and_sits_in_a_panel(cli_runner, name):
    """Typer shows `[default: X]` itself for a concrete default; an option whose default is None (the
    preset's, the run directory's, off) must say what that means in its help, as `\\[default: ...]`
    (rich reads a bare `[default ...]` as markup and drops it). Every option has a help panel."""
    command = _commands()[name]
    rendered = " ".join(_rendered_help(cli_runner, name).replace("│", " ").split())
    assert "\\" not in rendered, rendered
    for param in command.params:
        if param.param_type_name != "option" or param.name == "help":
            continue
        assert getattr(param, "rich_help_panel", None), f"{name} --{param.name}: no help panel"
        is_off_flag = param.is_flag and param.default is False and not param.secondary_opts
        if param.default is None and not is_off_flag:
            assert "[default:" in (param.help or ""), f"{name} {param.opts[0]}: default None not explained in its help"
            hint = param.help[param.help.index("[default:"):].split("]")[0] + "]"
            assert " ".join(hint.split()) in rendered, (name, param.opts[0], hint)
        elif not is_off_flag and param.show_default is not False:
            assert f"[default: " in rendered


def test_the_first_panel_holds_the_inputs(cli_runner):
    rendered = _rendered_help(cli_runner, "train")
    panels = [line.split("─")[1].strip() for line in rendered.splitlines() if line.startswith("╭─")]
    # Typer keeps --help alone in a first "Options" box; then come what most users set.
    assert panels[:3] == ["Options", "Inputs and outputs", "Quality and time"] and panels[-1] == "Console", panels
    assert panels.index("Advanced") == len(panels) - 2
    assert rendered.index("--dataset") < rendered.index("--smooth-weight")

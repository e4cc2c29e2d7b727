"""The `dofsynth` entry point: every subcommand registers, explains itself and fails clearly."""
import subprocess
import sys

import pytest

from dofsynth import __version__
from dofsynth.cli import build_parser, main

COMMANDS = ["assets", "demo", "depth", "docs", "eval", "generate", "manifest", "recipes", "render", "sheet", "stats", "train", "verify"]


def test_every_command_is_registered():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert sorted(sub.choices) == COMMANDS


@pytest.mark.parametrize("command", COMMANDS)
def test_command_help(command, capsys):
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    assert text.startswith(f"usage: dofsynth {command}") and len(text.split()) > 30


def test_no_command_prints_help_and_fails(capsys):
    assert main([]) == 2
    assert "COMMAND" in capsys.readouterr().out


def test_user_errors_are_one_line_with_status_2(tmp_path, capsys):
    assert main(["verify", str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("dofsynth verify: error:") and "missing" in err and "Traceback" not in err


def test_python_dash_m_and_version():
    out = subprocess.run([sys.executable, "-m", "dofsynth", "--version"], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == f"dofsynth {__version__}"


def test_every_command_takes_quiet_and_verbose_and_no_help_shows_a_none_default(capsys):
    from dofsynth.cli import _leaf_parsers

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    leaves = _leaf_parsers(sub)
    assert len(leaves) >= len(COMMANDS)
    for p in leaves:
        flags = {s for a in p._actions for s in a.option_strings}
        assert {"-q", "--quiet", "-v", "--verbose"} <= flags, p.prog
        assert "(default: None)" not in p.format_help(), p.prog


def test_redirected_progress_prints_lines_not_carriage_return_frames(capsys):
    from dofsynth import progress

    with progress.bar(50, "work") as b:   # pytest's stderr is not a terminal
        for _ in range(50):
            b.update(1)
    err = capsys.readouterr().err
    assert "\r" not in err
    lines = err.strip().splitlines()
    assert 9 <= len(lines) <= 11 and lines[-1].startswith("work: 50/50 samples (100%)")
    progress.set_verbosity(quiet=True)
    try:
        with progress.bar(50, "work") as b:
            b.update(50)
    finally:
        progress.set_verbosity()
    assert capsys.readouterr().err == ""


def test_quiet_silences_the_summary_lines(tmp_path, capsys):
    assert main(["recipes", "copy", "smoke", str(tmp_path), "-q"]) == 0
    assert capsys.readouterr().out == "" and (tmp_path / "smoke.toml").is_file()
    assert main(["recipes", "copy", "demo", str(tmp_path)]) == 0
    assert "copied demo.toml" in capsys.readouterr().out

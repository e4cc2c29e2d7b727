"""The `dofsynth` entry point: every subcommand registers, explains itself and fails clearly."""
import subprocess
import sys

import pytest

from dofsynth import __version__
from dofsynth.cli import build_parser, main

COMMANDS = ["assets", "demo", "eval", "generate", "manifest", "render", "sheet", "stats", "train", "verify"]


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

"""The `dofsynth` entry point: every subcommand registers, explains itself and fails clearly."""
import subprocess
import sys

import pytest

from dofsynth import __version__
from dofsynth.cli import build_parser, main

COMMANDS = ["assets", "demo", "depth", "docs", "eval", "generate", "manifest", "qa", "recipes", "render", "sheet", "stats", "train",
            "verify"]


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


def test_quiet_and_verbose_go_before_or_after_the_command_and_mean_the_same(smoke_set, capsys):
    assert main(["-q", "verify", str(smoke_set)]) == 0
    assert capsys.readouterr().out == ""                   # -q: problems only (none here)
    assert main(["verify", str(smoke_set), "-v"]) == 0
    cap = capsys.readouterr()
    shards = [ln for ln in cap.err.splitlines() if ln.strip().endswith("problems") and ".tar:" in ln]
    assert len(shards) == 4 and "OK" in cap.out         # -v: a line per shard
    assert main(["-v", "stats", str(smoke_set), "--out", str(smoke_set.parent / "s.png")]) == 0
    cap = capsys.readouterr()
    assert "train: 6 samples read" in cap.err and "train: 6 samples" in cap.out
    assert main(["stats", str(smoke_set), "-q", "--out", str(smoke_set.parent / "s.png")]) == 0
    assert capsys.readouterr().out == ""                 # stats -q prints nothing
    assert main(["-q", "verify", str(smoke_set), "-v"]) == 2
    assert "give one of them" in capsys.readouterr().err
    assert main(["docs", "list"]) == 0 and "FORMAT" in capsys.readouterr().out


def test_progress_has_a_total_and_draws_on_an_unsized_terminal(smoke_set):
    """verify's bar counts to the manifest's samples; on a pseudo-terminal whose size was never
    set (0 x 0, as a CI runner's) the bar still draws."""
    import os
    import pty
    import subprocess
    import sys

    master, slave = pty.openpty()   # a new pty: 0 x 0 until someone sets its size
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    proc = subprocess.Popen([sys.executable, "-m", "dofsynth", "verify", str(smoke_set)], stdin=slave, stdout=slave,
                            stderr=slave, env=env, close_fds=True)
    os.close(slave)
    out = b""
    while True:
        try:
            chunk = os.read(master, 4096)
        except OSError:
            break
        if not chunk:
            break
        out += chunk
    assert proc.wait(timeout=600) == 0, out
    text = out.decode(errors="replace")
    assert "verify:" in text and "/8 [" in text, text[-500:]   # a tqdm frame, with the total


def test_outputs_beside_a_read_only_set_are_refused_before_the_work(smoke_set, tmp_path, capsys):
    """On a read-only mount (what root cannot write either) stats and sheet say so at once,
    naming the path and how to write elsewhere."""
    import shutil
    import subprocess

    ro = tmp_path / "ro"
    shutil.copytree(smoke_set, ro)
    bound = subprocess.run(["mount", "--bind", str(ro), str(ro)], capture_output=True)
    if bound.returncode != 0:
        pytest.skip(f"cannot bind-mount here: {bound.stderr.decode().strip() or 'not permitted'}")
    try:
        subprocess.run(["mount", "-o", "remount,ro,bind", str(ro)], check=True, capture_output=True)
        for cmd in (["stats", str(ro)], ["sheet", str(ro)]):
            assert main(cmd) == 2
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and "read-only" in err[0] and str(ro) in err[0], err
        assert main(["stats", str(ro), "--out", str(tmp_path / "stats.png")]) == 0
        assert (tmp_path / "stats.png").is_file()
    finally:
        subprocess.run(["umount", "-l", str(ro)], capture_output=True)


def test_an_existing_destination_is_bad_input_everywhere(tmp_path, capsys):
    assert main(["recipes", "copy", "smoke", str(tmp_path)]) == 0
    assert main(["recipes", "copy", "smoke", str(tmp_path)]) == 2
    assert "exists" in capsys.readouterr().err


def test_a_stopped_run_prints_its_one_line_and_no_finalizer_tracebacks_after_it():
    """A signal that lands in a library's clean-up (a `with` block's close) can leave an object
    whose __del__ then fails at exit: the stopped run still ends in one line."""
    code = """if True:
        import signal, sys
        from dofsynth import cli
        class Half:
            def __del__(self):
                raise ValueError("I/O operation on closed file")
        def run(args):
            left = Half()
            left.cycle = left   # garbage only the collector finds, after main has printed its line
            del left
            signal.raise_signal(signal.SIGTERM)
        parser = cli.build_parser
        def build():
            p = parser()
            p._subparsers._group_actions[0].choices["stats"].set_defaults(func=run)
            return p
        cli.build_parser = build
        status = cli.main(["stats", "nowhere"])
        import gc
        gc.collect()
        raise SystemExit(status)
    """
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert res.returncode == 143 and len(lines) == 1 and "terminated" in lines[0], res.stderr

"""What a pip user gets: shipped recipes and docs by name, the extras, the files describing
themselves (FORMAT.md = the manifest's `format`), and a wheel that works without torch in a
folder with no checkout."""
from __future__ import annotations

import os
import re
import subprocess
import sys
import venv
from pathlib import Path

from dofsynth.cli import main
from dofsynth.manifest import load_manifest
from dofsynth.record import MEMBERS, members_markdown

ROOT = Path(__file__).resolve().parents[1]


def test_format_md_and_the_manifest_describe_the_same_members(smoke_set):
    text = (ROOT / "docs" / "FORMAT.md").read_text()
    assert members_markdown() in text  # the docs' table is the member table
    manifest = load_manifest(smoke_set)
    assert manifest["format"]["members"] == [m.to_dict() for m in MEMBERS.values() if m.option is None]
    assert manifest["format"]["conventions"]["disparity"].startswith("normalized disparity")
    assert {"python", "numpy", "opencv", "OpenEXR", "scipy"} <= set(manifest["libraries"])
    assert all(not Path(s["path"]).is_absolute() for b in manifest["splits"].values() for s in b["shards"])


def test_shipped_recipes_and_docs_by_name(tmp_path, capsys):
    assert main(["recipes", "list"]) == 0
    listing = capsys.readouterr().out
    assert re.search(r"^demo\s+data\s+Demo recipe", listing, re.M) and re.search(r"^train-demo\s+training", listing, re.M)
    assert main(["recipes", "copy", "demo", str(tmp_path / "mine")]) == 0
    copied = tmp_path / "mine" / "demo.toml"
    assert copied.read_bytes() == (ROOT / "recipes" / "demo.toml").read_bytes()
    assert main(["recipes", "copy", "demo", str(tmp_path / "mine")]) == 2       # never overwritten silently
    assert "exists" in capsys.readouterr().err
    assert main(["recipes", "show", "nope"]) == 2
    assert "shipped: deeplens-18k, demo" in capsys.readouterr().err
    assert main(["docs"]) == 0 and "FORMAT" in capsys.readouterr().out
    assert main(["docs", "FORMAT"]) == 0 and "## Sample members" in capsys.readouterr().out

    from dofsynth.recipe import load_recipe
    from dofsynth.train.config import load

    assert load_recipe("demo").name == "demo" and load_recipe("demo.toml").sha256 == load_recipe(copied).sha256
    assert load("train-demo").data.crop == 256


def test_a_command_that_needs_a_missing_extra_names_the_pip_install(tmp_path):
    code = ("import sys; sys.modules['torch'] = None; from dofsynth.cli import main; "
            f"raise SystemExit(main(['train', 'train-tiny', '--data', {str(tmp_path)!r}, '--run', {str(tmp_path / 'r')!r}]))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert "pip install 'dofsynth[train]'" in r.stderr and "Traceback" not in r.stderr


def test_generation_never_imports_torch():
    code = ("import sys, dofsynth.cli, dofsynth.generate, dofsynth.qa.sheets, dofsynth.qa.verify, dofsynth.qa.stats; "
            "dofsynth.cli.build_parser(); bad = [m for m in ('torch', 'webdataset') if m in sys.modules]; "
            "print(bad); raise SystemExit(bool(bad))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_a_wheel_in_a_fresh_environment_without_torch_runs_the_main_jobs(tmp_path):
    """pip wheel, a new virtual environment with the base install only (pip's cache supplies
    the dependencies), then the demo, generate, verify and sheet from a folder with no
    checkout."""
    wheels = tmp_path / "wheels"
    run = lambda *cmd, **kw: subprocess.run(cmd, capture_output=True, text=True, timeout=600, **kw)  # noqa: E731
    r = run(sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheels), str(ROOT))
    assert r.returncode == 0, r.stderr
    wheel = next(wheels.glob("dofsynth-*.whl"))
    env_dir = tmp_path / "env"
    venv.create(env_dir, with_pip=True)
    py = env_dir / "bin" / "python"
    r = run(str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check", str(wheel))
    assert r.returncode == 0, r.stderr
    r = run(str(py), "-c", "import importlib.util as u; print(u.find_spec('torch'), u.find_spec('webdataset'))")
    assert r.stdout.split() == ["None", "None"]
    work = tmp_path / "elsewhere"
    work.mkdir()
    exe = str(env_dir / "bin" / "dofsynth")
    env = {**os.environ, "PYTHONPATH": ""}
    for cmd in (["demo", "--out", "X"], ["generate", "demo", "--out", "G", "--limit", "4", "--quiet"],
                ["verify", "G"], ["sheet", "G", "--html", "H"]):
        r = run(exe, *cmd, cwd=work, env=env)
        assert r.returncode == 0, (cmd, r.stdout[-2000:], r.stderr[-2000:])
    assert (work / "X" / "demo" / "manifest.json").is_file() and (work / "H" / "index.html").is_file()
    r = run(exe, "train", "train-tiny", "--data", "G", "--run", "R", cwd=work, env=env)
    assert r.returncode == 2 and "pip install 'dofsynth[train]'" in r.stderr

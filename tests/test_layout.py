"""The package reads as the data flow: stage folders, each stage importing only earlier ones, no
import cycle, no dofsynth import hidden inside a function below the command line, and no module
of 400 lines or more (read from the source, as a newcomer would)."""
from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "dofsynth"
# Every top-level module or stage package, earliest first: a module may import its own stage
# and earlier ones only.
STAGES = ["dofsynth", "dofsynth.spawned", "dofsynth.config", "dofsynth.files", "dofsynth.progress", "dofsynth.stops", "dofsynth.shipped",
          "dofsynth.rng",
          "dofsynth.jit", "dofsynth.color", "dofsynth.image", "dofsynth.io", "dofsynth.optics", "dofsynth.codecs", "dofsynth.render",
          "dofsynth.record", "dofsynth.recipe", "dofsynth.assets", "dofsynth.scene", "dofsynth.compose",
          "dofsynth.sample", "dofsynth.shards", "dofsynth.manifest", "dofsynth.generate", "dofsynth.qa",
          "dofsynth.train", "dofsynth.commands", "dofsynth.cli", "dofsynth.__main__"]
FOLDERS = ("assets", "optics", "render", "manifest", "generate", "qa", "train", "commands")


def _modules() -> dict[str, Path]:
    out = {}
    for p in PKG.rglob("*.py"):
        parts = list(p.relative_to(PKG.parent).with_suffix("").parts)
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


def _imports(path: Path, modules) -> list[tuple[str, bool]]:
    """(imported dofsynth module, inside a function?) of one file; `from pkg import sub` counts
    as an import of the submodule."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    nested = {id(n) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
              for n in ast.walk(f)}
    out = []
    for n in ast.walk(tree):
        if isinstance(n, ast.Import):
            names = [a.name for a in n.names]
        elif isinstance(n, ast.ImportFrom) and n.module and n.level == 0:
            subs = [f"{n.module}.{a.name}" for a in n.names if f"{n.module}.{a.name}" in modules]
            names = subs if len(subs) == len(n.names) else [n.module, *subs]
        else:
            continue
        out += [(m, id(n) in nested) for m in names if m in modules]
    return out


def _stage(module: str) -> int:
    return STAGES.index(".".join(module.split(".")[:2]))


def test_every_module_belongs_to_a_stage_and_the_folders_exist():
    for folder in FOLDERS:
        assert (PKG / folder / "__init__.py").is_file(), folder
    for m in _modules():
        assert ".".join(m.split(".")[:2]) in STAGES, f"{m} is in no stage of tests/test_layout.py"


def test_stages_import_only_earlier_stages_and_nothing_cycles():
    modules = _modules()
    graph = {m: {d for d, _ in _imports(p, modules) if d != m} for m, p in modules.items()}
    upward = [(m, d) for m, deps in graph.items() for d in deps if _stage(d) > _stage(m)]
    assert not upward, f"imports of later stages: {upward}"
    state: dict[str, int] = {}

    def visit(m, path):
        state[m] = 1
        for d in graph[m]:
            assert state.get(d) != 1, f"import cycle: {' -> '.join(path + [d])}"
            if d not in state:
                visit(d, path + [d])
        state[m] = 2

    for m in graph:
        if m not in state:
            visit(m, [m])


def test_no_dofsynth_import_is_hidden_in_a_function_below_the_command_line():
    """Function-local imports would hide a dependency (or dodge a cycle); only the command
    modules import lazily, to keep `dofsynth --help` fast and torch out of generation."""
    modules = _modules()
    hidden = [(m, d) for m, p in modules.items() if _stage(m) < STAGES.index("dofsynth.commands")
              for d, nested in _imports(p, modules) if nested]
    assert not hidden, hidden


def test_every_module_is_under_400_lines():
    long = {m: n for m, p in _modules().items() if (n := len(p.read_text(encoding="utf-8").splitlines())) >= 400}
    assert not long, long

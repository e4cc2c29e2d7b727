"""Build hook only (the metadata is in pyproject.toml): a wheel carries the shipped recipes,
training configs and docs as package data (dofsynth/recipes/*.toml, dofsynth/docs/*.md), so
`dofsynth generate demo` and `dofsynth docs FORMAT` work from a wheel in any folder. An editable
install reads them from the checkout instead (dofsynth.shipped)."""
import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

SHIPPED = {"recipes": "*.toml", "docs": "*.md"}


class BuildPyWithShipped(build_py):
    def run(self):
        super().run()
        if getattr(self, "editable_mode", False):
            return
        for folder, pattern in SHIPPED.items():
            dst = Path(self.build_lib) / "dofsynth" / folder
            dst.mkdir(parents=True, exist_ok=True)
            for f in sorted(Path(folder).glob(pattern)):
                shutil.copy2(f, dst / f.name)


setup(cmdclass={"build_py": BuildPyWithShipped})

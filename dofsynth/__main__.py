"""`python -m dofsynth` is the `dofsynth` console script."""
from dofsynth.cli import main

raise SystemExit(main())

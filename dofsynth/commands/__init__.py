"""One module per `dofsynth` subcommand; each defines `register(subparsers)` (see dofsynth.cli)."""

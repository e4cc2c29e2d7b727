"""`python -m dofsynth` and the `dofsynth` console script.

Ctrl-C and SIGTERM are held from the first line: on a cold start the command line's own imports
take a second or more, and a signal inside them would end in a traceback (SIGINT) or with no
line at all (SIGTERM). `cli.main` installs its handlers, then lets a held signal through.
"""
import signal


def main() -> int:
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    from dofsynth.cli import main as run

    return run()


if __name__ == "__main__":
    raise SystemExit(main())

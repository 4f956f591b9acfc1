"""The ``sdh2svc`` command. Loading it takes about a second (numpy, scipy): Ctrl-C meanwhile
ends it as Ctrl-C later does, exit status 130, not with a traceback of the imports."""

from __future__ import annotations

import sys


def main() -> None:
    try:
        from sdh2svc.cli import main as command

        status = command()
    except KeyboardInterrupt:
        status = 130  # (cli.Exit.INTERRUPTED, which may not be loaded yet)
    sys.exit(status)

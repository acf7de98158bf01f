"""The ``skyfit`` console script: Ctrl-C handled before the package (and torch) is imported.

Importing skyfit imports torch, which takes seconds; a Ctrl-C then would end in a
KeyboardInterrupt traceback from inside the import machinery. This module lives outside the
package, so that nothing heavy is imported before it runs: it turns a Ctrl-C during start-up
into the same one line, ``skyfit: interrupted``, and exit status 130 as a Ctrl-C during the
work (which :func:`skyfit.cli.main` handles; docs/reliability.md). ``python -m skyfit.cli``
runs the same commands without this guard during its imports.
"""
from __future__ import annotations

import os
import signal
import sys

EXIT_INTERRUPTED = 130
"""128 + SIGINT, the shell's status for a command ended by Ctrl-C."""


def _interrupted_during_startup(signum, frame) -> None:
    # Nothing has been written yet: leave at once (a KeyboardInterrupt here would unwind through the imports).
    try:
        sys.stderr.write("skyfit: interrupted\n")
        sys.stderr.flush()
    finally:
        os._exit(EXIT_INTERRUPTED)


def main() -> int:
    """Import the command line with Ctrl-C guarded, then run it (it handles Ctrl-C from there on)."""
    previous = signal.getsignal(signal.SIGINT)
    guarded = previous is signal.default_int_handler  # a parent that ignores SIGINT keeps it ignored
    if guarded:
        signal.signal(signal.SIGINT, _interrupted_during_startup)
    from skyfit.cli import main as cli_main

    if guarded:
        signal.signal(signal.SIGINT, previous)
    return cli_main()


if __name__ == "__main__":
    sys.exit(main())

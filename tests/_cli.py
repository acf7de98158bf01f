"""Run the command line in-process, for the CLI tests."""
from __future__ import annotations

from skyfit.cli import main


def run(argv, capsys):
    """main() in-process -> (exit status, stdout, stderr); argparse errors exit via SystemExit."""
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as e:
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err

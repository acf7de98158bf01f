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


def minimal_result(path, mie_g: float = 0.7, version: int = 1):
    """A minimal RESULT.json (the keys skyfit.fit.results.check_result requires): earth with one fitted mie_g."""
    import json
    from pathlib import Path

    from skyfit.atmosphere import load_yaml

    cfg = load_yaml(Path(__file__).resolve().parents[1] / "skyfit" / "configs" / "earth.yaml")
    res = {"skyfit_result": version, "parameters": {"mie_g": mie_g}, "free": ["mie_g"], "integrator": {"name": "taylor"},
           "config": cfg, "model": {"wavelengths_nm": [450.0, 550.0, 650.0], "orders": 1}}
    path = Path(path)
    path.write_text(json.dumps(res))
    return path

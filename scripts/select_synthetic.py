"""The model ladder on the synthetic skies of tests/test_select.py, printed as Markdown (docs/selection.md).

Each scenario renders a sky from a config (with or without aerosol, ozone, multiple
scattering; noon or twilight), climbs the ladder with ``sigma="known"`` and prints the rung
table, the reason for the choice, the held-out check and the CPU time (process time: the
machine is shared). The sky helpers are the tests' own (tests/test_select.py).

    .venv/bin/python scripts/select_synthetic.py      # Markdown on stdout (docs/selection.md pastes it)
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_select import _cfg, _subset, ladder, synthetic  # noqa: E402

from skyfit.fit.select import format_table  # noqa: E402


def main() -> int:
    torch.set_num_threads(1)
    r4 = _subset("rayleigh", "mie", "ozone", "multiple")
    cases = [
        ("no aerosol (Rayleigh + ozone), sun 40 deg", _cfg(mie=False), 40.0, 1, 1, 240,
         _subset("rayleigh", "mie", "ozone", "scale_heights")),
        ("earth (aerosol + ozone), sun 60 deg", _cfg(), 60.0, 1, 4, 240, _subset("rayleigh", "mie", "ozone")),
        ("earth without ozone, sun 60 deg", _cfg(ozone=False), 60.0, 1, 5, 240, _subset("rayleigh", "mie", "ozone")),
        ("earth, single scattering only, sun 30 deg", _cfg(), 30.0, 1, 6, 120, r4),
        ("earth with multiple scattering, sun 94 deg (twilight)", _cfg(), 94.0, 2, 7, 120, r4),
        ("earth with multiple scattering, sun 30 deg (noon)", _cfg(), 30.0, 2, 8, 120, r4),
    ]
    for title, cfg, sun_zenith, orders, seed, n, rungs in cases:
        c0 = time.process_time()
        rep = ladder(_cfg(), synthetic(cfg, sun_zenith, orders=orders, seed=seed, n=n), rungs).run()
        print(f"### {title}: data orders {orders}, {n} directions, seed {seed}\n")
        print("```\n" + format_table(rep) + "\n```\n")
        chosen = next(r for r in rep["rungs"] if r["name"] == rep["chosen"])
        print(f"chosen: {rep['why']}\n\nparameters: {chosen['parameters']}\n")
        print(f"held-out choice: {rep['heldout_choice']} (agrees: {rep['heldout_agrees']}; margin {rep['heldout_margin']}); "
              f"CPU {time.process_time() - c0:.1f} s\n", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

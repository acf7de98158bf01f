"""Print every fit and every Bruneton table build of a photo fit's lagged refreshes (docs/photos.md).

    .venv/bin/python scripts/trace_lagged.py /tmp/photo_cases_s1/case_005

CASE is a folder of ``skyfit.tools.photo_synth.make_suite`` (its ``truth.json`` gives the photo, time and place).
Each ``fit`` line: the loss, AOD, Angstrom alpha and g it ended at, and the trust region's centre; each ``build``
line: the atmosphere the tables were built at; each ``change``: the factor's largest relative change at the rebuild.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import torch


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    import skyfit
    import skyfit.fit.photo as P

    folder = Path(args[0])
    truth = json.loads((folder / "truth.json").read_text())
    optimise, factor_change, freeze_tables = P.optimise, P.factor_change, P.freeze_tables

    def values(problem, x) -> str:
        d = problem.param.physical_dict(x)
        return f"AOD {float(d['mie_aod_550']):.4f} alpha {float(d['mie_angstrom_alpha']):.3f} g {float(d['mie_g']):.3f}"

    def traced_optimise(problem, options):
        r = optimise(problem, options)
        trust = getattr(problem, "trust", None)
        centre = f", trust centre AOD {float(torch.tensor(trust[0]).exp()):.4f}" if trust is not None else ""
        print(f"  fit    loss {r.loss:.4f} over {problem.n_elements} elements: {values(problem, r.x)}{centre}", flush=True)
        return r

    def traced_change(old, new):
        v = factor_change(old, new)
        print(f"  change {v:.4f}", flush=True)
        return v

    def traced_freeze(problem, x, bruneton=None, *a, **k):
        print(f"  build  at {values(problem, x)}", flush=True)
        return freeze_tables(problem, x, bruneton, *a, **k)

    P.optimise, P.factor_change, P.freeze_tables = traced_optimise, traced_change, traced_freeze
    r = skyfit.fit_photo(folder / truth["photo"].rstrip("/"), time=truth["time"], location=truth["location"])
    tp = truth["atmosphere"]["parameters"]
    true_aod = tp.get("aod_550", tp.get("mie_aod_550"))
    print(f"AOD {r.result['aerosol']['aod_550']:.4f} (truth {true_aod:.4f}), rel. rms {r.result['metrics']['rmse_rel']:.4f}")
    for n in r.result.get("notes", []):
        print("note:", n)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

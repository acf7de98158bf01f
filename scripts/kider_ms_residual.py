"""How the Kider residual near the sun and the horizon changes with the multiple-scattering model (issue 14, item 3).

    .venv/bin/python scripts/kider_ms_residual.py --results /tmp/kider_aerosol --variant hg --out docs/kider/ms_residual.json

For each per-capture fit RESULT.json (``{variant}_{HH.MM}.json`` from scripts/kider_aerosol.py), the
model is re-evaluated at the fitted values with each multiple-scattering setting below, nothing refitted:

- ``hillaire_32x12``: the fits' setting (configs/kider.yaml: 32 directions x 12 steps);
- ``hillaire_64x20``: the library default (docs/hillaire.md);
- ``bruneton_4``: Bruneton & Neyret 2008 tables, 4 orders, at ``--table-sizes`` (default: the fits'
  reduced set doubled; the convergence of that choice is printed for one capture with ``--check-sizes``).

Per capture and setting: RMSE over the valid samples and 36 bands (mW/(m^2 sr nm)), the share of the
squared error in the 5 samples nearest the sun and in the samples below 20 deg elevation, and the
mean signed residual (model - data) of each group, so a change of the model near the sun or the horizon
shows as a change of those numbers.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import time
from pathlib import Path

import torch

from skyfit.scattering.multiple import ACCURATE_QUADRATURE

ROOT = Path(__file__).resolve().parents[1]
DAY = ROOT.parent / "shared" / "data" / "kider2014" / "2013-05-27"
SETTINGS = {
    "hillaire_32x12": dict(multiple="hillaire", lut_directions=32, lut_samples=12),
    "hillaire_64x20": dict(multiple="hillaire", lut_directions=64, lut_samples=20),
    # Gauss-Legendre view rays and split zenith bands (ACCURATE_QUADRATURE; every fit's default since session 20):
    # the HG results' models are Hillaire's and carry no rule, so it is set here; before session 20 this row used
    # 2017's equal steps (docs/kider.md, item 3)
    "bruneton_4": dict(multiple="bruneton", orders=4, ray_rule=ACCURATE_QUADRATURE.ray_rule,
                       density_directions=ACCURATE_QUADRATURE.density_directions),
}


def _capture(name: str) -> Path:
    for p in DAY.iterdir():
        if p.is_dir() and p.name.split("___")[-1][:5] == name:
            return p
    raise SystemExit(f"no capture {name} under {DAY}")


def _predict(res: dict, capture: Path, changes: dict, bruneton: dict | None = None):
    """The fitted model's prediction (W/(m^2 sr nm)) for ``capture`` with SkyModel ``changes``, and its observation.

    ``bruneton``: SkyModel changes of Bruneton tables whose multiple scattering (all orders minus the tables'
    own first order) is added to the problem's live single scattering (``skyfit.fit.photo.freeze_tables``,
    the photo fits' model; the factor on 8 wavelength nodes, interpolated between them).
    """
    from skyfit.fit.parameters import NUISANCE
    from skyfit.fit.photo import freeze_tables
    from skyfit.fit.problem import fit_settings, load_data, prepare
    from skyfit.fit.results import fitted_atmosphere_values, model_from_result
    from skyfit.fit.run import _nuisance_for

    s = dataclasses.replace(fit_settings(res.get("settings"), None), max_samples=None)
    base = model_from_result(res)
    model = dataclasses.replace(base, **changes)
    obs = load_data([capture], s, None, None)
    prep = prepare(obs, res["config"], s, model=model)
    values = fitted_atmosphere_values(res)
    for n in NUISANCE:
        v = [_nuisance_for(res, o, n) for o in obs]
        if all(x is not None for x in v):
            values[n] = v if n != "noise_scale" else v[0]
    problem = prep.problem([], [n for n in NUISANCE if n != "noise_scale"], values)
    x = problem.param.initial_vector(s.torch_dtype, prep.base.device)
    if bruneton is not None:
        freeze_tables(problem, x, dataclasses.replace(base, **bruneton), wavelength_nodes_count=8)
    with torch.no_grad():
        return problem.predict(x)[0], problem.observations[0]


def evaluate(res: dict, capture: Path, setting: dict, table_sizes: tuple[int, ...] | None) -> dict:
    """The model at the fitted values with ``setting``: RMSE and the near-sun / near-horizon shares.

    Bruneton's tables carry only the multiple scattering (orders 2-4: the tables' all-orders minus their
    own single scattering, so the tables' interpolation of the Mie peak cancels) on top of the fit's
    live single scattering, as Hillaire's LUT does.
    """
    t0 = time.process_time()
    if setting.get("multiple") == "bruneton":
        pred, o = _predict(res, capture, {"orders": 1}, bruneton={**setting, "table_sizes": table_sizes})
    else:
        pred, o = _predict(res, capture, setting)
    cpu = time.process_time() - t0
    m = o.mask.bool()
    r = (pred - o.values)[m] * 1000.0  # mW/(m^2 sr nm)
    d = o.directions[m]
    sz, sa = o.sun_zenith, o.sun_azimuth
    sun = torch.stack([torch.sin(sz) * torch.sin(sa), torch.sin(sz) * torch.cos(sa), torch.cos(sz)], -1)  # (3,) or (N, 3)
    if sun.dim() == 2:
        sun = sun[m]
    ang = torch.rad2deg(torch.acos(torch.clamp((d * sun).sum(-1), -1.0, 1.0)))
    elev = torch.rad2deg(torch.asin(torch.clamp(d[:, 2], -1.0, 1.0)))
    sq = (r * r).sum(1)
    near = torch.argsort(ang)[:5]
    low = elev < 20.0
    tot = float(sq.sum())
    return {
        "rmse": math.sqrt(tot / r.numel()), "cpu_s": cpu,
        "sun5_share": float(sq[near].sum()) / tot, "sun5_mean_resid": float(r[near].mean()),
        "horizon_share": float(sq[low].sum()) / tot, "horizon_mean_resid": float(r[low].mean()) if bool(low.any()) else None,
        "horizon_n": int(low.sum()), "n": int(m.sum()),
    }


def main() -> None:
    from skyfit.fit.results import read_result

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default="/tmp/kider_aerosol")
    ap.add_argument("--variant", default="hg")
    ap.add_argument("--captures", default="all")
    ap.add_argument("--table-sizes", default="128,32,32,8,16,64,16,8", help="Bruneton sizes (the fit's 8-tuple)")
    ap.add_argument("--check-sizes", default="", help="also evaluate bruneton_4 at these sizes on the first capture")
    ap.add_argument("--out", default="")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    files = sorted(Path(args.results).glob(f"{args.variant}_??.??.json"))
    if args.captures != "all":
        files = [f for f in files if f.stem.split("_")[-1] in args.captures.split(",")]
    sizes = tuple(int(v) for v in args.table_sizes.split(","))
    rows = []
    for k, f in enumerate(files):
        name = f.stem.split("_")[-1]
        res = read_result(f)
        row = {"capture": name}
        for label, setting in SETTINGS.items():
            row[label] = evaluate(res, _capture(name), setting, sizes)
        if k == 0 and args.check_sizes:
            fine = tuple(int(v) for v in args.check_sizes.split(","))
            row["bruneton_4_check"] = {"sizes": fine, **evaluate(res, _capture(name), SETTINGS["bruneton_4"], fine)}
        rows.append(row)
        print(json.dumps(row), flush=True)
    summary = {label: {key: statistics.mean(r[label][key] for r in rows) for key in ("rmse", "sun5_share", "horizon_share")}
               for label in SETTINGS}
    print(json.dumps({"mean": summary}), flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps({"command": "python scripts/kider_ms_residual.py " + " ".join(
            f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items() if v not in ("", None)), "variant": args.variant,
            "table_sizes": sizes, "rows": rows, "mean": summary}, indent=1))


if __name__ == "__main__":
    main()

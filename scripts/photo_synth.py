"""Write realistic synthetic all-sky photos with known truth (skyfit.tools.photo_synth).

    .venv/bin/python scripts/photo_synth.py --out synth --n 10 --seed 0
    .venv/bin/python scripts/photo_synth.py --out one --n 1 --seed 7 --bracket --projection stereographic
    .venv/bin/python scripts/photo_synth.py --out quick --n 5 --quick          # single scattering, small

With ``--n N`` and neither ``--bracket`` nor ``--single``, the suite spreads the cases over the five
projections with and without brackets (:func:`make_suite`); with one of them every case is of that
kind, seeded ``seed * 1000 + i``. Each case folder holds ``photo.jpg`` or ``bracket/``, ``mask_truth.png``,
``truth.json`` and ``truth_arrays.npz``; ``suite.json`` lists them.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from skyfit.camera.fisheye import PROJECTIONS
from skyfit.tools import photo_synth as ps


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n", 1)[1])
    ap.add_argument("--out", required=True, type=Path, help="folder for the cases (case_NNN/ each)")
    ap.add_argument("--n", type=int, default=10, help="number of cases (default 10)")
    ap.add_argument("--seed", type=int, default=0, help="random seed of the suite (default 0)")
    ap.add_argument("--size", type=int, default=600, help="side of single photos, even (default 600) [px]")
    ap.add_argument("--bracket-size", type=int, default=300, help="side of bracket frames, even (default 300) [px]")
    kind = ap.add_mutually_exclusive_group()
    kind.add_argument("--bracket", action="store_true", help="every case a bracket (3-7 JPEG frames)")
    kind.add_argument("--single", action="store_true", help="every case a single JPEG")
    ap.add_argument("--projection", choices=PROJECTIONS, help="one projection for every case (default: spread)")
    ap.add_argument("--aod", type=float, help="Mie AOD at 550 nm for every case (default: 0.05-0.5)")
    ap.add_argument("--sun-zenith", type=float, help="geometric sun zenith for every case (default: 20-80) [deg]")
    ap.add_argument("--frames", type=int, help="bracket frames (default: 3-7 as the scene needs)")
    ap.add_argument("--quick", action="store_true", help="single scattering on a coarse grid (for smoke tests)")
    ap.add_argument("--cache", type=Path, help="folder caching rendered skies between runs")
    args = ap.parse_args(argv)
    for name in ("size", "bracket_size"):
        v = getattr(args, name)
        if v < 32 or v % 2:
            ap.error(f"--{name.replace('_', '-')} must be even and >= 32, got {v}")
    if args.n < 1:
        ap.error("--n must be >= 1")
    settings = ps.TEST_SETTINGS if args.quick else ps.SynthSettings()
    if args.cache:
        settings = dataclasses.replace(settings, cache_dir=str(args.cache))
    t0 = time.perf_counter()
    if not (args.bracket or args.single or args.projection or args.aod is not None
            or args.sun_zenith is not None or args.frames):
        ps.make_suite(args.out, args.n, args.seed, size=args.size, bracket_size=args.bracket_size, settings=settings,
                      progress=print)
    else:
        summary = []
        for i in range(args.n):
            bracket = args.bracket or (not args.single and i % 2 == 1)
            t = ps.make_case(args.seed * 1000 + i, args.out / f"case_{i:03d}",
                             size=args.bracket_size if bracket else args.size, bracket=bracket,
                             projection=args.projection or PROJECTIONS[i % len(PROJECTIONS)], aod_550=args.aod,
                             sun_zenith_deg=args.sun_zenith, n_frames=args.frames, settings=settings)
            print(f"case_{i:03d}: {t['camera']['projection']}, {'bracket' if bracket else 'single'}, "
                  f"AOD {t['atmosphere']['parameters']['mie_aod_550']:.3f}, sun zenith {t['sun']['zenith_deg']:.2f}, "
                  f"{t['generator']['case_wall_s']:.1f} s")
            summary.append({"case": f"case_{i:03d}", "time": t["time"], "location": t["location"],
                            "bracket": bracket, "projection": t["camera"]["projection"]})
        (args.out / "suite.json").write_text(json.dumps({"schema": ps.SCHEMA, "seed": args.seed, "cases": summary}, indent=1))
    print(f"{args.n} case(s) in {args.out} ({time.perf_counter() - t0:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

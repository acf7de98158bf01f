"""Tooling on top of the library: benchmarks, reference integrations, checks and the demo.

Nothing in the library (``skyfit.atmosphere`` ... ``skyfit.api``) imports this package;
``skyfit.cli`` and ``scripts/`` do.

========================  =====================================================================
module                    what it is
========================  =====================================================================
bench                     ``skyfit bench``: speed and accuracy of the transmittance integrators
                          (Gałaj 2021 Table 3 with our code), and :func:`bench.torch_threads`
trade                     ``skyfit bench --study trade``: speed/accuracy of every renderer
                          setting; writes the measurements :mod:`skyfit.render.auto` reads
reference                 independent float64 scipy references (optical-depth columns) for
                          tests, accuracy tables and benchmarks
stability                 the extreme-grid stability check: NaN/Inf and error counts per method
                          (tests/test_extremes.py, scripts/stability_report.py)
integrator_calibration    ``skyfit calibrate-integrator``: Taylor (a, b) per atmosphere and layer,
                          spline grid and view samples (docs/integrator_calibration.md)
demo                      ``skyfit demo``: render, noise, fit, uncertainty, LUTs, truth vs recovered
photo_synth               realistic synthetic all-sky photos and brackets with known truth (multiple
                          scattering, camera sensitivities, Bayer, flare, skyline, JPEG/EXIF);
                          ``scripts/photo_synth.py``
========================  =====================================================================
"""

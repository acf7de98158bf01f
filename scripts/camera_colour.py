"""How three published cameras render sky colours against CIE colorimetry (docs/photos.md, "A camera is not a
colorimeter").

Spectra D65 x (lambda / 550 nm)^-a (a = 4: a clear zenith, 0: white haze) go through each camera's sensitivities
(colour-science), its daylight white balance and rawtoaces matrix to linear sRGB
(:func:`skyfit.tools.photo_synth.colour_pipeline`, the generator's pipeline), and through CIE 1931 -> linear sRGB.
Prints the camera's red/green and blue/green over CIE's, relative to white, and the least-squares fit of three
models of the difference on log chromaticity: gains only, gains and one saturation, gains and red/blue saturations
(Y + s (c - Y) about sRGB's luminance; what :class:`skyfit.fit.model.FitProblem` applies).

    .venv/bin/python scripts/camera_colour.py
"""
from __future__ import annotations

import warnings

import numpy as np
from scipy.optimize import least_squares

import skyfit
from skyfit.tools.photo_synth import camera_sensitivities, colour_pipeline

CAMERAS = ("Canon EOS 5D Mark II (rawtoaces)", "Nikon 5100 (NPL)", "Sigma SDMerill (NPL)")


def main() -> int:
    warnings.filterwarnings("ignore")
    import colour

    shape = colour.SpectralShape(400, 700, 5)
    lam = np.arange(400.0, 701.0, 5.0)
    d65 = colour.SDS_ILLUMINANTS["D65"].copy().align(shape).values
    cmf = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(shape).values
    to_srgb = np.asarray(skyfit.render.colour.xyz_to_srgb_matrix())
    y_w = np.linalg.inv(to_srgb)[1]
    slopes = np.linspace(-0.5, 4.5, 11)
    spectra = np.stack([d65 * (lam / 550.0) ** -a for a in slopes])
    base = spectra @ (cmf @ to_srgb.T)
    print("| camera | R/G over CIE at a = 4, 2, 0.5 | B/G over CIE at a = 4, 2, 0.5 | rms log chromaticity: gains | "
          "+ one saturation (s) | + red, blue saturations (s_R, s_B) |")
    print("|---|---|---|---|---|---|")
    for name in CAMERAS:
        wl, sens = camera_sensitivities(name)
        s_i = np.stack([np.interp(lam, wl, sens[:, c]) for c in range(3)], 1)
        pipe = colour_pipeline(name)
        cam = ((spectra @ s_i) * pipe["daylight_gains"] / pipe["daylight_gains"][1]) @ pipe["matrix"].T
        white_c, white_b = cam[np.argmin(abs(slopes))], base[np.argmin(abs(slopes))]
        rel = (cam / white_c) / (base / white_b)
        pick = [int(np.argmin(abs(slopes - a))) for a in (4.0, 2.0, 0.5)]
        target = np.log(cam / cam[:, 1:2])[:, [0, 2]]

        def resid(q):
            y = (base @ y_w)[:, None]
            out = (y + np.array([q[2], 1.0, q[3]]) * (base - y)) * np.array([np.exp(q[0]), 1.0, np.exp(q[1])])
            return (np.log(out / out[:, 1:2])[:, [0, 2]] - target).ravel()

        rms = lambda r: float(np.sqrt(np.mean(r.fun**2)))  # noqa: E731
        g = least_squares(lambda q: resid(np.r_[q, 1.0, 1.0]), [0.0, 0.0])
        one = least_squares(lambda q: resid(np.r_[q[:2], q[2], q[2]]), [0.0, 0.0, 1.0])
        two = least_squares(resid, [0.0, 0.0, 1.0, 1.0])
        print(f"| {name} | " + ", ".join(f"{rel[k, 0] / rel[k, 1]:.3f}" for k in pick) + " | "
              + ", ".join(f"{rel[k, 2] / rel[k, 1]:.3f}" for k in pick)
              + f" | {rms(g):.4f} | {rms(one):.4f} (s {one.x[2]:.2f}) | {rms(two):.4f} (s_R {two.x[2]:.2f}, s_B {two.x[3]:.2f}) |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

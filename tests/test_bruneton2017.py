"""``export-lut --layout bruneton2017`` (skyfit.export.bruneton2017, docs/luts.md).

The NumPy transcription of the exported GLSL (skyfit.export.shader_reference: GL texel fetches
and filtering written from the OpenGL specification, not skyfit's torch sampler) renders the
exported files; it must reproduce skyfit's own render. Small tables keep the file near a minute.
"""
from __future__ import annotations

import json
import math
import shutil
import subprocess

import numpy as np
import pytest
import torch

from skyfit.atmosphere import load_atmosphere
from skyfit.export import bruneton2017 as b17
from skyfit.export.lut import LutError, rgb_matrix
from skyfit.export.shader_reference import Bruneton2017Shader, band_table, relative_errors, texture2d, view_grid
from skyfit.io import read_exr
from skyfit.scattering.bruneton_tables import TableSizes, mu_s_from_unit, scattering_texel_params
from skyfit.scattering.multiple import Quadrature, precompute
from skyfit.scattering.phase import rayleigh_phase

from _cli import minimal_result, run

SIZES = TableSizes(scattering_r=8, scattering_mu=32, scattering_mu_s=8, scattering_nu=4, transmittance_mu=64,
                   transmittance_r=16, irradiance_mu_s=16, irradiance_r=8)
QUAD = Quadrature(density_theta=8, density_phi=16, irradiance_theta=8, irradiance_phi=16, multiple_samples=20)
LAM = [400.0, 450.0, 500.0, 550.0, 600.0, 650.0, 700.0]
SUNS = (0.0, 30.0, 60.0, 80.0, 90.0, 95.0)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    atm = load_atmosphere("earth", LAM)
    atm_rgb = load_atmosphere("earth", list(b17.LAMBDAS_RGB_NM))
    m = b17.skyfit_mu_s_min(b17.UPSTREAM_MU_S_MIN, atm.bottom_radius, atm.top_radius)
    with torch.no_grad():
        t1 = precompute(atm, orders=1, sizes=SIZES, quadrature=QUAD, mu_s_min=m)
        t2 = precompute(atm, orders=2, sizes=SIZES, quadrature=QUAD, mu_s_min=m)
    root = tmp_path_factory.mktemp("b17")
    dirs = {(o, p): b17.export_bruneton2017(t, root / f"o{o}_{p}", precision=p, atm_rgb=atm_rgb)
            for o, t in ((1, t1), (2, t2)) for p in ("f16", "f32")}
    return {"atm": atm, 1: t1, 2: t2, "dirs": dirs}


def test_mu_s_mapping_equivalence():
    """skyfit's texels at mu_s_min m are upstream's texels at upstream_mu_s_min(m), computed here from upstream's formula."""
    b, t = 6_360_000.0, 6_420_000.0
    up = -0.2
    m = b17.skyfit_mu_s_min(up, b, t)
    assert b17.upstream_mu_s_min(m, b, t) == pytest.approx(up, abs=1e-12)
    x = np.linspace(0.0, 1.0, 9)
    H = math.sqrt(t * t - b * b)
    dist = lambda mu: -b * mu + math.sqrt(b * b * (mu * mu - 1) + t * t)  # noqa: E731
    A = (dist(up) - (t - b)) / (H - (t - b))  # upstream GetRMuMuSNuFromScatteringTextureUvwz
    a = (A - x * A) / (1 + x * A)
    d = (t - b) + np.minimum(a, A) * (H - (t - b))
    want = np.clip((H * H - d * d) / (2 * b * d), -1, 1)
    got = mu_s_from_unit(torch.as_tensor(x, dtype=torch.float64), b, t, m).numpy()
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    assert want[0] == pytest.approx(up)
    with pytest.raises(LutError, match="mu_s_min"):
        b17.skyfit_mu_s_min(0.1, b, t)


def test_gl_texture_filtering_on_a_known_image():
    """texture2d on an affine image returns the affine function at texel-centre coordinates, clamped at the edges."""
    h, w = 4, 6
    y, x = np.mgrid[0:h, 0:w].astype(float)
    img = np.stack([2 * x + 3 * y], -1)
    u, v = (np.array([0.5, 2.75, 4.5]) + 0.5) / w, (np.array([0.0, 1.25, 3.0]) + 0.5) / h
    np.testing.assert_allclose(texture2d(img, u, v)[:, 0], 2 * np.array([0.5, 2.75, 4.5]) + 3 * np.array([0.0, 1.25, 3.0]))
    np.testing.assert_allclose(texture2d(img, np.array([-1.0]), np.array([2.0]))[:, 0], [3 * (h - 1)])  # clamp to edge


def test_scattering_texture_folds_multiple_scattering_as_2017(setup):
    """RGB = (S_R + S_multiple / P_R(nu_texel)) M / 683 and A = red of S_M M / 683, at every texel (model.cc)."""
    t = setup[2]
    tex, consts = b17.bruneton2017_textures(t)
    m = rgb_matrix(t.atm.wavelengths).numpy() / 683.0
    p = scattering_texel_params(t.atm.bottom_radius, t.atm.top_radius, t.mu_s_min, SIZES, torch.float64, "cpu")
    i = (3, 20, 5, 2)  # (r, mu, mu_s, nu), a sky texel
    p_r = float(rayleigh_phase(p.nu[i]))
    want = (t.single_rayleigh[i].numpy() + t.multiple[i].numpy() / p_r) @ m
    row, col = i[0] * SIZES.scattering_mu + i[1], i[3] * SIZES.scattering_mu_s + i[2]
    np.testing.assert_allclose(tex["scattering"][row, col, :3], want, rtol=1e-12)
    assert tex["scattering"][row, col, 3] == pytest.approx((t.single_mie[i].numpy() @ m)[0], rel=1e-12)
    assert consts["mu_s_min"] == pytest.approx(-0.2) and consts["sky_spectral_radiance_to_luminance"] == [683.0] * 3


def test_single_scattering_is_reproduced_exactly(setup):
    """Orders 1, float32, separate Mie texture: the shader's sky equals skyfit's to float32 rounding."""
    sh = Bruneton2017Shader.from_dir(setup["dirs"][(1, "f32")], combined=False)
    view = view_grid(2.0, 30.0)
    view = view[view[:, 2] > 0]
    for sz in (0.0, 60.0, 90.0):
        err, ref = relative_errors(sh, setup[1], view, sz)
        keep = ref > 1e-6 * ref.max()
        assert err[keep].max() < 2e-6, (sz, err[keep].max())


# Measured with the tables above (8 r x 32 mu x 8 mu_s x 4 nu, orders 2, 400:700:50 nm), suns 0, 30, 60, 80, 90,
# 95 deg, view zenith 1 deg x azimuth 30 deg steps, separate Mie texture: (median, max) of the per-channel relative
# error by band [0-30, 30-60, 60-80, 80-85, 85-88, 88-90, ground]. docs/luts.md has the table at 16 x 64 x 16 x 8
# (scripts/bruneton2017_accuracy.py). The sky's error is 2017's storage itself: S_multiple / P_R(nu) interpolated in
# nu (skyfit's sampler on such a folded table differs from its unfolded one as much: max 12 % / 16 % at sun 30 / 60
# deg with 4 nu texels); the ground's adds the sun and transmittance at three wavelengths.
MEASURED = {"f32": [(0.0050, 0.089), (0.0140, 0.090), (0.0070, 0.102), (0.0042, 0.099), (0.0056, 0.108),
                    (0.0074, 0.121), (0.0056, 0.174)],
            "f16": [(0.0050, 0.089), (0.0140, 0.090), (0.0070, 0.102), (0.0043, 0.099), (0.0058, 0.108),
                    (0.0074, 0.121), (0.0056, 0.174)]}


@pytest.fixture(scope="module")
def band_errors(setup):
    view = view_grid(1.0, 30.0)
    out = {}
    for prec in ("f32", "f16"):
        sh = Bruneton2017Shader.from_dir(setup["dirs"][(2, prec)], combined=False)
        errs = [relative_errors(sh, setup[2], view, sz)[0] for sz in SUNS]
        out[prec] = band_table(np.concatenate(errs), np.concatenate([view] * len(SUNS)))
    return out


@pytest.mark.parametrize("prec", ["f32", "f16"])
def test_orders_2_by_view_zenith_band(band_errors, prec):
    rows = band_errors[prec]
    for row, (med, mx) in zip(rows, MEASURED[prec]):
        print(prec, row)
        assert row["median"] < 1.5 * med and row["max"] < 1.5 * mx, row


def test_half_precision_adds_only_rounding_even_at_the_horizon(setup):
    """|f16 - f32| / f32 of the shader's sky <= a few half-float roundings (2^-11), horizon band included."""
    view = view_grid(0.25, 45.0)
    view = view[view[:, 2] > 0]
    a = Bruneton2017Shader.from_dir(setup["dirs"][(2, "f32")], combined=False)
    h = Bruneton2017Shader.from_dir(setup["dirs"][(2, "f16")], combined=False)
    cam = np.tile([0.0, 0.0, setup["atm"].bottom_radius / 1000.0], (view.shape[0], 1))
    for sz in SUNS:
        z = math.radians(sz)
        sun = np.array([0.0, math.sin(z), math.cos(z)])
        la, lh = a.sky_luminance(cam, view, sun)[0], h.sky_luminance(cam, view, sun)[0]
        keep = la > 1e-4 * la.max()
        rel = np.abs(lh - la)[keep] / la[keep]
        assert rel.max() < 3 * 2.0**-11, (sz, rel.max())


def test_files(setup):
    d = setup["dirs"][(2, "f16")]
    meta = json.loads((d / "lut.json").read_text())
    assert meta["layout"] == "bruneton2017" and meta["precision"] == "f16"
    import OpenEXR

    def types(name):
        f = OpenEXR.File(str(d / name), separate_channels=True)
        return {k: str(c.type()) for k, c in f.channels().items()}

    assert set(types("scattering.exr").values()) == {"PixelType.HALF"} and set(types("scattering.exr")) == set("RGBA")
    assert set(types("transmittance.exr").values()) == {"PixelType.FLOAT"}  # 2017 keeps transmittance float32
    # .dat: RGBA float32, x fastest then y then z: the stacked image row by row
    ch, _ = read_exr(d / "scattering.exr")
    dat = np.fromfile(d / "scattering.dat", dtype="<f4").reshape(SIZES.scattering_r * SIZES.scattering_mu,
                                                                  SIZES.scattering_nu * SIZES.scattering_mu_s, 4)
    np.testing.assert_array_equal(dat, np.stack([ch[c] for c in "RGBA"], -1))
    tr = np.fromfile(d / "transmittance.dat", dtype="<f4").reshape(SIZES.transmittance_r, SIZES.transmittance_mu, 4)
    assert np.all(tr[..., 3] == 0) and 0.8 < tr[0, 0, 1] < 0.95 and tr[0, -1, 1] < 0.05  # ground: zenith (x_mu = 0), horizon
    glsl = (d / "atmosphere.glsl").read_text()
    assert "const int SCATTERING_TEXTURE_MU_SIZE = 32;" in glsl and "const float MU_S_MIN = -0.2" in glsl


@pytest.mark.skipif(shutil.which("glslangValidator") is None, reason="glslangValidator not installed")
def test_glsl_compiles(setup, tmp_path):
    src = (setup["dirs"][(2, "f32")] / "atmosphere.glsl").read_text()
    main = ("\nout vec4 color;\nvoid main() {\n  vec3 t;\n  vec3 c = vec3(0.0, 0.0, BOTTOM_RADIUS + 0.001);\n"
            "  color = vec4(GetSkyAndGroundLuminance(c, vec3(0.0, 0.6, -0.8), vec3(0.0, 0.0, 1.0))\n"
            "      + GetSkyLuminance(c, vec3(0.0, 0.0, 1.0), vec3(0.0, 0.0, 1.0), t) + GetSolarLuminance(), 1.0);\n}\n")
    for combined in (True, False):
        f = tmp_path / f"sky{int(combined)}.frag"
        f.write_text(src.replace("#define COMBINED_SCATTERING_TEXTURES", "" if not combined else
                                 "#define COMBINED_SCATTERING_TEXTURES") + main)
        r = subprocess.run(["glslangValidator", str(f)], capture_output=True, text=True)
        assert r.returncode == 0, r.stdout + r.stderr


FAST = ["--orders", 1, "--table-sizes", "4,8,4,2"]


def test_cli_bruneton2017(tmp_path, capsys):
    res = minimal_result(tmp_path / "RESULT.json")
    out = tmp_path / "luts"
    rc, o, e = run(["export-lut", res, "--out", out, "--layout", "bruneton2017", "--precision", "f16", "--json", *FAST], capsys)
    assert rc == 0, e
    info = json.loads(o)
    assert info["layout"] == "bruneton2017" and info["precision"] == "f16"
    meta = json.loads((out / "lut.json").read_text())
    assert meta["constants"]["mie_g"] == pytest.approx(0.7)  # the fitted value
    assert meta["constants"]["constants_from"].startswith("exact")
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["atmosphere.glsl", "irradiance.dat", "irradiance.exr", "lut.json", "scattering.dat", "scattering.exr",
         "single_mie_scattering.exr", "transmittance.dat", "transmittance.exr"])


def _fails(argv, capsys, match, tmp_path):
    before = sorted(p.name for p in tmp_path.rglob("*"))
    rc, _, err = run(argv, capsys)
    assert rc == 2 and err.count("\n") == 1 and match in err, err
    assert sorted(p.name for p in tmp_path.rglob("*")) == before


def test_cli_bruneton2017_bad_input(tmp_path, capsys):
    res = minimal_result(tmp_path / "RESULT.json")
    out = tmp_path / "o"
    _fails(["export-lut", res, "--out", out, "--layout", "unreal4", *FAST], capsys, "invalid choice", tmp_path)
    _fails(["export-lut", res, "--out", out, "--layout", "bruneton2017", "--precision", "f8", *FAST], capsys,
           "invalid choice", tmp_path)
    _fails(["export-lut", res, "--out", out, "--precision", "f16", *FAST], capsys, "--layout bruneton2017", tmp_path)
    _fails(["export-lut", res, "--out", out, "--layout", "bruneton2017", "--format", "npz", *FAST], capsys, "EXR", tmp_path)
    _fails(["export-lut", minimal_result(tmp_path / "v9.json", version=9), "--out", out, "--layout", "bruneton2017", *FAST], capsys,
           "version 9", tmp_path)

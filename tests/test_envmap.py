"""Environment maps (skyfit.export.envmap, ``skyfit envmap``, docs/envmap.md).

Geometry against closed forms and an independent transcription of OpenGL's cube-map rule; the
sun where NREL SPA puts it; energy against a fisheye render of the same sky; files; bad input.
Small Bruneton tables keep the file at ~1 min on a loaded 2-core CPU.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import skyfit
from skyfit.atmosphere import load_atmosphere, load_yaml
from skyfit.camera import FisheyeCamera, sun_position
from skyfit.export.envmap import (cubemap_directions, cubemap_solid_angles, cubemap_texel, latlong_directions,
                                  latlong_pixel, latlong_solid_angles, latlong_texel, render_envmap, sun_transmittance,
                                  write_envmap)
from skyfit.io import read_exr, read_hdr
from skyfit.render.colour import spectral_to_xyz, xyz_to_linear_srgb
from skyfit.render.sky import render_vectors
from skyfit.scattering.bruneton_tables import TableSizes
from skyfit.scattering.multiple import Quadrature, precompute
from skyfit.transmittance import make_integrator

from _cli import run

LAM = [440.0, 550.0, 680.0]
SIZES = TableSizes(scattering_r=8, scattering_mu=32, scattering_mu_s=8, scattering_nu=4, transmittance_mu=64,
                   transmittance_r=16, irradiance_mu_s=16, irradiance_r=8)
QUAD = Quadrature(density_theta=8, density_phi=16, irradiance_theta=8, irradiance_phi=16, multiple_samples=20)


@pytest.fixture(scope="module")
def atm():
    return load_atmosphere("earth", LAM)


@pytest.fixture(scope="module")
def tables(atm):
    with torch.no_grad():
        return precompute(atm, orders=2, sizes=SIZES, quadrature=QUAD)


# -- geometry -------------------------------------------------------------------------------------
@pytest.mark.parametrize("h", [2, 8, 64])
def test_latlong_solid_angles_and_directions(h):
    om = latlong_solid_angles(h)
    torch.testing.assert_close(om.sum(), torch.tensor(4 * math.pi, dtype=torch.float64), rtol=1e-12, atol=0.0)
    d = latlong_directions(h)
    assert d.shape == (h, 2 * h, 3)
    # row 0 straight up, the horizon between rows h/2 - 1 and h/2, column 0 just East of North
    assert bool((d[: h // 2, :, 2] > 0).all()) and bool((d[h // 2:, :, 2] < 0).all())
    zen = torch.rad2deg(torch.acos(d[..., 2]))
    az = torch.rad2deg(torch.atan2(d[..., 0], d[..., 1])) % 360
    i, j = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(2 * h, dtype=torch.float64), indexing="ij")
    torch.testing.assert_close(zen, (i + 0.5) * 180.0 / h, rtol=0, atol=1e-9)
    torch.testing.assert_close(az, (j + 0.5) * 180.0 / h, rtol=0, atol=1e-9)
    row, col = latlong_texel(d, h)
    assert torch.equal(row, i.long()) and torch.equal(col, j.long())


def test_latlong_pixel_of_the_cardinal_points():
    # East at a quarter of the width, South in the middle, West at three quarters (pixel centres at integers)
    assert latlong_pixel(90.0, 90.0, 32) == (15.5, 15.5)
    assert latlong_pixel(90.0, 180.0, 32) == (15.5, 31.5)
    assert latlong_pixel(0.0, 270.0, 32) == (-0.5, 47.5)


def _gl_face_st(r: np.ndarray) -> tuple[int, float, float]:
    """OpenGL 4.6 core, Table 8.19, written from the specification: (face, s, t) of a Y-up direction."""
    rx, ry, rz = r
    a = np.abs(r)
    if a[0] >= a[1] and a[0] >= a[2]:
        face, sc, tc, ma = (0, -rz, -ry, rx) if rx > 0 else (1, rz, -ry, rx)
    elif a[1] >= a[2]:
        face, sc, tc, ma = (2, rx, rz, ry) if ry > 0 else (3, rx, -rz, ry)
    else:
        face, sc, tc, ma = (4, rx, -ry, rz) if rz > 0 else (5, -rx, -ry, rz)
    return face, (sc / abs(ma) + 1) / 2, (tc / abs(ma) + 1) / 2


def test_cubemap_follows_the_opengl_rule():
    n = 8
    d = cubemap_directions(n)
    om = cubemap_solid_angles(n)
    torch.testing.assert_close(om.sum(), torch.tensor(4 * math.pi, dtype=torch.float64), rtol=1e-12, atol=0.0)
    for f in range(6):
        for i in range(n):
            for j in range(n):
                e, nn, u = d[f, i, j].tolist()
                face, s, t = _gl_face_st(np.array([e, u, -nn]))  # Y-up frame: x = East, y = Up, z = South
                assert face == f and math.isclose(s, (j + 0.5) / n) and math.isclose(t, (i + 0.5) / n)
    face, row, col = cubemap_texel(d, n)
    F, I, J = torch.meshgrid(torch.arange(6), torch.arange(n), torch.arange(n), indexing="ij")
    assert torch.equal(face, F) and torch.equal(row, I) and torch.equal(col, J)
    # face centres: +X East, +Y Up, +Z South, -Z North
    centre = lambda f: d[f, n // 2 - 1: n // 2 + 1, n // 2 - 1: n // 2 + 1].mean((0, 1))  # noqa: E731
    for f, want in ((0, [1, 0, 0]), (2, [0, 0, 1]), (4, [0, -1, 0]), (5, [0, 1, 0])):
        v = centre(f)
        torch.testing.assert_close(v / v.norm(), torch.tensor(want, dtype=torch.float64), rtol=0, atol=1e-12)


def test_cube_texel_solid_angle_is_the_projected_area_integral():
    """One texel's solid angle against scipy's dblquad of 1 / (1 + x^2 + y^2)^1.5 over its face rectangle."""
    from scipy.integrate import dblquad

    n = 4
    om = cubemap_solid_angles(n)[0]
    for i, j in ((0, 0), (1, 2)):
        y0, x0 = -1 + 2 * i / n, -1 + 2 * j / n
        ref, _ = dblquad(lambda y, x: (1 + x * x + y * y) ** -1.5, x0, x0 + 2 / n, y0, y0 + 2 / n, epsabs=1e-13)
        assert math.isclose(float(om[i, j]), ref, rel_tol=1e-10)


# -- the sun ---------------------------------------------------------------------------------------
SITES = [  # (time, lat, lon, elev)
    ("2013-05-27T09:30:00-04:00", 42.443449, -76.481962, 250.0),  # the Kider site, morning
    ("2021-12-21T12:00:00+11:00", -33.87, 151.21, 0.0),  # Sydney, summer noon
    ("2020-03-20T17:00:00+01:00", 48.85, 2.35, 35.0),  # Paris, evening
]


def _dark(d):
    return torch.zeros(d.shape[0], len(LAM), dtype=d.dtype)


@pytest.mark.parametrize("when, lat, lon, elev", SITES)
@pytest.mark.parametrize("layout, size", [("latlong", 64), ("latlong", 512), ("cubemap", 128)])
def test_sun_disc_lands_where_spa_puts_it(atm, when, lat, lon, elev, layout, size):
    sp = sun_position(when, lat, lon, elev)
    zen, az = float(sp.zenith_geometric), float(sp.azimuth)
    sun = skyfit.sun_vector(time=when, location=(lat, lon, elev))
    env = render_envmap(atm, sun, _dark, size=size, layout=layout, sun_disk=True, spectral=False)
    y = env.rgb[..., 1]
    k = np.unravel_index(np.argmax(y), y.shape)
    if layout == "latlong":
        row, col = latlong_pixel(zen, az, size)
        assert abs(k[0] - row) <= 1.0
        assert min(abs(k[1] - col), 2 * size - abs(k[1] - col)) <= 1.0
    else:  # the SPA direction's texel, from the GL rule written in the test
        z, a = math.radians(zen), math.radians(az)
        e, n, u = math.sin(z) * math.sin(a), math.sin(z) * math.cos(a), math.cos(z)
        face, s, t = _gl_face_st(np.array([e, u, -n]))
        assert k[0] == face and abs(k[1] - (t * size - 0.5)) <= 1.0 and abs(k[2] - (s * size - 0.5)) <= 1.0


def test_sun_disc_carries_the_attenuated_solar_flux(atm):
    """Sum over the disc's pixels of L dOmega = E_sun x the disc-mean transmittance (sun at 60 deg)."""
    sun = skyfit.sun_vector((60.0, 135.0))
    for layout, size in (("latlong", 32), ("latlong", 2048), ("cubemap", 16)):
        env = render_envmap(atm, sun, _dark, size=size, layout=layout, sun_disk=True)
        flux = (env.spectral * env.solid_angle[..., None]).reshape(-1, len(LAM)).sum(0)
        t = sun_transmittance(atm, atm.bottom_radius, sun[None])[0]
        np.testing.assert_allclose(flux, (atm.solar_irradiance * t).numpy(), rtol=2e-4)


def test_sun_transmittance_against_scipy_quad(atm):
    """T to space along a ray at 60 and 89 deg: scipy quad of the three density profiles in float64 (independent)."""
    from scipy.integrate import quad

    R, top = atm.bottom_radius, atm.top_radius
    hr, hm = float(atm.rayleigh_scale_height), float(atm.mie_scale_height)
    lo, peak, hi = atm.ozone_layer_m
    tent = lambda h: max(0.0, min((h - lo) / (peak - lo), (hi - h) / (hi - peak)))  # noqa: E731
    for zen in (60.0, 89.0):
        mu = math.cos(math.radians(zen))
        d_top = -R * mu + math.sqrt(R * R * (mu * mu - 1) + top * top)
        h = lambda s: math.sqrt(s * s + 2 * R * mu * s + R * R) - R  # noqa: E731
        col = [quad(lambda s: math.exp(-h(s) / hr), 0, d_top, epsrel=1e-12, limit=200)[0],
               quad(lambda s: math.exp(-h(s) / hm), 0, d_top, epsrel=1e-12, limit=200)[0],
               quad(lambda s: tent(h(s)), 0, d_top, epsrel=1e-12, limit=200, points=[1e4, 4e4, 1e5, 3e5])[0]]
        ext = np.stack([atm.rayleigh_scattering.numpy(), atm.mie_extinction.numpy(), atm.ozone_absorption.numpy()])
        ref = np.exp(-np.asarray(col) @ ext)
        z = math.radians(zen)
        got = sun_transmittance(atm, R, torch.tensor([[0.0, math.sin(z), math.cos(z)]], dtype=torch.float64))[0].numpy()
        np.testing.assert_allclose(got, ref, rtol=2e-4)


# -- energy ----------------------------------------------------------------------------------------
def _fisheye_irradiance(atm, fn, size):
    """Integral of L cos over the upper hemisphere from an equidistant fisheye: dOmega = sin(t) / (f^2 t) per pixel."""
    cam = FisheyeCamera(size)
    vec, valid = cam.pixel_vectors(torch.float64)
    v = vec[valid]
    rgb = xyz_to_linear_srgb(spectral_to_xyz(fn(v), atm.wavelengths))
    th = torch.acos(v[:, 2].clamp(-1, 1))
    f = float(cam.r90) / (math.pi / 2)
    om = torch.where(th > 0, torch.sin(th) / (f * f * th), torch.full_like(th, 1 / (f * f)))
    return (rgb * (v[:, 2].clamp_min(0) * om)[:, None]).sum(0).numpy()


# Measured (docs/envmap.md): relative difference to the fisheye's integral (256 px), sun 30 deg / 75 deg:
# latlong H = 64: +0.11 % / +0.16 %; cubemap N = 32: +0.15 % / +0.21 %; midpoint rule, O(h^2).
@pytest.mark.parametrize("sun_zenith", [30.0, 75.0])
def test_hemisphere_energy_matches_the_fisheye_render(atm, tables, sun_zenith):
    sun = skyfit.sun_vector((sun_zenith, 135.0))
    fn = lambda d: render_vectors(atm, d, sun, make_integrator("gauss"), orders=2, tables=tables)  # noqa: E731
    ref = _fisheye_irradiance(atm, fn, 256)
    for layout, size in (("latlong", 64), ("cubemap", 32)):
        env = render_envmap(atm, sun, fn, size=size, layout=layout)
        rel = env.irradiance() / ref - 1
        print(layout, sun_zenith, rel)
        assert np.all(np.abs(rel) < 3e-3), (layout, rel)
    # The disc adds E_sun T cos(sun zenith) to the horizontal irradiance, up to the cosine of the pixel
    # centre that holds it: |d cos| / cos <= tan(zenith) (pi / H) / 2 = 0.09 % at 30 deg, 0.46 % at 75 deg, H = 1024.
    env_sun = render_envmap(atm, sun, _dark, size=1024, sun_disk=True)
    t = sun_transmittance(atm, atm.bottom_radius, sun[None])[0]
    direct = (atm.solar_irradiance * t * float(sun[2])).numpy()
    bound = math.tan(math.radians(sun_zenith)) * math.pi / 1024 / 2
    np.testing.assert_allclose(env_sun.irradiance(env_sun.spectral), direct, rtol=bound + 2e-4)


# -- files and the command line ---------------------------------------------------------------------
def test_exr_and_hdr_files(atm, tmp_path):
    sun = skyfit.sun_vector((40.0, 200.0))
    fn = lambda d: render_vectors(atm, d, sun, make_integrator("gauss"), orders=1, view_samples=8)  # noqa: E731
    env = render_envmap(atm, sun, fn, size=16, sun_disk=True)
    exr, png = write_envmap(env, tmp_path / "sky.exr", preview=True)
    ch, meta = read_exr(exr)
    assert ch["R"].shape == (16, 32) and {"L440", "L550", "L680", "Y"} <= set(ch)
    np.testing.assert_allclose(np.stack([ch[c] for c in "RGB"], -1), env.rgb, rtol=1e-6)
    assert meta["layout"] == "latlong" and "row 0 straight up" in meta["conventions"]["latlong"]
    assert png.suffix == ".png" and png.stat().st_size > 0
    (hdr,) = write_envmap(env, tmp_path / "sky.hdr")
    img, _ = read_hdr(hdr)
    # RGBE keeps 8 mantissa bits of the largest channel of each pixel
    assert np.all(np.abs(img - env.rgb) <= env.rgb.max(-1, keepdims=True) / 128 + 1e-30)
    cube = render_envmap(atm, sun, fn, size=8, layout="cubemap")
    (p,) = write_envmap(cube, tmp_path / "cube.exr")
    ch, meta = read_exr(p)
    assert ch["G"].shape == (8, 48) and meta["faces"] == ["+X", "-X", "+Y", "-Y", "+Z", "-Z"]
    np.testing.assert_allclose(ch["G"][:, 16:24], cube.rgb[2, ..., 1], rtol=1e-6)  # the +Y (Up) face third


def _result(path: Path, version: int = 1) -> Path:
    cfg = load_yaml(Path(__file__).resolve().parents[1] / "skyfit" / "configs" / "earth.yaml")
    res = {"skyfit_result": version, "parameters": {"mie_g": 0.7}, "free": ["mie_g"], "integrator": {"name": "taylor"},
           "config": cfg, "model": {"wavelengths_nm": LAM, "orders": 1}}
    path.write_text(json.dumps(res))
    return path


def test_cli_envmap_from_a_result_with_time_and_place(tmp_path, capsys):
    res = _result(tmp_path / "RESULT.json")
    when, loc = "2013-05-27T16:00:00-04:00", "42.443449,-76.481962,250"
    out = tmp_path / "sky.exr"
    rc, o, e = run(["envmap", res, "--out", out, "--time", when, "--location", loc, "--size", 32, "--orders", 1,
                    "--sun-disk", "--preview", "--json"], capsys)
    assert rc == 0, e
    info = json.loads(o)
    assert info["shape"] == [32, 64] and (tmp_path / "sky.png").is_file()
    ch, meta = read_exr(out)
    assert meta["sun"]["time"].startswith("2013-05-27T16:00:00") and meta["atmosphere"]["mie_g"] == pytest.approx(0.7)
    sp = sun_position(when, 42.443449, -76.481962, 250.0)
    row, col = latlong_pixel(float(sp.zenith_geometric), float(sp.azimuth), 32)
    k = np.unravel_index(np.argmax(ch["Y"]), ch["Y"].shape)
    assert abs(k[0] - row) <= 1 and abs(k[1] - col) <= 1
    assert info["horizontal_illuminance_lux"] > 1e4  # a sunny afternoon


def _fails(argv, capsys, match, tmp_path):
    before = sorted(p.name for p in tmp_path.rglob("*"))
    rc, _, err = run(argv, capsys)
    assert rc == 2 and err.count("\n") == 1 and match in err, err
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing written, no preview, no temporaries


def test_cli_envmap_bad_input(tmp_path, capsys):
    out = tmp_path / "sky.exr"
    sun = ["--sun-zenith", 50, "--orders", 1, "--preview"]
    _fails(["envmap", "earth", "--out", out, "--size", 0, *sun], capsys, "--size", tmp_path)
    _fails(["envmap", "earth", "--out", out, "--size", 33, *sun], capsys, "even", tmp_path)
    _fails(["envmap", "earth", "--out", out, "--format", "sphere", *sun], capsys, "invalid choice", tmp_path)
    _fails(["envmap", "earth", "--out", tmp_path / "sky.png", *sun], capsys, ".exr or .hdr", tmp_path)
    _fails(["envmap", "earth", "--out", tmp_path / "sky.hdr", "--spectral", *sun], capsys, "spectral", tmp_path)
    _fails(["envmap", "earth", "--out", out, "--orders", 1], capsys, "--sun-zenith", tmp_path)
    _fails(["envmap", "earth", "--out", out, "--table-sizes", "4,7,4,2", "--sun-zenith", 50], capsys, "scattering_mu", tmp_path)
    _fails(["envmap", "nowhere.yaml", "--out", out, *sun], capsys, "nowhere", tmp_path)
    future = _result(tmp_path / "future.json", version=2)
    _fails(["envmap", future, "--out", out, *sun], capsys, "version 2", tmp_path)
    _fails(["envmap", tmp_path / "missing.json", "--out", out, *sun], capsys, "not found", tmp_path)


def test_python_envmap_of_a_fit_result(tmp_path):
    fr = skyfit.load_result(_result(tmp_path / "RESULT.json"))
    env = skyfit.envmap(fr, (45.0, 90.0), size=8, orders=1)
    assert env.rgb.shape == (8, 16, 3) and env.meta["atmosphere"]["mie_g"] == pytest.approx(0.7)
    assert np.all(env.rgb[:4] > 0)  # the sky above the horizon is lit


def test_version(capsys):
    from importlib.metadata import version

    rc, out, _ = run(["--version"], capsys)
    assert rc == 0 and out.strip() == f"skyfit {skyfit.__version__}" == f"skyfit {version('skyfit')}"


def test_the_default_bruneton_envmap_is_built_for_its_sun_and_matches_tables_built_so(tmp_path):
    """skyfit.envmap's default renderer (Bruneton orders) builds its tables for the map's one sun (SkyModel.sun_window:
    the mu_s axis over the sun's zenith angle +- 5 deg): the map equals one rendered from tables precomputed so, says
    so in its header, and differs from 2017's axis where that axis is coarse (a hazy sky, the sun at 30 deg)."""
    import dataclasses
    import math

    import torch

    from skyfit.api import render_model
    from skyfit.scattering.bruneton_tables import TableSizes
    from skyfit.scattering.multiple import precompute

    wl = [450.0, 550.0, 650.0]
    a = skyfit.load_atmosphere("earth", wl)
    ext = 0.3 / 1200.0 * (torch.tensor(wl, dtype=torch.float64) / 550.0) ** -1.3
    atm = a.replace(mie_extinction=ext, mie_scattering=0.9 * ext, mie_g=torch.tensor(0.82, dtype=torch.float64))
    small = (64, 16, 16, 4, 4, 16, 4, 8)
    env = skyfit.envmap(atm, (30.0, 90.0), size=8, table_sizes=",".join(map(str, small[4:])), spectral=True)
    assert env.meta["renderer"]["sun_window"] is True
    model = dataclasses.replace(render_model(None, 4, "bruneton"), table_sizes=dataclasses.astuple(TableSizes())[:4] + small[4:])
    sizes = TableSizes(*model.table_sizes)
    one_sun = precompute(atm, orders=4, sizes=dataclasses.replace(sizes, scattering_mu_s=6), progress=False,
                         mu_s_range=(math.cos(math.radians(35.0)), math.cos(math.radians(25.0))), quadrature=model.quadrature())
    same = skyfit.envmap(atm, (30.0, 90.0), size=8, model=model, tables=one_sun, spectral=True)
    np.testing.assert_allclose(env.spectral, same.spectral, rtol=1e-12, atol=0.0)
    whole = skyfit.envmap(atm, (30.0, 90.0), size=8, model=model, tables=model.tables(atm), spectral=True)
    assert np.abs(whole.spectral[:4] / env.spectral[:4] - 1.0).max() > 0.05  # 2017's 4 texels over the whole axis


def test_skyfit_render_orders_is_the_python_render_with_its_sun_tables(tmp_path, capsys):
    """``skyfit render --orders N`` (Bruneton) renders what ``skyfit.render(..., orders=N)`` does: tables for the one
    sun (mu_s window, Gauss view rays, split density bands), at --table-sizes where given (to the EXR's float32); before,
    the CLI used 2017's mu_s axis and trapezoid rays, over 5 % off on a hazy sky with the sun at 30 deg."""
    import dataclasses

    from skyfit.api import render_model
    from skyfit.io import read_exr

    wl, small = [450.0, 550.0, 650.0], (4, 16, 8, 8)
    out = tmp_path / "sky.exr"
    rc, _, err = run(["render", "earth_hazy", "--out", out, "--size", 8, "--sun-zenith", 30, "--sun-azimuth", 90,
                      "--orders", 4, "--table-sizes", ",".join(map(str, small)), "--wavelengths", "450,550,650",
                      "--spectral", "--dtype", "float64"], capsys)
    assert rc == 0, err
    chans, meta = read_exr(out)
    tables = meta["multiple_tables"]  # the header says which tables: the sun's 30 deg +- 5 in 6 texels, Gauss rays
    np.testing.assert_allclose(tables["mu_s_range"], [math.cos(math.radians(35.0)), math.cos(math.radians(25.0))], rtol=1e-12)
    assert tables["table_sizes"][4:] == [4, 16, 6, 8] and tables["ray_rule"] == "gauss"
    atm = load_atmosphere("earth_hazy", wl)
    model = render_model(None, 4, "bruneton")
    model = dataclasses.replace(model, table_sizes=model.table_sizes[:4] + small)
    sky = skyfit.render(atm, FisheyeCamera(8, projection="equidistant"), (30.0, 90.0), model=model)
    got = np.stack([chans[f"L{v:g}"] for v in wl], -1)
    np.testing.assert_allclose(got, sky.radiance.numpy(), rtol=1e-6, atol=0.0)  # the EXR holds float32
    old = skyfit.render(atm, FisheyeCamera(8, projection="equidistant"), (30.0, 90.0),
                        model=dataclasses.replace(model, sun_window=False, ray_rule="trapezoid", density_directions=(16, 32)))
    v = sky.valid.numpy()
    assert np.abs(old.radiance.numpy()[v] / got[v] - 1.0).max() > 0.05


def test_skyfit_render_orders_with_the_sun_below_the_tables_is_one_line_in_the_clis_terms(tmp_path, capsys):
    """A sun lower than Bruneton's tables reach (mu_s_min -0.2: 101.5 deg) is one line, exit 2, no file, naming the
    flags that render it (the library's message names Python arguments); the library still raises its ValueError;
    --multiple hillaire renders it."""
    from skyfit.scattering.multiple import SunBelowTables

    assert issubclass(SunBelowTables, ValueError)
    out = tmp_path / "sky.exr"
    rc, _, err = run(["render", "earth", "--out", out, "--size", 8, "--sun-zenith", 120, "--orders", 2,
                      "--table-sizes", "4,16,8,4", "--wavelengths", "550"], capsys)
    assert rc == 2 and not out.exists()
    line = err.strip()
    assert "\n" not in line and "--sun-zenith 120" in line and "101.5 deg" in line and "--orders 1" in line, line
    assert "below_mu_s_min" not in line
    rc, _, err = run(["render", "earth", "--out", out, "--size", 8, "--sun-zenith", 120, "--orders", 2,
                      "--multiple", "hillaire", "--wavelengths", "550"], capsys)
    assert rc == 0 and out.exists(), err

"""skyfit.camera.icc and the photos that embed a profile (Display P3 phones, Adobe RGB cameras).

References are independent of the parser under test: LittleCMS (through Pillow's ImageCms) reads the same bytes and
converts pixels; the tone curves' closed forms of ICC.1:2022 Table 68 and IEC 61966-2-1 are written here in numpy;
the colour spaces' primaries come from colour-science.
"""
from __future__ import annotations

import io
import types

import colour
import numpy as np
import pytest
import tifffile
import torch
from PIL import Image, ImageCms

from _files import exif_colour_space, png16
from test_photo_read import srgb_dec, srgb_enc  # IEC 61966-2-1 in numpy

from skyfit.camera.icc import (Curve, IccError, build_icc, icc_sensitivities, parse_icc, profile_for,
                               srgb_colorants)
from skyfit.camera.sensor import spectral_response_matrix
from skyfit.fit.model import channel_matrix
from skyfit.io.photo import read_photo


def lcms(data: bytes):
    return ImageCms.ImageCmsProfile(io.BytesIO(data))


def test_littlecms_srgb_profile_is_srgb():
    data = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    prof = parse_icc(data)
    assert prof.is_srgb() and not prof.grey
    c = np.linspace(0, 1, 257)
    np.testing.assert_allclose(prof.decode(np.stack([c] * 3, -1)), np.stack([srgb_dec(c)] * 3, -1), atol=2e-5)
    p = lcms(data).profile
    theirs = np.array([p.red_colorant[0], p.green_colorant[0], p.blue_colorant[0]]).T
    np.testing.assert_allclose(prof.colorants, theirs, atol=1e-6)
    np.testing.assert_allclose(srgb_colorants(), theirs, atol=2e-4)


@pytest.mark.parametrize("space", ["Display P3", "Adobe RGB (1998)"])
def test_profile_reads_as_littlecms_converts(space):
    data = profile_for(space)
    prof = parse_icc(data)
    assert prof.description == space and not prof.is_srgb()
    assert ImageCms.getProfileDescription(lcms(data)).strip() == space
    rng = np.random.default_rng(0)
    px = rng.integers(20, 236, (1, 2000, 3)).astype(np.uint8)
    out = ImageCms.profileToProfile(Image.fromarray(px), lcms(data), ImageCms.createProfile("sRGB"), renderingIntent=1)
    theirs = np.asarray(out, np.float64)[0]
    # ours: the profile's curves, its primaries to XYZ (D65 relative), sRGB's matrix, sRGB's curve
    xyz = prof.decode(px[0] / 255.0) @ np.linalg.inv(prof.rgb_from_xyz()).T
    cs = colour.RGB_COLOURSPACES["sRGB"]
    lin = xyz @ np.linalg.inv(colour.normalised_primary_matrix(cs.primaries, cs.whitepoint)).T
    inside = ((lin > 1e-3) & (lin < 0.999)).all(-1)
    assert inside.sum() > 800
    np.testing.assert_allclose(srgb_enc(lin[inside]) * 255, theirs[inside], atol=0.8)  # LittleCMS rounds to codes


def test_primaries_match_colour_science():
    for space in ("Display P3", "Adobe RGB (1998)", "sRGB"):
        cs = colour.RGB_COLOURSPACES[space]
        npm = colour.normalised_primary_matrix(cs.primaries, cs.whitepoint)
        # both whites are D65: XYZ -> the space's linear RGB is the inverse of its primary matrix
        np.testing.assert_allclose(parse_icc(profile_for(space)).rgb_from_xyz(), np.linalg.inv(npm), atol=2e-4)


@pytest.mark.parametrize("params, closed", [
    ((0, 2.2, 0, 0, 0, 0, 0, 0), lambda x: x ** 2.2),
    ((1, 2.0, 1.25, -0.25, 0, 0, 0, 0), lambda x: np.where(x >= 0.2, (1.25 * x - 0.25) ** 2.0, 0.0)),
    ((2, 2.0, 1.25, -0.25, 0.05, 0, 0, 0), lambda x: np.where(x >= 0.2, (1.25 * x - 0.25) ** 2.0 + 0.05, 0.05)),
    ((3, 2.4, 1 / 1.055, 0.055 / 1.055, 1 / 12.92, 0.04045, 0, 0), srgb_dec),
    ((4, 2.0, 0.9, 0.1, 0.5, 0.3, 0.02, 0.01), lambda x: np.where(x >= 0.3, (0.9 * x + 0.1) ** 2 + 0.02, 0.5 * x + 0.01)),
])
def test_parametric_curves_against_table_68(params, closed):
    prof = parse_icc(build_icc("t", Curve("parametric", params), None))
    x = np.linspace(0.005, 0.995, 100)  # not on a break point, which the parameters' rounding moves
    np.testing.assert_allclose(prof.decode(x), closed(x), atol=3e-5)  # s15Fixed16 rounding of the parameters


def test_curv_tables_gamma_and_identity():
    x = np.linspace(0, 1, 101)
    tab = np.linspace(0, 1, 7) ** 3
    assert np.allclose(parse_icc(build_icc("t", Curve("table", table=tuple(tab)), None)).decode(x),
                       np.interp(x, np.linspace(0, 1, 7), tab), atol=2e-5)
    g = parse_icc(build_icc("t", Curve("gamma", (2.2,)), None)).curves[0]
    assert g.gamma == 563 / 256  # u8Fixed8
    assert np.array_equal(parse_icc(build_icc("t", Curve("identity"), None)).decode(x), x)


def test_bad_and_unsupported_profiles():
    with pytest.raises(IccError, match="not an ICC profile"):
        parse_icc(b"\0" * 200)
    good = profile_for("Display P3")
    with pytest.raises(IccError, match="runs past the end"):
        parse_icc(good[:200])
    assert parse_icc(ImageCms.ImageCmsProfile(ImageCms.createProfile("LAB")).tobytes()) is None


def test_icc_sensitivities_render_the_space():
    wl = torch.tensor([420.0, 470.0, 530.0, 600.0, 650.0], dtype=torch.float64)
    obs = types.SimpleNamespace(kind="rgb", metadata={})  # what channel_matrix reads of an RGB observation
    default = channel_matrix(wl, obs)  # the CIE observer through sRGB's matrix
    cs = colour.RGB_COLOURSPACES["sRGB"]
    to_srgb = colour.normalised_primary_matrix(cs.primaries, cs.whitepoint)
    for space in ("sRGB", "Display P3"):
        m = parse_icc(profile_for(space)).rgb_from_xyz()
        w, s = icc_sensitivities(m)
        got = spectral_response_matrix(wl, torch.as_tensor(s), torch.as_tensor(w))
        np.testing.assert_allclose(got.numpy(), default.numpy() @ (m @ to_srgb).T, rtol=1e-9, atol=1e-12)


def _p3_codes(lin_srgb):
    cs = colour.RGB_COLOURSPACES["Display P3"]
    rgb = colour.RGB_to_RGB(lin_srgb, colour.RGB_COLOURSPACES["sRGB"], cs, chromatic_adaptation_transform=None)
    return cs.cctf_encoding(np.clip(rgb, 0, 1))


def test_read_photo_uses_the_profile(tmp_path):
    rng = np.random.default_rng(3)
    lin = rng.uniform(0.05, 0.8, (8, 10, 3))
    codes = np.round(_p3_codes(lin) * 255).astype(np.uint8)
    Image.fromarray(codes).save(tmp_path / "p3.png", icc_profile=profile_for("Display P3"))
    Image.fromarray(codes).save(tmp_path / "plain.png")
    ph, plain = read_photo(tmp_path / "p3.png"), read_photo(tmp_path / "plain.png")
    icc = ph.meta["icc"]
    assert icc["description"] == "Display P3" and not icc["srgb"] and ph.meta["response_source"] == "icc"
    assert any("Display P3" in n for n in ph.meta["notes"]) and "icc" not in plain.meta
    # P3's curve is sRGB's: the same linear values; the colour comes from its primaries in the fit
    np.testing.assert_allclose(ph.rgb, plain.rgb, rtol=1e-12)
    p3_lin = srgb_dec(codes / 255.0)
    xyz_from_p3 = np.linalg.inv(np.asarray(icc["rgb_from_xyz"]))
    cs = colour.RGB_COLOURSPACES["sRGB"]
    back = p3_lin @ xyz_from_p3.T @ np.linalg.inv(colour.normalised_primary_matrix(cs.primaries, cs.whitepoint)).T
    np.testing.assert_allclose(back, lin, atol=0.01)  # 8-bit codes


def test_adobe_rgb_16bit_png_and_tiff_decode_with_its_gamma(tmp_path):
    codes = np.random.default_rng(4).integers(700, 64000, (6, 7, 3)).astype(np.uint16)
    png16(tmp_path / "a.png", codes, icc=profile_for("Adobe RGB (1998)"))
    tifffile.imwrite(tmp_path / "a.tif", codes, photometric="rgb", iccprofile=profile_for("Adobe RGB (1998)"))
    for name in ("a.png", "a.tif"):
        ph = read_photo(tmp_path / name)
        assert ph.meta["response"] == "gamma:2.2" and ph.meta["icc"]["description"] == "Adobe RGB (1998)"
        np.testing.assert_allclose(ph.rgb, (codes / 65535.0) ** (563 / 256), rtol=1e-12)


def test_grey_profile_and_mismatched_profile(tmp_path):
    grey = np.random.default_rng(5).integers(10, 240, (6, 7)).astype(np.uint8)
    Image.fromarray(grey, mode="L").save(tmp_path / "g.png", icc_profile=build_icc("Gray Gamma 1.8", Curve("gamma", (1.8,)), None))
    ph = read_photo(tmp_path / "g.png")
    assert ph.meta["monochrome"] and ph.meta["icc"]["rgb_from_xyz"] is None
    np.testing.assert_allclose(ph.rgb[..., 0], (grey / 255.0) ** (461 / 256), rtol=1e-12)
    # a colour profile on a grey image is not used, and the note says why
    Image.fromarray(grey, mode="L").save(tmp_path / "x.png", icc_profile=profile_for("Display P3"))
    ph = read_photo(tmp_path / "x.png")
    assert "icc" not in ph.meta and ph.meta["response"] == "srgb"
    assert any("for colour images" in n for n in ph.meta["notes"])
    Image.fromarray(grey, mode="L").save(tmp_path / "y.png", icc_profile=b"garbage" * 30)
    assert any("cannot be read" in n for n in read_photo(tmp_path / "y.png").meta["notes"])


def test_a_given_response_wins_over_the_profile(tmp_path):
    codes = np.random.default_rng(6).integers(10, 240, (6, 7, 3)).astype(np.uint8)
    Image.fromarray(codes).save(tmp_path / "a.jpg", quality=95, icc_profile=profile_for("Adobe RGB (1998)"))
    ph = read_photo(tmp_path / "a.jpg", response="srgb")
    assert ph.meta["response"] == "srgb" and ph.meta["response_source"] == "given"
    assert ph.meta["icc"]["rgb_from_xyz"] is not None  # the primaries still give the colour


def test_a_cameras_srgb_profile_with_a_curve_table_is_srgb():
    # the classic "sRGB IEC61966-2.1" profile cameras embed: a 1024-entry curv table and 4-digit colorants
    table = tuple(srgb_dec(np.linspace(0, 1, 1024)).tolist())
    colorants = np.array([[0.4361, 0.3851, 0.1431], [0.2225, 0.7169, 0.0606], [0.0139, 0.0971, 0.7141]])
    prof = parse_icc(build_icc("sRGB IEC61966-2.1", Curve("table", table=table), colorants))
    assert prof.is_srgb()
    # a gamma-2.2 profile on sRGB's primaries is not
    assert not parse_icc(build_icc("sRGB-ish", Curve("gamma", (2.2,)), colorants)).is_srgb()


def test_a_bracket_in_adobe_rgb_decodes_with_its_power_law(tmp_path):
    yy, xx = np.mgrid[0:40, 0:50]
    lin = np.stack([0.02 + 0.2 * xx / 50, 0.03 + 0.2 * yy / 40, 0.1 + 0.0 * xx], -1)
    g = 563 / 256
    for k, t in enumerate((1.0, 2.0, 4.0)):
        codes = np.round(np.clip(lin * t, 0, 1) ** (1 / g) * 255).astype(np.uint8)
        Image.fromarray(codes).save(tmp_path / f"f{k}.png", icc_profile=profile_for("Adobe RGB (1998)"))
    ph = read_photo(tmp_path, exposures=[1.0, 2.0, 4.0])
    assert ph.meta["response"] == "gamma:2.2" and ph.meta["response_source"] == "icc"
    e = ph.meta["frames"][0]["relative_exposure"]
    np.testing.assert_allclose(ph.rgb * e, lin, rtol=0.02)  # 8-bit codes, merged
    # asked to, the bracket still estimates its own curve
    assert read_photo(tmp_path, exposures=[1.0, 2.0, 4.0], response="estimate").meta["response_source"] == "estimated"


def test_adobe_rgb_declared_by_exif_alone(tmp_path):
    """A Canon in Adobe RGB mode embeds no profile: ColorSpace uncalibrated + interoperability R03 (or a DCF option
    file name "_MG_...") declares it. The codes decode exactly as with the embedded Adobe RGB profile."""
    codes = np.random.default_rng(8).integers(10, 240, (6, 7, 3)).astype(np.uint8)
    Image.fromarray(codes).save(tmp_path / "icc.jpg", quality=95, icc_profile=profile_for("Adobe RGB (1998)"))
    Image.fromarray(codes).save(tmp_path / "r03.jpg", quality=95, exif=exif_colour_space(0xFFFF, "R03"))
    Image.fromarray(codes).save(tmp_path / "_MG_0001.jpg", quality=95, exif=exif_colour_space(0xFFFF))
    Image.fromarray(codes).save(tmp_path / "unknown.jpg", quality=95, exif=exif_colour_space(0xFFFF))
    Image.fromarray(codes).save(tmp_path / "srgb.jpg", quality=95, exif=exif_colour_space(1, "R98"))
    ref = read_photo(tmp_path / "icc.jpg")
    for name, why in (("r03.jpg", "interoperability index R03"), ("_MG_0001.jpg", "DCF option file name")):
        ph = read_photo(tmp_path / name)
        assert ph.meta["response"] == "gamma:2.2" and ph.meta["response_source"] == "icc"
        assert ph.meta["icc"]["source"] == "exif" and ref.meta["icc"]["source"] == "embedded"
        np.testing.assert_array_equal(ph.rgb, ref.rgb)
        np.testing.assert_allclose(ph.meta["icc"]["rgb_from_xyz"], ref.meta["icc"]["rgb_from_xyz"], rtol=1e-12)
        assert any(why in n and "Adobe RGB" in n for n in ph.meta["notes"])
    plain = read_photo(tmp_path / "srgb.jpg")
    assert "icc" not in plain.meta and plain.meta["response"] == "srgb" and not plain.meta["notes"]
    np.testing.assert_allclose(plain.rgb, srgb_dec(np.asarray(Image.open(tmp_path / "srgb.jpg")) / 255.0), rtol=1e-12)
    # uncalibrated with nothing else: the space is unknown, read as sRGB, and the note says so
    un = read_photo(tmp_path / "unknown.jpg")
    assert "icc" not in un.meta and un.meta["response"] == "srgb"
    assert any("'uncalibrated'" in n for n in un.meta["notes"])
    np.testing.assert_allclose(un.rgb, srgb_dec(np.asarray(Image.open(tmp_path / "unknown.jpg")) / 255.0), rtol=1e-12)
    # a bracket of such frames takes the power law too
    (tmp_path / "b").mkdir()
    for k in range(3):
        Image.fromarray(np.clip(codes.astype(int) + 10 * k, 0, 255).astype(np.uint8)).save(
            tmp_path / "b" / f"f{k}.jpg", quality=95, exif=exif_colour_space(0xFFFF, "R03"))
    b = read_photo(tmp_path / "b", exposures=[1.0, 1.2, 1.4])
    assert b.meta["response_source"] == "icc" and b.meta["icc"]["source"] == "exif"
    # an embedded profile wins over the EXIF declaration
    Image.fromarray(codes).save(tmp_path / "both.jpg", quality=95, exif=exif_colour_space(0xFFFF, "R03"),
                                icc_profile=profile_for("Display P3"))
    assert read_photo(tmp_path / "both.jpg").meta["icc"]["description"] == "Display P3"

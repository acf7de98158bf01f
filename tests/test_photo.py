"""Photos as data: sRGB decoding, LDR loading, censored likelihood, exposure scale, synthetic photos.

Expected values come from closed forms (the camera noise model written out in
the test, Sheppard's 1/12 DN^2 for rounding, cos^4 and polynomial falloff from
pixel coordinates), colour-science (sRGB curve), scipy.stats (normal tails)
and torch.distributions.Normal, never from outputs of skyfit.camera (srgb, photo_io, likelihood, sensor).
Random tests use fixed seeds and 5-sigma bounds from the sampling distribution.
"""
from __future__ import annotations

import math

import colour
import numpy as np
import pytest
import scipy.stats
import skimage.io
import torch
from torch.testing import assert_close

from _files import png16

from skyfit.camera import FisheyeCamera
from skyfit.camera.likelihood import censored_gaussian_nll, fit_exposure_scale
from skyfit.camera.photo_io import load_ldr_photo, read_png16
from skyfit.camera.sensor import spectral_response_matrix, synthesize_photo, vignetting_map
from skyfit.camera.srgb import srgb_decode, srgb_encode
from skyfit.render import spectral_to_xyz, spectral_to_xyz_matrix, xyz_to_linear_srgb

F64 = torch.float64
WL = torch.linspace(400.0, 700.0, 7, dtype=F64)


def _flat(h: int, w: int, level: float = 1e-2) -> torch.Tensor:
    """Equal-energy spectrum (all sRGB channels > 0), shape (h, w, 7). [W/(m^2 sr nm)]"""
    return torch.full((h, w, WL.numel()), level, dtype=F64)


def _srgb_of(spectral: torch.Tensor) -> torch.Tensor:
    """Camera signal of the default path, from skyfit.render (tested against colour-science in test_colour.py)."""
    return xyz_to_linear_srgb(spectral_to_xyz(spectral, WL))


# ---------------------------------------------------------------- sRGB curve


@pytest.mark.parametrize("dtype, atol", [(torch.float64, 1e-12), (torch.float32, 5e-7)])  # float32: ~4 ulp at 1
def test_srgb_decode_equals_colour_on_every_code(dtype, atol):
    for bits in (8, 16):
        codes = np.arange(2**bits) / (2**bits - 1)
        ref = colour.cctf_decoding(codes, function="sRGB")
        assert_close(srgb_decode(torch.tensor(codes, dtype=dtype)), torch.tensor(ref, dtype=dtype), atol=atol, rtol=0)
        assert_close(srgb_encode(torch.tensor(ref, dtype=dtype)), torch.tensor(codes, dtype=dtype), atol=10 * atol, rtol=0)


def test_srgb_round_trip_within_8bit_quantisation():
    # encode with colour-science, quantise to 8 bits, decode with ours: in the encoded
    # domain the error is the rounding, at most half a code.
    x = np.concatenate([np.linspace(0, 0.01, 500), np.geomspace(1e-4, 1.0, 2000)])
    codes = np.round(255 * colour.cctf_encoding(x, function="sRGB"))
    lin = srgb_decode(torch.tensor(codes / 255, dtype=F64)).numpy()
    err = np.abs(colour.cctf_encoding(lin, function="sRGB") - colour.cctf_encoding(x, function="sRGB"))
    assert err.max() <= 0.5 / 255 + 1e-12


def test_srgb_decode_gradcheck_across_the_break():
    v = torch.tensor([0.0, 0.01, 0.04045 - 1e-4, 0.04045 + 1e-4, 0.5, 1.0], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(srgb_decode, (v[1:],))
    srgb_decode(v).sum().backward()
    assert torch.isfinite(v.grad).all()


# ---------------------------------------------------------------- LDR files


@pytest.mark.parametrize("bits, ext", [(8, "png"), (16, "tif")])
def test_load_round_trip_and_censoring(tmp_path, bits, ext):
    rng = np.random.default_rng(bits)
    top = 2**bits - 1
    codes = rng.integers(0, top + 1, size=(24, 20, 3))
    codes[0, 0] = [top, 10 * (top // 255), 5 * (top // 255)]  # saturated red
    codes[0, 1] = [0, 100 * (top // 255), 100 * (top // 255)]  # black red
    codes[0, 2] = [254 * top // 255, 253 * top // 255, 3 * top // 255]  # at the default clip level
    arr = codes.astype(np.uint8 if bits == 8 else np.uint16)
    path = tmp_path / f"sky{bits}.{ext}"
    skimage.io.imsave(path, arr, check_contrast=False)
    obs = load_ldr_photo(path)
    assert obs.bit_depth == bits and obs.exposure_unknown and obs.path == str(path)
    assert_close(obs.rgb, torch.tensor(colour.cctf_decoding(codes / top, function="sRGB"), dtype=F64), atol=1e-12, rtol=0)
    enc = codes / top
    high = enc >= 254 / 255 - 1e-12
    low = enc <= 1 / 255 + 1e-12
    assert torch.equal(obs.censored_high, torch.tensor(high))
    assert torch.equal(obs.censored_low, torch.tensor(low))
    assert torch.equal(obs.censored, torch.tensor((high | low).any(-1)))
    assert obs.censored[0, 0] and obs.censored[0, 1] and obs.censored[0, 2]
    assert obs.clip_high == pytest.approx(colour.cctf_decoding(254 / 255, function="sRGB"), abs=1e-15)
    # a stricter clip level flags fewer pixels; float32 follows the dtype argument
    obs2 = load_ldr_photo(path, clip_level=1.0, dtype=torch.float32)
    assert obs2.rgb.dtype == torch.float32 and not obs2.censored_high[0, 2, 0] and obs2.censored_high[0, 0, 0]


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_16bit_png_is_read_at_full_depth(tmp_path, channels):
    # Pillow (13.0) decodes 16-bit RGB PNG to 8 bits; pypng reads every colour type at 16 bits
    codes = np.random.default_rng(channels).integers(0, 65536, size=(6, 5, channels)).astype(np.uint16)
    if channels in (2, 4):
        codes[..., -1] = 65535
        codes[0, 0, -1] = 0  # one transparent pixel: not valid
    png16(tmp_path / "sky16.png", codes)
    arr = read_png16(str(tmp_path / "sky16.png"))
    assert arr.dtype == np.uint16 and np.array_equal(arr, codes[..., 0] if channels == 1 else codes)
    if channels >= 3:
        obs = load_ldr_photo(tmp_path / "sky16.png")
        assert obs.bit_depth == 16
        assert_close(obs.rgb, torch.tensor(colour.cctf_decoding(codes[..., :3] / 65535, function="sRGB"), dtype=F64),
                     atol=1e-12, rtol=0)
        assert bool(obs.valid[0, 0]) == (channels == 3)


def test_broken_16bit_png_is_one_line(tmp_path):
    codes = np.zeros((6, 5, 3), np.uint16)
    png16(tmp_path / "cut.png", codes)
    data = (tmp_path / "cut.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[:60])
    with pytest.raises(ValueError, match=r"cut\.png: cannot read the 16-bit PNG") as e:
        load_ldr_photo(tmp_path / "cut.png")
    assert "\n" not in str(e.value)


def test_load_jpeg_and_alpha(tmp_path):
    yy, xx = np.mgrid[0:64, 0:64]
    codes = np.stack([2 * xx + 40, 2 * yy + 40, np.full_like(xx, 128)], -1).astype(np.uint8)  # smooth
    skimage.io.imsave(tmp_path / "sky.jpg", codes, check_contrast=False)  # quality 75
    obs = load_ldr_photo(tmp_path / "sky.jpg")
    back = np.round(255 * colour.cctf_encoding(obs.rgb.numpy(), function="sRGB"))
    assert obs.bit_depth == 8 and np.abs(back - codes).mean() < 1.5  # lossy, but close
    rgba = np.concatenate([codes, np.full((64, 64, 1), 255, np.uint8)], -1)
    rgba[:10, :, 3] = 0
    skimage.io.imsave(tmp_path / "sky.png", rgba, check_contrast=False)
    obs = load_ldr_photo(tmp_path / "sky.png")
    assert not obs.valid[:10].any() and obs.valid[10:].all()


def test_load_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.png"):
        load_ldr_photo(tmp_path / "nope.png")
    skimage.io.imsave(tmp_path / "grey.png", np.zeros((8, 8), np.uint8), check_contrast=False)
    with pytest.raises(ValueError, match=r"grey\.png: expected an RGB"):
        load_ldr_photo(tmp_path / "grey.png")
    (tmp_path / "junk.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="junk.png"):
        load_ldr_photo(tmp_path / "junk.png")
    with pytest.raises(ValueError, match="black_level < clip_level"):
        load_ldr_photo(tmp_path / "grey.png", clip_level=0.0)


# ---------------------------------------------------------------- censored likelihood


def test_censored_nll_is_gaussian_nll_without_censoring():
    g = torch.Generator().manual_seed(3)
    model = torch.rand(50, 3, generator=g, dtype=F64)
    obs = model + 0.1 * torch.randn(50, 3, generator=g, dtype=F64)
    sigma = 0.05 + torch.rand(50, 3, generator=g, dtype=F64) * 0.1
    ref = -torch.distributions.Normal(model, sigma).log_prob(obs)
    none = torch.zeros(50, 3, dtype=torch.bool)
    assert_close(censored_gaussian_nll(model, obs, sigma, none, none, reduction="none"), ref)
    assert_close(censored_gaussian_nll(model, obs, sigma), ref.sum())
    assert_close(censored_gaussian_nll(model, obs, sigma, reduction="mean"), ref.mean())


def test_censored_nll_tails_against_scipy():
    clip, sigma = 1.0, 0.02
    model = torch.tensor([0.2, 0.9, 0.99, 1.0, 1.05, 1.5], dtype=F64)  # down to -40 sigma
    high = torch.ones(6, dtype=torch.bool)
    got = censored_gaussian_nll(model, torch.ones(6, dtype=F64), sigma, high, None, clip_high=clip, reduction="none")
    ref = -scipy.stats.norm.logsf((clip - model.numpy()) / sigma)  # -log P(model + noise >= clip)
    assert_close(got, torch.tensor(ref, dtype=F64), rtol=1e-10, atol=1e-12)
    got = censored_gaussian_nll(model, torch.zeros(6, dtype=F64), sigma, None, high, clip_low=0.95, reduction="none")
    ref = -scipy.stats.norm.logcdf((0.95 - model.numpy()) / sigma)  # -log P(model + noise <= clip)
    assert_close(got, torch.tensor(ref, dtype=F64), rtol=1e-10, atol=1e-12)


def test_censored_nll_gradient_pushes_clipped_pixel_up():
    sigma, clip = 0.01, 1.0
    model = torch.tensor([0.5, 0.98, 1.0, 1.3], dtype=F64, requires_grad=True)
    high = torch.ones(4, dtype=torch.bool)
    censored_gaussian_nll(model, torch.full((4,), clip, dtype=F64), sigma, censored_high=high).backward()
    gr = model.grad
    assert (gr[:3] < 0).all()  # descent raises a clipped pixel modelled below (or at) the clip
    assert abs(gr[0]) > abs(gr[1]) > abs(gr[2])  # and harder the further below: ~ (clip - m)/sigma^2
    assert_close(gr[0], torch.tensor(-(clip - 0.5) / sigma**2, dtype=F64), rtol=1e-3, atol=0)  # Mills ratio asymptote
    assert abs(gr[3]) < 1e-100  # 30 sigma above: no pull
    # a censored-low pixel modelled above its clip is pushed down
    m = torch.tensor([0.1], dtype=F64, requires_grad=True)
    censored_gaussian_nll(m, torch.zeros(1, dtype=F64), sigma, None, torch.ones(1, dtype=torch.bool), clip_low=0.01).backward()
    assert m.grad[0] > 0


def test_censored_nll_gradcheck_and_errors():
    model = torch.tensor([0.2, 0.7, 0.97, 1.2], dtype=F64, requires_grad=True)
    obs = torch.tensor([0.25, 0.6, 1.0, 0.0], dtype=F64)
    high = torch.tensor([False, False, True, False])
    low = torch.tensor([False, False, False, True])
    sigma = torch.tensor(0.05, dtype=F64, requires_grad=True)
    f = lambda m, s: censored_gaussian_nll(m, obs, s, high, low, clip_low=0.01)  # noqa: E731
    assert torch.autograd.gradcheck(f, (model, sigma))
    with pytest.raises(ValueError, match="sigma must be > 0"):
        censored_gaussian_nll(model, obs, 0.0)
    with pytest.raises(ValueError, match="both high and low"):
        censored_gaussian_nll(model, obs, 0.1, high, high)


# ---------------------------------------------------------------- exposure scale


@pytest.mark.parametrize("method", ["linear", "log"])
def test_exposure_scale_exact_on_noiseless_data(method):
    g = torch.Generator().manual_seed(5)
    model = 0.1 + torch.rand(16, 16, 3, generator=g, dtype=F64)
    obs = 3.7 * model
    obs[0, 0] = 1.0  # a clipped pixel, masked out
    mask = torch.ones(16, 16, 1, dtype=torch.bool)
    mask[0, 0] = False
    assert_close(fit_exposure_scale(model, obs, mask, method=method), torch.tensor(3.7, dtype=F64), rtol=1e-12, atol=0)


def test_exposure_scale_within_sampling_error():
    # 400 noisy photos of the same model: the weighted LS estimate is unbiased with
    # variance 1 / sum(m^2 / s^2) (closed form for observed = k m + N(0, s^2)).
    g = torch.Generator().manual_seed(11)
    k, trials = 2.5, 400
    model = 0.05 + torch.rand(500, 3, generator=g, dtype=F64)
    s = 0.02 + 0.05 * model
    obs = k * model + s * torch.randn(trials, 500, 3, generator=g, dtype=F64)
    est = torch.stack([fit_exposure_scale(model, o, weights=1 / s**2) for o in obs])
    sd = float(1 / torch.sqrt((model**2 / s**2).sum()))
    assert abs(float(est.mean()) - k) < 5 * sd / math.sqrt(trials)
    ratio = float(est.var()) / sd**2  # ~ chi2(trials-1)/(trials-1), sd sqrt(2/399) = 0.071
    assert abs(ratio - 1) < 5 * math.sqrt(2 / (trials - 1))


def test_exposure_scale_errors():
    m = torch.ones(4, 3, dtype=F64)
    with pytest.raises(ValueError, match="valid: linear, log"):
        fit_exposure_scale(m, m, method="median")
    with pytest.raises(ValueError, match="mask out censored-low"):
        fit_exposure_scale(m, m - 1, method="log")
    with pytest.raises(ValueError, match="no pixel"):
        fit_exposure_scale(m, m, torch.zeros(4, 3, dtype=torch.bool))


# ---------------------------------------------------------------- synthetic photos


@pytest.mark.parametrize("noise", ["poisson", "gaussian"])
def test_flat_field_mean_and_variance_match_the_noise_model(noise):
    # Per exposure level and channel: N = 128^2 pixels; mean within 5 SE and variance
    # within 5 SE of the sample variance, SE^2 = sigma^4 (2/(N-1) + kurt/N), kurt <= 1/e.
    g = torch.Generator().manual_seed(21)
    spec = _flat(128, 128)
    s = _srgb_of(spec)[0, 0]  # camera signal of the default path, (3,)
    gain, read, full = 0.8, 2.5, 1e5
    n = 128 * 128
    for green_e in (40.0, 400.0, 4000.0, 40000.0):
        expo = green_e / float(s[1])
        ph = synthesize_photo(spec, WL, exposure=expo, gain=gain, read_noise=read, full_well=full, bit_depth=16, noise=noise, generator=g)
        e = expo * s
        mean = gain * e
        var = gain**2 * (e + read**2) + 1 / 12  # shot + read + Sheppard's rounding term
        x = ph.image.reshape(-1, 3)
        se_mean = torch.sqrt(var / n)
        assert (torch.abs(x.mean(0) - mean) < 5 * se_mean).all(), (green_e, x.mean(0), mean)
        se_var = var * torch.sqrt(2 / (n - 1) + 1 / (e * n))
        assert (torch.abs(x.var(0) - var) < 5 * se_var).all(), (green_e, x.var(0), var)
        assert not ph.saturated.any() and not ph.black.any()
        assert_close(ph.expected[0, 0], mean)
        assert_close(ph.variance[0, 0], var)


def test_dark_frame_variance_includes_quantisation():
    # Read noise of 0.7 DN only: variance 0.49 + 1/12 = 0.573 (Sheppard), 17% above
    # the read noise alone; SE of the sample variance is 1.1% at N = 3 * 128^2.
    g = torch.Generator().manual_seed(4)
    ph = synthesize_photo(_flat(128, 128, 0.0), WL, exposure=1.0, gain=1.0, read_noise=0.7, black_level=100.0, bit_depth=12, generator=g)
    x = ph.image.flatten()
    assert torch.equal(x, torch.round(x))
    var = 0.49 + 1 / 12
    se = var * math.sqrt(2 / (x.numel() - 1))
    assert abs(float(x.var()) - var) < 5 * se
    assert abs(float(x.mean()) - 100.0) < 5 * math.sqrt(var / x.numel())


def test_saturation_clips_and_flags():
    g = torch.Generator().manual_seed(8)
    spec = _flat(40, 40)
    spec[10:14, 20:24] *= 1000.0  # the sun
    s = _srgb_of(spec[0:1, 0:1])[0, 0]
    expo = 5000.0 / float(s.max())  # sky at <= 5000 e-, sun at ~5e6 e-
    full, gain = 20000.0, 0.2  # sky <= 1000 DN
    ph = synthesize_photo(spec, WL, exposure=expo, full_well=full, gain=gain, read_noise=3.0, bit_depth=12, generator=g)
    sun = torch.zeros(40, 40, dtype=torch.bool)
    sun[10:14, 20:24] = True
    assert ph.saturated[sun].all() and not ph.saturated[~sun].any()
    # at the full well the value is gain * full_well plus read noise only (N(4000, 0.6^2) DN)
    assert (torch.abs(ph.image[sun] - gain * full) <= 5 * gain * 3.0 + 0.5).all()
    assert (ph.image <= 2**12 - 1).all()
    # with gain such that the full well exceeds the DN range, the DN clip saturates
    ph = synthesize_photo(spec, WL, exposure=expo, full_well=1e7, gain=0.5, bit_depth=12, generator=g)  # sky <= 2500 DN
    assert ph.saturated[sun].all() and (ph.image[sun] == 4095).all() and not ph.saturated[~sun].any()
    obs = ph.observation()
    assert obs.censored[sun].all() and not obs.exposure_unknown


@pytest.mark.parametrize("projection", ["equidistant", "equisolid"])
def test_vignetting_edge_to_centre_ratio(projection):
    cam = FisheyeCamera(41, projection=projection)
    spec = _flat(41, 41)
    s = _srgb_of(spec)[0, 0]
    expo = 1e6 / float(s.max())
    kw = dict(exposure=expo, full_well=1e7, gain=0.05, bit_depth=20, noise="none", camera=cam)
    flat = synthesize_photo(spec, WL, **kw).image
    yy, xx = np.mgrid[0:41, 0:41]
    rho = np.hypot(xx - 20.0, yy - 20.0) / 20.5  # centre (size-1)/2, radius size/2
    theta = rho * np.pi / 2 if projection == "equidistant" else 2 * np.arcsin(np.clip(rho * np.sin(np.pi / 4), 0, 1))
    models = {"cos4": np.cos(np.minimum(theta, np.pi / 2)) ** 4, (1.0, 0.0, -0.3, 0.0, -0.1): 1 - 0.3 * rho**2 - 0.1 * rho**4}
    for vig, ref in models.items():
        img = synthesize_photo(spec, WL, vignetting=vig, **kw).image
        edge = (20, 2)  # rho = 18 / 20.5
        ratio = img[edge] / img[20, 20]
        tol = 0.5 / img[20, 20].min() * 2  # half a DN in each of two values
        assert_close(ratio, torch.full((3,), ref[edge], dtype=F64), atol=float(tol) + 1e-12, rtol=0)
        inside = torch.tensor(rho <= 1.0)
        ph = synthesize_photo(spec, WL, vignetting=vig, **kw)  # every pixel, before quantisation
        assert_close(ph.vignetting[inside], torch.tensor(ref, dtype=F64)[inside], atol=1e-12, rtol=0)
        assert_close(ph.electrons, ph.vignetting[..., None] * expo * s)
        # and after quantisation, within half a DN in each of the two values
        assert (torch.abs(img / flat - torch.tensor(ref, dtype=F64)[..., None])[inside] <= (0.5 + 0.5 * img / flat)[inside] / flat[inside] + 1e-12).all()


def test_vignetting_errors():
    with pytest.raises(ValueError, match="needs the camera"):
        vignetting_map("cos4", (5, 5))
    with pytest.raises(ValueError, match="valid: none, cos4"):
        vignetting_map("cos3", (5, 5))
    with pytest.raises(ValueError, match=">= 0"):
        vignetting_map([1.0, 0.0, -2.0], (5, 5))


def test_camera_response_cmfs_reproduce_xyz_and_triangle_area():
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    rw = torch.tensor(cmfs.wavelengths, dtype=F64)
    resp = 683.0 * torch.tensor(cmfs.values, dtype=F64)
    wl = torch.tensor([405.5, 450.0, 520.0, 555.0, 610.0, 700.0], dtype=F64)
    assert_close(spectral_response_matrix(wl, resp, rw), spectral_to_xyz_matrix(wl), rtol=1e-12, atol=1e-12)
    # a triangle of half-width 50 nm at 550 nm on a coarse grid: integral of a linear
    # spectrum L = 1 + (lambda - 550)/300 against it is L(550) * 50 = 50 (symmetry).
    grid = torch.arange(400.0, 701.0, 50.0, dtype=F64)
    tri = (grid == 550).to(F64)[:, None]
    m = spectral_response_matrix(grid, tri)
    spec = 1 + (grid - 550) / 300
    assert_close(spec @ m, torch.tensor([50.0], dtype=F64), rtol=1e-9, atol=0)
    # synthesize_photo with the CMFs as sensitivities sees XYZ
    sp = torch.rand(3, 4, wl.numel(), generator=torch.Generator().manual_seed(2), dtype=F64)
    ph = synthesize_photo(sp, wl, camera_response=(rw, resp), exposure=1.0, noise="none", full_well=1e9, gain=1.0, bit_depth=24)
    assert_close(ph.electrons, spectral_to_xyz(sp, wl))


def test_srgb8_output_and_gaussian_mode_is_differentiable():
    g = torch.Generator().manual_seed(13)
    spec = _flat(64, 64).requires_grad_(True)
    s = _srgb_of(spec.detach())[0, 0]
    ph = synthesize_photo(spec, WL, exposure=3000 / float(s[1]), full_well=20000.0, read_noise=3.0, bit_depth=12, noise="gaussian", generator=g, output="srgb8")
    x = ph.image.reshape(-1, 3)
    assert torch.equal(x, torch.round(x)) and x.min() >= 0 and x.max() <= 255
    # delta-method mean and variance of the codes
    assert (torch.abs(x.mean(0) - ph.expected[0, 0]) < 5 * torch.sqrt(ph.variance[0, 0] / x.shape[0])).all()
    assert (torch.abs(x.var(0) / ph.variance[0, 0] - 1) < 0.1).all()
    ph.image.sum().backward()
    assert torch.isfinite(spec.grad).all() and (spec.grad > 0).all()
    obs = ph.observation()
    assert obs.exposure_unknown and obs.bit_depth == 8
    assert_close(obs.rgb, srgb_decode(ph.image.detach() / 255))


def test_synthesize_errors():
    with pytest.raises(ValueError, match="needs its wavelengths"):
        synthesize_photo(_flat(4, 4))
    with pytest.raises(ValueError, match="valid: poisson, gaussian, none"):
        synthesize_photo(_flat(4, 4), WL, noise="shot")
    with pytest.raises(ValueError, match="valid: raw, srgb8"):
        synthesize_photo(_flat(4, 4), WL, output="jpeg")
    with pytest.raises(ValueError, match="negative camera signal"):
        synthesize_photo(_flat(4, 4), WL, camera_response=-torch.ones(WL.numel(), 3, dtype=F64))


def test_rendered_sky_to_ldr_photo_and_back_to_its_exposure():
    # End to end on a rendered sky: the exposure scale fitted on the 8-bit photo's
    # usable pixels equals the one the simulation used (gain * exposure / max DN),
    # within the 8-bit rounding (~0.3% per pixel, averaged over > 100 pixels).
    from skyfit.atmosphere import load_atmosphere
    from skyfit.camera import render_fisheye
    from skyfit.transmittance import make_integrator

    wl = torch.linspace(400.0, 700.0, 5, dtype=F64)
    sky = render_fisheye(load_atmosphere("earth", wl), FisheyeCamera(21), 40.0, 120.0, make_integrator("taylor"))
    ph = synthesize_photo(sky, vignetting=[1.0, 0.0, -0.2], noise="none", output="srgb8", bit_depth=16)
    obs = ph.observation()
    use = (obs.usable & sky.valid)[..., None]
    assert int(use.sum()) > 100 and obs.exposure_unknown
    k = fit_exposure_scale(sky.rgb * ph.vignetting[..., None], obs.rgb, use)
    assert_close(k, torch.tensor(ph.exposure * ph.gain / ph.max_dn, dtype=F64), rtol=2e-3, atol=0)

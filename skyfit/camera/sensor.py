"""Synthetic photos: a rendered spectral sky through a camera's sensor, with its noise model.

**Synthetic photos** (:func:`synthesize_photo`) turn a rendered spectral sky
into raw sensor values with an explicit noise model: camera RGB (CIE 1931
-> linear sRGB by default, or given spectral sensitivities), exposure
(camera signal -> expected electrons), vignetting, shot noise (Poisson, or
its Gaussian approximation for gradients), saturation at the full well,
read noise, gain, quantisation to whole DN and clipping to the DN range,
optionally followed by sRGB encoding to 8-bit codes. The result carries the
per-pixel expected value and variance and the saturation mask, so a fit can
weight or censor pixels (:meth:`SyntheticPhoto.observation` gives the
:class:`~skyfit.camera.photo_io.PhotoObservation` a fit sees).

Units: camera signal in the units of the camera response (linear sRGB of XYZ
with 683 lm/W by default: Y in cd/m^2, CONTRACT.md); electrons [e-]; raw
values in DN (digital numbers).
"""
from __future__ import annotations

import dataclasses
import functools
import math
from typing import Callable, Sequence, Union

import numpy as np
import torch
from torch import Tensor

from ..render.colour import spectral_to_xyz, xyz_to_linear_srgb
from .fisheye import FisheyeCamera, rho_to_theta
from .photo_io import DEFAULT_BLACK_LEVEL, DEFAULT_CLIP_LEVEL, PhotoObservation, observation_from_encoded
from .srgb import srgb_encode, srgb_encode_slope

# --------------------------------------------------------------------------- camera response


@functools.lru_cache(maxsize=64)
def _response_weights(wavelengths: tuple[float, ...], response_wavelengths: tuple[float, ...]) -> np.ndarray:
    """(W, K) weights A so that the camera signal is ``L @ A @ response``.

    The rule of :mod:`skyfit.render.colour`: the spectrum L is piecewise linear
    between its samples (constant beyond the ends), the response is resampled
    linearly onto a grid of at most 1 nm steps, and the product is summed with
    ``np.gradient`` weights of that grid (as ``_xyz_matrix`` does on the 1 nm CMF table).
    """
    lam = np.asarray(wavelengths, float)
    rw = np.asarray(response_wavelengths, float)
    steps = np.diff(rw)
    if steps.size and np.all(steps <= 1.0 + 1e-9):
        fine = rw
    else:
        fine = np.union1d(np.arange(rw[0], rw[-1], 1.0), rw)

    def hats(nodes: np.ndarray, at: np.ndarray) -> np.ndarray:  # (len(nodes), len(at))
        if nodes.size == 1:
            return np.ones((1, at.size))
        order = np.argsort(nodes)
        out = np.zeros((nodes.size, at.size))
        for k, i in enumerate(order):
            e = np.zeros(nodes.size)
            e[k] = 1.0
            out[i] = np.interp(at, nodes[order], e)
        return out

    dl = np.gradient(fine) if fine.size > 1 else np.ones(1)
    return (hats(lam, fine) * dl) @ hats(rw, fine).T


def spectral_response_matrix(wavelengths_nm: Tensor, response: Tensor, response_wavelengths_nm: Tensor | None = None) -> Tensor:
    """Matrix M with camera signal = L @ M for spectral radiance L on ``wavelengths_nm``.

    Integration rule as :func:`skyfit.render.spectral_to_xyz_matrix` (see
    :func:`_response_weights`); with ``response = 683 * CIE CMFs`` on their
    1 nm table it reproduces that matrix. Differentiable in ``response``.

    Args:
        wavelengths_nm: the spectrum's wavelengths, shape (W,). [nm]
        response: spectral sensitivities, shape (K, C). [signal per (W/(m^2 sr nm)) per nm]
        response_wavelengths_nm: shape (K,), increasing; default ``wavelengths_nm``. [nm]

    Returns:
        shape (W, C), dtype and device of ``response``.
    """
    rw = wavelengths_nm if response_wavelengths_nm is None else response_wavelengths_nm
    if response.ndim != 2 or response.shape[0] != rw.shape[0]:
        raise ValueError(f"camera response must have shape (K, C) with K = {rw.shape[0]} wavelengths, got {tuple(response.shape)}")
    rwt = tuple(float(v) for v in rw.detach().cpu().tolist())
    if any(b <= a for a, b in zip(rwt, rwt[1:])):
        raise ValueError("camera response wavelengths must be strictly increasing")
    a = _response_weights(tuple(float(v) for v in wavelengths_nm.detach().cpu().tolist()), rwt)
    return torch.as_tensor(a, dtype=response.dtype, device=response.device) @ response


# --------------------------------------------------------------------------- synthetic photos

VIGNETTING_MODELS = ("none", "cos4")
NOISE_MODELS = ("poisson", "gaussian", "none")
OUTPUTS = ("raw", "srgb8")

Vignetting = Union[None, str, Sequence[float], Callable[[Tensor], Tensor], Tensor]


@dataclasses.dataclass
class SyntheticPhoto:
    """A synthesized photo and its noise model.

    Attributes:
        image: the photo, shape (H, W, 3): raw DN for ``output='raw'``, 8-bit
            codes 0..255 for ``'srgb8'``; float (whole numbers) so gradients can
            pass (rounding uses a straight-through estimator).
        expected: per-pixel expected value of ``image`` (first order: clipping
            ignored), shape (H, W, 3). [DN or code]
        variance: per-pixel variance of ``image`` (first order, incl. the 1/12
            of quantisation), shape (H, W, 3). [DN^2 or code^2]
        saturated: channel clipped at the full well or the largest DN, shape (H, W, 3), bool.
        black: channel clipped at 0 DN, shape (H, W, 3), bool.
        electrons: expected electrons before noise, shape (H, W, 3). [e-]
        vignetting: relative illumination applied, shape (H, W). [1]
        valid: pixels inside the camera's field, shape (H, W), bool.
        exposure: electrons per unit camera signal used (the auto value if not given). [e- / signal]
        gain: DN per electron. [DN/e-]
        full_well: electrons at saturation. [e-]
        black_level: DN offset. [DN]
        max_dn: largest raw value, 2**bit_depth - 1. [DN]
        bit_depth: raw bits.
        output: 'raw' or 'srgb8'.
    """

    image: Tensor
    expected: Tensor
    variance: Tensor
    saturated: Tensor
    black: Tensor
    electrons: Tensor
    vignetting: Tensor
    valid: Tensor
    exposure: float
    gain: float
    full_well: float
    black_level: float
    max_dn: int
    bit_depth: int
    output: str

    def observation(
        self, clip_level: float = DEFAULT_CLIP_LEVEL, black_level: float = DEFAULT_BLACK_LEVEL
    ) -> PhotoObservation:
        """The photo as a :class:`PhotoObservation` (what a fit sees).

        ``'srgb8'``: decoded and censored exactly as :func:`~skyfit.camera.photo_io.load_ldr_photo`
        (exposure unknown). ``'raw'``: ``rgb = (DN - black) / (max DN - black)``,
        censored high where saturated, low where black; the exposure is known:
        ``rgb ~= exposure_scale * vignetting * camera_signal``.
        """
        if self.output == "srgb8":
            return observation_from_encoded(self.image, 255, 8, clip_level, black_level, self.valid, None)
        span = self.max_dn - self.black_level
        return PhotoObservation(
            rgb=(self.image - self.black_level) / span,
            valid=self.valid,
            censored_high=self.saturated,
            censored_low=self.black,
            bit_depth=self.bit_depth,
            clip_high=(min(self.max_dn, self.black_level + self.gain * self.full_well) - self.black_level) / span,
            clip_low=-self.black_level / span,
            exposure_unknown=False,
            exposure_scale=self.exposure * self.gain / span,
        )


def _pixel_grid(h: int, w: int, dtype, device) -> tuple[Tensor, Tensor]:
    yy, xx = torch.meshgrid(torch.arange(h, dtype=dtype, device=device), torch.arange(w, dtype=dtype, device=device), indexing="ij")
    return xx, yy


def _normalised_radius(h: int, w: int, camera: FisheyeCamera | None, dtype, device) -> Tensor:
    """Distance of each pixel centre from the optical axis over the 90° radius, shape (H, W). [1]

    Without a camera: centre ((W-1)/2, (H-1)/2) and radius min(H, W)/2, the camera defaults.
    """
    cx, cy, r = (w - 1) / 2.0, (h - 1) / 2.0, min(h, w) / 2.0
    if camera is not None:
        f = lambda v, d: d if v is None else float(torch.as_tensor(v).detach())  # noqa: E731
        cx, cy, r = f(camera.cx, cx), f(camera.cy, cy), f(camera.r90, r)
    xx, yy = _pixel_grid(h, w, dtype, device)
    return torch.hypot(xx - cx, yy - cy) / r


def _cos_off_axis(h: int, w: int, camera: FisheyeCamera, dtype, device) -> Tensor:
    """Cosine of each pixel's angle from the optical axis (0 beyond the field of view), shape (H, W). [1]"""
    with torch.no_grad():
        if hasattr(camera, "pixel_to_camera"):  # the camera's own map (every projection)
            xx, yy = _pixel_grid(h, w, dtype, device)
            d, inside = camera.pixel_to_camera(xx, yy)
            return torch.where(inside, d[..., 2], torch.zeros_like(xx)).clamp(min=0.0)
        theta = rho_to_theta(_normalised_radius(h, w, camera, dtype, device), camera.projection)
        return torch.cos(torch.clamp(theta, max=math.pi / 2))


def vignetting_map(
    vignetting: Vignetting, shape: tuple[int, int], camera: FisheyeCamera | None = None, dtype=torch.float64, device="cpu"
) -> Tensor:
    """Relative illumination V per pixel, shape (H, W). [1]

    ``vignetting`` is one of:

    * ``None`` or ``'none'``: V = 1;
    * ``'cos4'``: V = cos^4(theta), theta the pixel's angle from the optical
      axis through the camera's projection (0 beyond 90° and outside the
      field of view; the natural-vignetting law of a
      thin lens; it reaches 0 at 90°, so it suits narrow fields better than a
      real fisheye, whose falloff is milder: use a polynomial there). Needs a camera;
    * a sequence ``(c0, c1, c2, ...)``: V = sum_k c_k rho^k, rho the distance
      from the image centre divided by the radius of the 90° circle;
    * a callable ``rho -> V``;
    * a tensor of shape (H, W): V itself.

    V must be >= 0 and finite.
    """
    h, w = shape
    if isinstance(vignetting, Tensor):
        v = vignetting.to(dtype=dtype, device=device)
        if tuple(v.shape) != (h, w):
            raise ValueError(f"vignetting map has shape {tuple(v.shape)}, image is {(h, w)}")
    elif vignetting is None or (isinstance(vignetting, str) and vignetting == "none"):
        return torch.ones(h, w, dtype=dtype, device=device)
    elif isinstance(vignetting, str):
        if vignetting != "cos4":
            raise ValueError(f"unknown vignetting {vignetting!r}; valid: {', '.join(VIGNETTING_MODELS)}, a polynomial, a callable or a map")
        if camera is None:
            raise ValueError("vignetting='cos4' needs the camera's projection: pass a SkyImage or camera=FisheyeCamera(...)")
        v = _cos_off_axis(h, w, camera, dtype, device) ** 4
    elif callable(vignetting):
        v = torch.as_tensor(vignetting(_normalised_radius(h, w, camera, dtype, device)), dtype=dtype, device=device)
        v = torch.broadcast_to(v, (h, w))
    else:
        coeffs = [float(c) for c in vignetting]
        if not coeffs:
            raise ValueError("vignetting polynomial needs at least one coefficient")
        rho = _normalised_radius(h, w, camera, dtype, device)
        v = torch.zeros_like(rho)
        for c in reversed(coeffs):  # Horner
            v = v * rho + c
    if not bool(torch.all(torch.isfinite(v) & (v >= 0))):
        raise ValueError("vignetting must be finite and >= 0 over the image")
    return v


def synthesize_photo(
    image,
    wavelengths: Tensor | None = None,
    *,
    camera: FisheyeCamera | None = None,
    camera_response: Tensor | tuple[Tensor, Tensor] | None = None,
    exposure: float | None = None,
    full_well: float = 30000.0,
    read_noise: float = 3.0,
    gain: float | None = None,
    black_level: float = 0.0,
    vignetting: Vignetting = None,
    bit_depth: int = 14,
    noise: str = "poisson",
    generator: torch.Generator | None = None,
    output: str = "raw",
    auto_exposure_fill: float = 0.5,
) -> SyntheticPhoto:
    """A synthetic camera photo of a spectral sky, with its noise model.

    Pipeline per pixel and channel c:

    1. camera signal ``s_c = L @ M[:, c]``: by default linear sRGB of CIE 1931
       XYZ at 683 lm/W (``skyfit.render``); or given spectral sensitivities
       integrated with the same piecewise-linear rule (:func:`spectral_response_matrix`);
    2. expected electrons ``e = exposure * V * s_c`` with V the vignetting;
    3. shot noise: ``n ~ Poisson(e)`` (``'poisson'``), or ``e + sqrt(e) z``
       (``'gaussian'``, differentiable in e), or ``n = e`` (``'none'``);
       then the full well: ``n = min(n, full_well)``;
    4. read-out: ``v = black_level + gain * (n + read_noise * z')``;
    5. quantisation ``round(v)`` (straight-through gradient) and clipping to [0, 2**bit_depth - 1];
    6. ``output='srgb8'``: ``x = (DN - black) / (max DN - black)`` clipped to
       [0, 1], sRGB-encoded, rounded to 8-bit codes (a camera JPEG without tone curve).

    Noise model returned (valid away from the clip levels):
    mean ``black + gain * e``, variance ``gain^2 (e + read_noise^2) + 1/12`` [DN^2];
    for ``'srgb8'`` both are carried through the encoding to first order
    (delta method) and 1/12 code^2 is added.

    Args:
        image: a :class:`skyfit.camera.SkyImage`, or spectral radiance of shape
            (H, W, W_l) [W/(m^2 sr nm)] with ``wavelengths``.
        wavelengths: shape (W_l,), when ``image`` is a tensor. [nm]
        camera: for vignetting's radius and projection (default: the SkyImage's,
            else centred with radius min(H, W)/2).
        camera_response: None (CIE -> linear sRGB), sensitivities (W_l, C) on
            ``wavelengths``, or a tuple (response_wavelengths (K,) [nm], sensitivities (K, C)).
        exposure: electrons per unit camera signal [e-/signal]; None: chosen so
            that the 99th percentile of the brightest channel over valid pixels
            reaches ``auto_exposure_fill * full_well``.
        full_well: electrons at which a pixel saturates. [e-]
        read_noise: read-noise standard deviation. [e-]
        gain: DN per electron; None: ``(2**bit_depth - 1 - black_level) / full_well``. [DN/e-]
        black_level: offset added to every raw value. [DN]
        vignetting: see :func:`vignetting_map`.
        bit_depth: raw bits per channel, 1..24.
        noise: 'poisson', 'gaussian' or 'none'.
        generator: the random source (a fresh nondeterministic one if None).
        output: 'raw' or 'srgb8'.
        auto_exposure_fill: fraction of the full well for the auto exposure. [1]

    Returns:
        :class:`SyntheticPhoto`.
    """
    # ---- inputs
    if hasattr(image, "spectral") and hasattr(image, "wavelengths"):
        spectral, wl, valid = image.spectral, image.wavelengths, image.valid
        spectral = torch.where(valid[..., None], spectral, torch.zeros_like(spectral))  # no light outside the field
        camera = camera if camera is not None else getattr(image, "camera", None)
    elif isinstance(image, Tensor):
        if wavelengths is None:
            raise ValueError("synthesize_photo: a spectral tensor needs its wavelengths")
        spectral, wl = image, wavelengths
        valid = torch.ones(spectral.shape[:2], dtype=torch.bool, device=spectral.device)
    else:
        raise TypeError(f"synthesize_photo: expected a SkyImage or a (H, W, W_l) tensor, got {type(image).__name__}")
    if spectral.ndim != 3 or spectral.shape[-1] != wl.shape[-1]:
        raise ValueError(f"spectral radiance must have shape (H, W, {wl.shape[-1]}), got {tuple(spectral.shape)}")
    if noise not in NOISE_MODELS:
        raise ValueError(f"unknown noise model {noise!r}; valid: {', '.join(NOISE_MODELS)}")
    if output not in OUTPUTS:
        raise ValueError(f"unknown output {output!r}; valid: {', '.join(OUTPUTS)}")
    if not (isinstance(bit_depth, int) and 1 <= bit_depth <= 24):
        raise ValueError(f"bit_depth must be an integer in 1..24, got {bit_depth}")
    max_dn = 2**bit_depth - 1
    if not 0 < full_well < math.inf:
        raise ValueError(f"full_well must be > 0 e-, got {full_well}")
    if not 0 <= read_noise < math.inf:
        raise ValueError(f"read_noise must be >= 0 e-, got {read_noise}")
    if not 0 <= black_level < max_dn:
        raise ValueError(f"black_level must be in [0, {max_dn}) DN, got {black_level}")
    if gain is None:
        gain = (max_dn - black_level) / full_well
    if not 0 < gain < math.inf:
        raise ValueError(f"gain must be > 0 DN/e-, got {gain}")
    dtype, device = spectral.dtype, spectral.device
    h, w = spectral.shape[:2]

    # ---- camera signal
    if camera_response is None:
        signal = xyz_to_linear_srgb(spectral_to_xyz(spectral, wl))
    else:
        if isinstance(camera_response, tuple):
            rw, resp = camera_response
        else:
            rw, resp = None, camera_response
        signal = spectral @ spectral_response_matrix(wl, resp.to(dtype=dtype, device=device), rw)
    if bool(torch.any(signal < -1e-9 * signal.abs().max().clamp(min=1e-300))):
        raise ValueError(
            "negative camera signal: a colour outside the sRGB gamut (default response) or a negative "
            "camera_response; a sensor needs non-negative sensitivities"
        )
    signal = torch.where(signal < 0, torch.zeros_like(signal), signal)  # rounding-level negatives only
    vig = vignetting_map(vignetting, (h, w), camera, dtype, device)
    lit = vig[..., None] * signal
    if exposure is None:
        vals = lit.detach().amax(-1)[valid]
        ref = float(vals.kthvalue(max(1, math.ceil(0.99 * vals.numel()))).values) if vals.numel() else 0.0
        if not ref > 0:
            raise ValueError("auto exposure: the image is black; pass exposure=")
        exposure = auto_exposure_fill * full_well / ref
    if not 0 < float(exposure) < math.inf:
        raise ValueError(f"exposure must be > 0, got {exposure}")
    electrons = exposure * lit

    # ---- noise
    if noise != "none" and generator is None:
        generator = torch.Generator(device=device)
        generator.seed()
    if noise == "poisson":
        n = torch.poisson(electrons.detach(), generator=generator)  # no gradient: use 'gaussian' to differentiate
    elif noise == "gaussian":
        # clamp only at e = 0, where d sqrt(e)/de is infinite
        std = torch.sqrt(torch.clamp(electrons, min=torch.finfo(dtype).tiny))
        n = electrons + std * torch.randn(electrons.shape, generator=generator, dtype=dtype, device=device)
    else:
        n = electrons
    well_full = n >= full_well
    n = torch.clamp(n, max=full_well)
    v = n
    if read_noise > 0 and noise != "none":
        v = n + read_noise * torch.randn(n.shape, generator=generator, dtype=dtype, device=device)
    v = black_level + gain * v
    dn = v + (torch.round(v) - v).detach()
    saturated = well_full | (dn >= max_dn)
    black = dn <= 0
    dn = torch.clamp(dn, 0.0, float(max_dn))

    e_mean = torch.clamp(electrons, max=full_well)
    mean = torch.clamp(black_level + gain * e_mean, 0.0, float(max_dn))
    shot_var = e_mean if noise != "none" else torch.zeros_like(e_mean)
    read_var = read_noise**2 if noise != "none" else 0.0
    var = gain**2 * (shot_var + read_var) + 1.0 / 12.0

    if output == "srgb8":
        span = max_dn - black_level
        x = torch.clamp((dn - black_level) / span, 0.0, 1.0)
        enc = 255.0 * srgb_encode(x)
        img = enc + (torch.round(enc) - enc).detach()
        xm = torch.clamp((mean - black_level) / span, 0.0, 1.0)
        mean_out = 255.0 * srgb_encode(xm)
        var_out = (255.0 * srgb_encode_slope(xm) / span) ** 2 * (var - 1.0 / 12.0) + 1.0 / 12.0
    else:
        img, mean_out, var_out = dn, mean, var

    return SyntheticPhoto(
        image=img,
        expected=mean_out,
        variance=var_out,
        saturated=saturated,
        black=black,
        electrons=electrons,
        vignetting=vig,
        valid=valid,
        exposure=float(exposure),
        gain=float(gain),
        full_well=float(full_well),
        black_level=float(black_level),
        max_dn=max_dn,
        bit_depth=bit_depth,
        output=output,
    )



__all__ = [
    "NOISE_MODELS",
    "OUTPUTS",
    "SyntheticPhoto",
    "VIGNETTING_MODELS",
    "spectral_response_matrix",
    "synthesize_photo",
    "vignetting_map",
]

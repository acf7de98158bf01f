"""Environment maps of a sky for image-based lighting: equirectangular (lat-long) and cubemap.

An :class:`EnvMap` holds the radiance of every direction around the observer (sky above,
ground below), linear sRGB (CONTRACT.md: CIE 1931 2 deg with 683 lm/W, so G-weighted Y is
cd/m^2) and optionally spectral, with each pixel's direction and solid angle, so that
integrals over the sphere are sums (:meth:`EnvMap.irradiance`).

Conventions (docs/envmap.md has the renderer mappings):

- World frame: East-North-Up (ENU) as everywhere in skyfit; the Y-up frame of the maps
  is ``x = East, y = Up, z = South`` (right-handed: x cross y = z), i.e. -z points North.
- ``latlong``: H rows x 2H columns. Row 0 is straight up: pixel (row i, column j) has its
  centre at zenith angle theta = (i + 0.5) 180 / H deg and azimuth
  phi = (j + 0.5) 360 / (2H) deg clockwise from North, so the left edge of column 0 is
  North, East is at a quarter of the width, South in the middle, West at three quarters;
  the horizon is the boundary between rows H/2 - 1 and H/2. Seen from inside, East is to
  the right of North (not mirrored). As texture coordinates: u = phi / 360 deg,
  v = theta / 180 deg with v = 0 at the first row.
- ``cubemap``: six N x N faces in OpenGL order +X, -X, +Y, -Y, +Z, -Z of the Y-up frame,
  side by side in one N x 6N image (a horizontal strip). Texel (row i, column j) of a face
  has s = (j + 0.5) / N, t = (i + 0.5) / N and the direction of the OpenGL cube-map rule
  (OpenGL 4.6 core specification, Sec. 8.13, Table 8.19: major axis ma and
  (sc, tc) per face, s = (sc / |ma| + 1) / 2, t = (tc / |ma| + 1) / 2), so that uploading
  face k's rows in file order to ``GL_TEXTURE_CUBE_MAP_POSITIVE_X + k`` and sampling with
  ``texture(cube, vec3(E, U, S))`` returns this map.

The solar disc (``sun_disk``) is a uniform disc of the atmosphere's angular radius carrying
E_sun T(sun) (T the transmittance along each part of the disc, 0 below the horizon). It is
added by splatting: K points spread evenly over the disc each carry E_sun T / K into the
pixel that contains it, divided by that pixel's solid angle. The map then holds exactly the
solar flux whatever its resolution (a 0.27 deg disc is smaller than a pixel below H = 340),
and the brightest pixel is the one that holds the disc's centre.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from ..atmosphere import Atmosphere
from ..geometry import distance_to_top, zenith_angle_deg
from ..render.colour import spectral_to_xyz, tonemap_srgb8, xyz_to_linear_srgb
from ..atmosphere.profiles import profile_densities
from ..scattering.bruneton_tables import extinction_matrix3
from ..scattering.single import sun_ray_cosine

LAYOUTS = ("latlong", "cubemap")
"""Map layouts: equirectangular (H x 2H) and cubemap (six N x N faces as an N x 6N strip)."""

SUFFIXES = (".exr", ".hdr")
"""Output formats: OpenEXR (float32, R, G, B [+ L<nm>]) and Radiance RGBE (R, G, B) via :mod:`skyfit.io.hdr`."""

MAX_SIZE = 8192
"""Largest map size (latlong height, cube face edge) [px]; 8192 x 16384 x 3 float32 is 1.6 GB."""

CUBE_FACES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")

CONVENTIONS = {
    "world": "East-North-Up; the maps' Y-up frame is x = East, y = Up, z = South (-z = North), right-handed",
    "latlong": "H rows x 2H columns; pixel (row i, col j) centre: zenith angle (i + 0.5) 180/H deg, azimuth "
               "(j + 0.5) 360/(2H) deg clockwise from North; row 0 straight up; column 0's left edge North, "
               "East at W/4, South at W/2, West at 3W/4; u = azimuth/360, v = zenith/180 (v = 0 first row)",
    "cubemap": "six N x N faces +X, -X, +Y, -Y, +Z, -Z of the Y-up frame side by side (N rows x 6N columns); "
               "texel (row i, col j): s = (j + 0.5)/N, t = (i + 0.5)/N with OpenGL's cube-map rule "
               "(GL 4.6 Table 8.19); sample with texture(cube, vec3(East, Up, South))",
    "units": "R, G, B: linear sRGB (D65) of CIE XYZ with 683 lm/W (Y = luminance in cd/m^2); L<nm>: W/(m^2 sr nm)",
}


def _check_size(size: int) -> int:
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or not 2 <= int(size) <= MAX_SIZE:
        raise ValueError(f"environment map size must be an integer in 2..{MAX_SIZE}, got {size!r}")
    if int(size) % 2:
        raise ValueError(f"environment map size must be even (the horizon falls between two rows), got {size}")
    return int(size)


def check_layout(layout: str) -> str:
    """``layout`` when it is one of :data:`LAYOUTS`; ValueError listing them otherwise."""
    if layout not in LAYOUTS:
        raise ValueError(f"unknown environment map format {layout!r}; valid: {', '.join(LAYOUTS)}")
    return layout


# -- geometry -------------------------------------------------------------------------------------
def yup_to_enu(v: Tensor) -> Tensor:
    """(x = East, y = Up, z = South) -> (East, North, Up), shape (..., 3)."""
    return torch.stack([v[..., 0], -v[..., 2], v[..., 1]], -1)


def enu_to_yup(v: Tensor) -> Tensor:
    """(East, North, Up) -> (x = East, y = Up, z = South), shape (..., 3)."""
    return torch.stack([v[..., 0], v[..., 2], -v[..., 1]], -1)


def latlong_directions(height: int, dtype=torch.float64, device="cpu") -> Tensor:
    """Unit ENU directions of the pixel centres of an H x 2H lat-long map, shape (H, 2H, 3)."""
    h = _check_size(height)
    theta = (torch.arange(h, dtype=dtype, device=device) + 0.5) * (math.pi / h)
    phi = (torch.arange(2 * h, dtype=dtype, device=device) + 0.5) * (math.pi / h)
    T, P = torch.meshgrid(theta, phi, indexing="ij")
    s = torch.sin(T)
    return torch.stack([s * torch.sin(P), s * torch.cos(P), torch.cos(T)], -1)


def latlong_solid_angles(height: int, dtype=torch.float64, device="cpu") -> Tensor:
    """Exact solid angle of each pixel of an H x 2H lat-long map, shape (H, 2H); sums to 4 pi. [sr]

    A pixel spans [theta_i, theta_i+1] x [phi_j, phi_j+1]: (phi_j+1 - phi_j)(cos theta_i - cos theta_i+1).
    """
    h = _check_size(height)
    edges = torch.arange(h + 1, dtype=dtype, device=device) * (math.pi / h)
    row = (math.pi / h) * (torch.cos(edges[:-1]) - torch.cos(edges[1:]))
    return row[:, None].expand(h, 2 * h).contiguous()


def latlong_pixel(zenith_deg: float, azimuth_deg: float, height: int) -> tuple[float, float]:
    """Continuous (row, column) of a direction in an H x 2H lat-long map (pixel centres at integers)."""
    return zenith_deg / 180.0 * height - 0.5, (azimuth_deg % 360.0) / 360.0 * 2 * height - 0.5


def _cube_face_vectors(sc: Tensor, tc: Tensor, face: int) -> Tensor:
    """Y-up direction (not normalised) of face ``face`` at (sc, tc) in [-1, 1] (GL 4.6 Table 8.19 inverted)."""
    one = torch.ones_like(sc)
    x, y, z = {
        0: (one, -tc, -sc),   # +X: sc = -rz, tc = -ry, ma = rx
        1: (-one, -tc, sc),   # -X: sc = +rz, tc = -ry
        2: (sc, one, tc),     # +Y: sc = +rx, tc = +rz, ma = ry
        3: (sc, -one, -tc),   # -Y: sc = +rx, tc = -rz
        4: (sc, -tc, one),    # +Z: sc = +rx, tc = -ry, ma = rz
        5: (-sc, -tc, -one),  # -Z: sc = -rx, tc = -ry
    }[face]
    return torch.stack([x, y, z], -1)


def cubemap_directions(size: int, dtype=torch.float64, device="cpu") -> Tensor:
    """Unit ENU directions of the texel centres of a cubemap, shape (6, N, N, 3) (faces in :data:`CUBE_FACES`)."""
    n = _check_size(size)
    c = (torch.arange(n, dtype=dtype, device=device) + 0.5) * (2.0 / n) - 1.0
    tc, sc = torch.meshgrid(c, c, indexing="ij")  # row i -> t, column j -> s
    v = torch.stack([_cube_face_vectors(sc, tc, f) for f in range(6)])
    return yup_to_enu(v / torch.linalg.vector_norm(v, dim=-1, keepdim=True))


def cubemap_solid_angles(size: int, dtype=torch.float64, device="cpu") -> Tensor:
    """Exact solid angle of each cubemap texel, shape (6, N, N); sums to 4 pi. [sr]

    The solid angle of the face rectangle [0, x] x [0, y] at unit distance is
    atan(x y / sqrt(1 + x^2 + y^2)) (the projected-area integral of 1 / (1 + x^2 + y^2)^1.5);
    a texel is the signed sum over its four corners.
    """
    n = _check_size(size)
    e = torch.arange(n + 1, dtype=dtype, device=device) * (2.0 / n) - 1.0
    Y, X = torch.meshgrid(e, e, indexing="ij")
    a = torch.atan2(X * Y, torch.sqrt(1.0 + X * X + Y * Y))
    omega = a[1:, 1:] - a[:-1, 1:] - a[1:, :-1] + a[:-1, :-1]
    return omega.unsqueeze(0).expand(6, n, n).contiguous()


def cubemap_texel(v_enu: Tensor, size: int) -> tuple[Tensor, Tensor, Tensor]:
    """(face, row, column) of the texel holding each ENU direction, shape (...) each (long)."""
    v = enu_to_yup(v_enu)
    ax = v.abs().argmax(-1)
    x, y, z = v.unbind(-1)
    ma = v.abs().max(-1).values
    face = 2 * ax + (torch.gather(v, -1, ax.unsqueeze(-1)).squeeze(-1) < 0).long()
    # (sc, tc) per face, GL 4.6 Table 8.19
    sc = torch.stack([-z, z, x, x, x, -x], -1).gather(-1, face.unsqueeze(-1)).squeeze(-1)
    tc = torch.stack([-y, -y, z, -z, -y, -y], -1).gather(-1, face.unsqueeze(-1)).squeeze(-1)
    s, t = (sc / ma + 1.0) / 2.0, (tc / ma + 1.0) / 2.0
    col = torch.clamp((s * size).floor().long(), 0, size - 1)
    row = torch.clamp((t * size).floor().long(), 0, size - 1)
    return face, row, col


def latlong_texel(v_enu: Tensor, height: int) -> tuple[Tensor, Tensor]:
    """(row, column) of the lat-long pixel holding each ENU direction, shape (...) each (long)."""
    e, n, u = v_enu.unbind(-1)
    theta = torch.atan2(torch.sqrt(e * e + n * n), u)
    phi = torch.remainder(torch.atan2(e, n), 2 * math.pi)
    row = torch.clamp((theta / math.pi * height).floor().long(), 0, height - 1)
    col = torch.remainder((phi / (2 * math.pi) * 2 * height).floor().long(), 2 * height)
    return row, col


# -- the map ------------------------------------------------------------------------------------------
@dataclasses.dataclass
class EnvMap:
    """A rendered environment map.

    Attributes:
        layout: ``latlong`` or ``cubemap``.
        rgb: linear sRGB radiance, shape (H, 2H, 3) or (6, N, N, 3). [cd/m^2 per channel weight]
        spectral: spectral radiance, shape (..., W) matching ``rgb``, or None. [W/(m^2 sr nm)]
        wavelengths: shape (W,). [nm]
        directions: unit ENU direction of each pixel centre, shape (..., 3).
        solid_angle: of each pixel, shape (...). [sr]
        sun: ``zenith_deg``, ``azimuth_deg`` (and ``time``, ``location`` when given), ``disk`` (bool).
        meta: renderer settings, atmosphere summary, conventions (written into the EXR header).
    """

    layout: str
    rgb: np.ndarray
    spectral: np.ndarray | None
    wavelengths: np.ndarray
    directions: np.ndarray
    solid_angle: np.ndarray
    sun: dict
    meta: dict

    @property
    def size(self) -> int:
        """Lat-long height or cube face edge. [px]"""
        return int(self.rgb.shape[0] if self.layout == "latlong" else self.rgb.shape[1])

    def irradiance(self, values: np.ndarray | None = None, normal=(0.0, 0.0, 1.0)) -> np.ndarray:
        """Sum of L max(cos, 0) dOmega over the pixels: irradiance on a surface facing ``normal`` (ENU).

        With the default normal (Up) this is the integral of radiance x cos over the upper
        hemisphere; per channel of ``values`` (default ``rgb``), shape (C,). [unit of values x sr]
        """
        v = self.rgb if values is None else values
        cos = np.clip(self.directions @ np.asarray(normal, float), 0.0, None)
        w = (cos * self.solid_angle).reshape(-1)
        return w @ np.asarray(v, np.float64).reshape(w.shape[0], -1)

    def image(self, values: np.ndarray | None = None) -> np.ndarray:
        """2-D image for writing: (H, 2H, C) for lat-long, the (N, 6N, C) strip of faces for a cubemap."""
        v = self.rgb if values is None else values
        if self.layout == "latlong":
            return v
        return np.concatenate(list(v), axis=1)


def _disc_points(sun: Tensor, radius: float, k: int) -> Tensor:
    """``k`` unit vectors spread evenly over a disc of angular ``radius`` around ``sun`` (Vogel's spiral), (k, 3)."""
    dtype, device = sun.dtype, sun.device
    i = torch.arange(k, dtype=dtype, device=device)
    rho = radius * torch.sqrt((i + 0.5) / k)  # equal-area rings
    psi = i * (math.pi * (3.0 - math.sqrt(5.0)))
    helper = torch.tensor([0.0, 0.0, 1.0] if abs(float(sun[2])) < 0.9 else [1.0, 0.0, 0.0], dtype=dtype, device=device)
    e1 = torch.linalg.cross(sun, helper)
    e1 = e1 / torch.linalg.vector_norm(e1)
    e2 = torch.linalg.cross(sun, e1)
    return (torch.cos(rho)[:, None] * sun + torch.sin(rho)[:, None] * (torch.cos(psi)[:, None] * e1
                                                                       + torch.sin(psi)[:, None] * e2))


def sun_transmittance(atm: Atmosphere, r: float, directions: Tensor, samples: int = 500) -> Tensor:
    """Transmittance from radius r to space along ENU ``directions``, 0 where they hit the ground, (..., W). [1]

    The optical length of each ray by the trapezoid rule with ``samples`` intervals of the
    density profiles (Rayleigh, Mie exponential; ozone tent), as Bruneton 2017's
    ComputeOpticalLengthToTopAtmosphereBoundary does for its table, but along each ray itself.
    A ray below the geometric horizon ends on the ground: 0.
    """
    shape = directions.shape[:-1]
    mu = torch.clamp(directions.reshape(-1, 3)[:, 2], -1.0, 1.0)
    rr = torch.full_like(mu, float(r))
    mu_c = sun_ray_cosine(rr, mu, atm.bottom_radius)
    x = torch.linspace(0.0, 1.0, samples + 1, dtype=mu.dtype, device=mu.device)
    w = torch.full_like(x, 1.0 / samples)
    w[0] *= 0.5
    w[-1] *= 0.5
    out = []
    with torch.no_grad():
        for i in range(0, mu.shape[0], 4096):
            rc, mc = rr[i:i + 4096, None], mu_c[i:i + 4096, None]
            d = distance_to_top(rc, mc, atm.top_radius)
            s = d * x
            r_s = torch.sqrt(torch.clamp_min(s * s + 2.0 * rc * mc * s + rc * rc, 0.0))
            col = torch.einsum("nsk,s->nk", profile_densities(r_s - atm.bottom_radius, atm), w) * d
            out.append(torch.exp(-col @ extinction_matrix3(atm)))
    above = (mu >= mu_c).unsqueeze(-1)  # below the geometric horizon the ray ends on the ground
    return (torch.cat(out) * above).reshape(*shape, -1)


def sun_disc_splat(atm: Atmosphere, sun: Tensor, layout: str, size: int, solid_angle: Tensor, altitude: float = 0.0,
                   points: int | None = None) -> Tensor:
    """Radiance of the solar disc as a map, shape (H, 2H, W) or (6, N, N, W). [W/(m^2 sr nm)]

    Each of ``points`` evenly spread points of the disc carries E_sun T / points [W/(m^2 nm)] into
    the pixel holding it (divided by that pixel's solid angle), so the map's integral of the disc
    is E_sun times the disc-averaged transmittance whatever the resolution. Default ``points``:
    16 per pixel the disc covers, at least 256, at most 65536.
    """
    alpha = atm.sun_angular_radius
    disc_sr = math.pi * alpha * alpha
    if points is None:
        points = int(min(max(256, 16 * disc_sr / float(solid_angle.min())), 65536))
    d = _disc_points(sun, alpha, points)
    t = sun_transmittance(atm, atm.bottom_radius + altitude, d)  # (k, W)
    flux = atm.solar_irradiance * t / points  # (k, W) [W/(m^2 nm)]
    n_w = flux.shape[-1]
    out = torch.zeros(*solid_angle.shape, n_w, dtype=flux.dtype, device=flux.device)
    if layout == "latlong":
        row, col = latlong_texel(d, size)
        flat = row * (2 * size) + col
    else:
        face, row, col = cubemap_texel(d, size)
        flat = (face * size + row) * size + col
    out.view(-1, n_w).index_add_(0, flat, flux / solid_angle.reshape(-1)[flat].unsqueeze(-1))
    return out


def render_envmap(atm: Atmosphere, sun: Tensor, radiance_fn: Callable[[Tensor], Tensor], *, size: int = 512,
                  layout: str = "latlong", sun_disk: bool = False, spectral: bool = True, altitude: float = 0.0,
                  meta: dict | None = None, rows_per_chunk: int | None = None) -> EnvMap:
    """Render an environment map of ``atm`` with the sun at unit ENU vector ``sun``.

    Args:
        atm: the atmosphere (dtype and device followed).
        sun: unit vector to the sun's centre (East, North, Up), shape (3,).
        radiance_fn: ``directions (N, 3) -> spectral radiance (N, W)`` without the solar disc
            (e.g. ``SkyModel.renderer(atm, altitude)`` with the sun bound).
        size: lat-long height H (width 2H) or cube face edge N, even, 2..8192. [px]
        layout: ``latlong`` or ``cubemap``.
        sun_disk: add the solar disc by splatting (module docstring).
        spectral: keep the spectral radiance (for EXR channels ``L<nm>``).
        altitude: observer height (for the disc's transmittance and horizon). [m]
        meta: extra metadata (renderer settings, time, location).
        rows_per_chunk: directions are rendered in chunks of this many rows (bounded memory).
    """
    check_layout(layout)
    size = _check_size(size)
    dtype, device = atm.dtype, atm.device
    if layout == "latlong":
        dirs = latlong_directions(size, dtype, device)
        omega = latlong_solid_angles(size, dtype, device)
    else:
        dirs = cubemap_directions(size, dtype, device)
        omega = cubemap_solid_angles(size, dtype, device)
    flat = dirs.reshape(-1, 3)
    n_w = atm.wavelengths.shape[0]
    step = max(1, (rows_per_chunk or max(1, 2**18 // (2 * size))) * 2 * size)
    with torch.no_grad():
        rad = torch.cat([radiance_fn(flat[i:i + step]) for i in range(0, flat.shape[0], step)]).reshape(*dirs.shape[:-1], n_w)
        if sun_disk:
            rad = rad + sun_disc_splat(atm, sun, layout, size, omega, altitude)
        rgb = xyz_to_linear_srgb(spectral_to_xyz(rad, atm.wavelengths))
    zen = zenith_angle_deg(sun)
    az = math.degrees(math.atan2(float(sun[0]), float(sun[1]))) % 360.0
    np_ = lambda t: t.detach().cpu().numpy()  # noqa: E731
    rgb_np = np_(rgb)
    if not np.isfinite(rgb_np).all():
        raise ValueError("the environment map has non-finite values; nothing written")
    return EnvMap(layout=layout, rgb=rgb_np, spectral=np_(rad) if spectral else None,
                  wavelengths=np_(atm.wavelengths), directions=np_(dirs), solid_angle=np_(omega),
                  sun={"zenith_deg": zen, "azimuth_deg": az, "disk": bool(sun_disk)},
                  meta={"conventions": CONVENTIONS, **(meta or {})})


# -- files -------------------------------------------------------------------------------------------
def check_output(path: str | Path, spectral: bool = False) -> Path:
    """``path`` as a Path when its suffix is a known format (and can hold the channels asked); ValueError otherwise."""
    p = Path(path)
    if p.suffix.lower() not in SUFFIXES:
        raise ValueError(f"--out must name an .exr or .hdr file, got {p}")
    if spectral and p.suffix.lower() == ".hdr":
        raise ValueError(f"Radiance .hdr holds R, G, B only; spectral channels need an .exr file, got {p}")
    return p


def preview_path(path: str | Path) -> Path:
    """Where ``--preview`` writes: the output's name with the suffix ``.png``."""
    return Path(path).with_suffix(".png")


def write_preview(path: str | Path, rgb: np.ndarray, exposure: float | None = None) -> Path:
    """An 8-bit sRGB PNG of a linear sRGB image (H, W, 3): tone map 1 - exp(-k L), k from the 90th percentile."""
    import skimage.io  # optional at import: only previews need it (~0.3 s)

    from ..io.atomic import atomic_path

    path = Path(path)
    with atomic_path(path, ".tmp.png") as tmp:
        skimage.io.imsave(tmp, tonemap_srgb8(rgb, exposure), check_contrast=False)
    return path


def write_envmap(env: EnvMap, path: str | Path, *, preview: bool = False, extra_meta: dict | None = None) -> list[Path]:
    """Write ``env`` to ``path`` (.exr: float32 R, G, B, Y [+ L<nm>] and JSON metadata; .hdr: Radiance RGBE).

    Returns the written paths (the map, then the preview PNG when asked).
    """
    from ..io import write_exr, write_hdr

    p = check_output(path, spectral=False)
    img = env.image()
    written = []
    if p.suffix.lower() == ".exr":
        chans = {"R": img[..., 0], "G": img[..., 1], "B": img[..., 2]}
        from ..render.colour import xyz_to_srgb_matrix

        chans["Y"] = img @ np.linalg.inv(xyz_to_srgb_matrix())[1]
        if env.spectral is not None:
            spec = env.image(env.spectral)
            for k, lam in enumerate(env.wavelengths.tolist()):
                name = f"L{lam:g}"
                if name in chans:
                    raise ValueError(f"wavelengths closer than the channel names resolve ({name} twice); use a coarser grid")
                chans[name] = spec[..., k]
        meta = {"layout": env.layout, "size": env.size, "sun": env.sun, **env.meta, **(extra_meta or {}),
                "wavelengths_nm": env.wavelengths.tolist(),
                "units": {"R,G,B": "linear sRGB of XYZ with 683 lm/W (Y in cd/m^2)", "Y": "cd/m^2",
                          "L<nm>": "W/(m^2 sr nm)"}}
        if env.layout == "cubemap":
            meta["faces"] = list(CUBE_FACES)
        written.append(write_exr(p, chans, meta))
    else:
        written.append(write_hdr(p, img))
    if preview:
        written.append(write_preview(preview_path(p), img))
    return written

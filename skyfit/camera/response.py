"""Calibrated camera responses from an exposure bracket, and tabulated inverse responses.

An *inverse response* maps an encoded value ``c`` in [0, 1] (code / full-scale code) to the linear
value ``X`` in [0, 1] of the frame's full scale (the convention of :mod:`skyfit.io.photo`):
``X(1) = 1``. Two calibrations recover it, per channel, from frames of one scene at known relative
exposures ``t_j``:

- :func:`debevec_response`: Debevec & Malik 1997, "Recovering High Dynamic Range Radiance Maps from
  Photographs", SIGGRAPH 97. ``g(c) = ln X(c)`` and the log radiances ``ln E_i`` minimise eq. 5, the
  hat-weighted (eq. 4) form of eq. 3: the squared residuals of eq. 2, ``g(Z_ij) = ln E_i + ln t_j``,
  plus ``lambda`` times the weighted squared second derivative of ``g``.
- :func:`robertson_response`: Robertson, Borman & Stevenson 2003, "Estimation-theoretic approach to
  dynamic range enhancement using multiple exposures", J. Electronic Imaging 12(2) 219-228, §3:
  alternate the weighted least-squares radiance ``x_i = sum_j w_ij t_j I(y_ij) / sum_j w_ij t_j^2``
  and the response update ``I_m = mean of t_j x_i over the samples (i, j) with y_ij = m``, normalising
  ``I`` after each step. That iteration is a power iteration of a non-negative matrix; its limit (the
  Perron vector) is computed directly, as the plain iteration needs thousands of steps.

Both return a :class:`TabulatedResponse` on a grid of code levels (every code of an 8-bit frame; 256
levels for deeper frames, each sample then split between its two neighbouring levels by linear
interpolation), made monotone (cumulative maximum of ``X``: a camera's response does not decrease)
and scaled so that code 1 maps to 1.

What the frames cannot tell (Grossberg & Nayar 2003, "What can be known about the radiometric response
from images?", ECCV): the exposures are *relative*, their common scale is the radiance's; without them
the exponent of a response is unknown (the exponential ambiguity), so the calibrations refuse equal
exposures; and when every exposure ratio is the same ``r`` (a camera's +-n EV bracket) a response is
known only up to a ripple periodic in ``ln X`` with period ``ln r``, since the data only ever compare
``X`` with ``r^k X`` (:func:`constant_exposure_ratio`). Debevec's smoothness term picks the smoothest
curve; Robertson's method has no such term and ripples by ~30 % on such a bracket (tests).

Why by hand: OpenCV's ``createCalibrateDebevec`` / ``createCalibrateRobertson`` do the same, but
OpenCV is a ~60 MB dependency for one small least-squares problem and one eigenvector; numpy and
scipy.sparse do both in well under a second on a sample of pixels, and the code says what it solves.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

CALIBRATION_LEVELS: int = 256
"""Code levels of a calibrated response [1]: every code of an 8-bit frame; deeper frames are interpolated onto it."""
DEBEVEC_SMOOTHNESS: float = 1e-7
"""Weight lambda of the smoothness term of Debevec & Malik 1997 eq. 3 [1], in this module's normalisation:
objective = mean over samples of (w r)^2 + lambda * integral over c of (w(c) g''(c))^2 dc, with g = ln X, c in
[0, 1] and the hat w in [0, 1] (max 1 at c = 0.5). Measured on tests/test_photo_response.py's filmic S-curve
(Naka-Rushton, exponents 1.15-1.4; 8 bits, 1 % noise), largest error over codes 0.05-0.95 after a per-channel
scale, 6 frames 4x apart / 7 frames at irregular ratios: 2.7 / 0.3 % at 1e-8, 1.0 / 0.3 % at 3e-8, 1.2 / 1.3 %
at 1e-7, 2.4 / 2.3 % at 1e-6, 14 % at 1e-5, 58 % at 1e-4. Too little smoothing leaves the ripple a constant
exposure ratio cannot see (:func:`constant_exposure_ratio`), too much bends the toe; 1e-7 keeps a factor 10
from the first."""
DEBEVEC_PIXELS: int = 3000
"""Pixels per channel in the Debevec system [1], chosen spread over brightness (module docstring). With
``ln E_i`` eliminated in closed form the solve is a 256-column least-squares problem whatever this is."""
ROBERTSON_PIXELS: int = 20000
"""Pixels per channel used by the Robertson iteration [1] (a random subset when there are more)."""
ROBERTSON_ITERATIONS: int = 3
"""Steps of Robertson et al. 2003's update applied to the fixed point computed directly [1]; their last relative
change (``info["last_change"]``, ~1e-14) shows the result is the iteration's limit."""
MIN_CALIBRATION_PIXELS: int = 50
"""Fewest pixels per channel well exposed in two frames of different exposure for a calibration [1]:
Debevec & Malik 1997 §2.1 ask for N (P - 1) > (Zmax - Zmin) and find N ~ 50 ample for their 11 frames."""
MIN_CODE_SPAN: float = 0.5
"""Least span of the encoded values those pixels cover [1]: a curve measured over less is extrapolated over
more than half the codes, which a calibration should not pretend to know."""
MIN_EXPOSURE_RATIO: float = 1.01
"""Exposures closer than this ratio count as equal [1]: equal exposures say nothing about the response."""
CONSTANT_RATIO_TOL: float = 0.1
"""Adjacent log exposure ratios within this fraction of their mean count as one constant ratio [1]
(:func:`constant_exposure_ratio`)."""
SLOPE_FLOOR: float = 1e-3
"""Least slope dX/dc of a tabulated response [1], as a fraction of its mean slope X(1) - X(0): in the noise model of
:mod:`skyfit.io.photo` a flat part of the curve would otherwise have no quantisation noise, hence too much weight."""
CURVE_SAMPLES: int = 17
"""Points per channel of :meth:`TabulatedResponse.curve` (the compact form written to RESULT.json)."""

CHANNEL_NAMES: tuple[str, ...] = ("R", "G", "B")


class ResponseError(ValueError):
    """A response that cannot be calibrated or tabulated as asked; the message is one line (no path: the caller adds it)."""


def hat_weight(c: np.ndarray) -> np.ndarray:
    """Debevec & Malik 1997 eq. 4 on encoded values, scaled to 1 at c = 0.5: ``1 - |2c - 1|``, 0 at 0 and 1.

    Args:
        c: encoded values, shape (...). [1]

    Returns:
        Weights in [0, 1], shape (...). [1]
    """
    return np.clip(1.0 - np.abs(2.0 * np.asarray(c, np.float64) - 1.0), 0.0, 1.0)


@dataclasses.dataclass(frozen=True, eq=False)
class TabulatedResponse:
    """An inverse camera response tabulated on code levels, interpolated linearly between them.

    Attributes:
        codes: encoded values of the nodes, shape (K,), strictly increasing from 0 to 1. [1]
        values: linear values at the nodes, shape (K, C) with C = 1 (every channel) or 3 (R, G, B),
            finite, >= 0, non-decreasing along K, and 1 at code 1. [1]
        method: "debevec", "robertson" or "table".
        info: JSON-ready facts of the calibration (pixels, residuals, iterations).
    """

    codes: np.ndarray
    values: np.ndarray
    method: str = "table"
    info: dict = dataclasses.field(default_factory=dict)
    _slopes: np.ndarray = dataclasses.field(init=False, repr=False)

    def __post_init__(self):
        codes = np.asarray(self.codes, np.float64)
        values = np.asarray(self.values, np.float64)
        if values.ndim == 1:
            values = values[:, None]
        check_table(codes, values)
        if not math.isclose(values[-1].min(), 1.0, rel_tol=1e-9) or not math.isclose(values[-1].max(), 1.0, rel_tol=1e-9):
            raise ResponseError("the value at code 1 must be 1 (scale the table by its last row)")
        mean_slope = values[-1] - values[0]
        slopes = np.gradient(values, codes, axis=0, edge_order=1)
        slopes = np.maximum(slopes, SLOPE_FLOOR * mean_slope)
        object.__setattr__(self, "codes", codes)
        object.__setattr__(self, "values", values)
        object.__setattr__(self, "_slopes", slopes)

    @property
    def channels(self) -> int:
        """1 (one curve for every channel) or 3."""
        return self.values.shape[1]

    def _per_channel(self, table: np.ndarray, c, channel) -> np.ndarray:
        c = np.asarray(c, np.float64)
        if self.channels == 1:
            return np.interp(c, self.codes, table[:, 0])
        if channel is not None:
            channel = np.broadcast_to(np.asarray(channel), c.shape)
            out = np.empty(c.shape)
            for k in range(3):
                m = channel == k
                out[m] = np.interp(c[m], self.codes, table[:, k])
            return out
        cb = np.broadcast_to(c, np.broadcast_shapes(c.shape, (3,)))
        return np.stack([np.interp(cb[..., k], self.codes, table[:, k]) for k in range(3)], -1)

    def decode(self, c, channel=None) -> np.ndarray:
        """Linear values of encoded values.

        Args:
            c: encoded values in [0, 1] (clamped), shape (...). [1]
            channel: None, or the channel (0, 1, 2) of each value, shape of ``c``. With None a
                three-channel table reads ``c``'s last axis as R, G, B (``c`` broadcast to (..., 3)).

        Returns:
            Linear values X, shape of ``c`` (or (..., 3) as said). [1]
        """
        return self._per_channel(self.values, c, channel)

    def slope(self, c, channel=None) -> np.ndarray:
        """dX/dc at encoded values (central differences at the nodes, interpolated; floored at
        :data:`SLOPE_FLOOR` of the mean slope). Arguments and shape as :meth:`decode`. [1]"""
        return self._per_channel(self._slopes, c, channel)

    def curve(self, n: int = CURVE_SAMPLES) -> dict:
        """The response at ``n`` evenly spaced codes, JSON-ready: ``{"codes": [...], "R": [...], ...}``
        (one key ``"X"`` for a one-channel table)."""
        c = np.linspace(0.0, 1.0, n)
        out = {"codes": [round(float(v), 6) for v in c]}
        names = CHANNEL_NAMES if self.channels == 3 else ("X",)
        for k, name in enumerate(names):
            out[name] = [float(f"{v:.6g}") for v in np.interp(c, self.codes, self.values[:, k])]
        return out


def check_table(codes: np.ndarray, values: np.ndarray) -> None:
    """Raise :class:`ResponseError` (one line) unless ``codes`` (K,) and ``values`` (K, C) form an inverse response:
    K >= 2, C in (1, 3), codes finite, strictly increasing, from 0 to 1; values finite, >= 0, non-decreasing per
    channel and rising somewhere."""
    if codes.ndim != 1 or values.ndim != 2 or values.shape[0] != codes.shape[0]:
        raise ResponseError(f"codes of shape {codes.shape} and values of shape {values.shape} do not form a table")
    if codes.size < 2:
        raise ResponseError(f"a table needs at least 2 rows, has {codes.size}")
    if values.shape[1] not in (1, 3):
        raise ResponseError(f"a table has 1 or 3 value columns (one curve, or R, G, B), not {values.shape[1]}")
    if not np.isfinite(codes).all():
        raise ResponseError(f"code column: {int((~np.isfinite(codes)).sum())} value(s) are NaN or infinite")
    if not np.isfinite(values).all():
        bad = np.argwhere(~np.isfinite(values))[0]
        raise ResponseError(f"value at code {codes[bad[0]]:g} is {values[tuple(bad)]} (values must be finite)")
    if codes.min() < 0 or codes.max() > 1:
        hint = " (divide 8-bit codes by 255)" if codes.max() > 1 else ""
        raise ResponseError(f"codes must lie in [0, 1], found {codes.min():g} .. {codes.max():g}{hint}")
    if (np.diff(codes) <= 0).any():
        k = int(np.argmax(np.diff(codes) <= 0))
        raise ResponseError(f"codes must increase strictly, but code {codes[k + 1]:g} follows {codes[k]:g}")
    if codes[0] != 0.0 or codes[-1] != 1.0:
        raise ResponseError(f"codes must run from 0 to 1, run from {codes[0]:g} to {codes[-1]:g}")
    if (values < 0).any():
        k = np.argwhere(values < 0)[0]
        raise ResponseError(f"value at code {codes[k[0]]:g} is {values[tuple(k)]:g}; linear values must be >= 0")
    dec = np.diff(values, axis=0) < 0
    if dec.any():
        k, ch = np.argwhere(dec)[0]
        name = CHANNEL_NAMES[ch] if values.shape[1] == 3 else "X"
        raise ResponseError(f"not monotone: {name} falls from {values[k, ch]:g} at code {codes[k]:g} to "
                            f"{values[k + 1, ch]:g} at code {codes[k + 1]:g}")
    if (values[-1] <= values[0]).any():
        raise ResponseError("a response must rise from code 0 to code 1; this one is flat")


def table_response(codes, values, method: str = "table", info: dict | None = None) -> TabulatedResponse:
    """A :class:`TabulatedResponse` from a user's table, checked (:func:`check_table`) and scaled so code 1 -> 1.

    Args:
        codes: encoded values, shape (K,), strictly increasing from 0 to 1. [1]
        values: linear values, shape (K,), (K, 1) or (K, 3) (R, G, B), any positive scale. [relative]

    Returns:
        The response, values divided by their value at code 1.
    """
    codes = np.asarray(codes, np.float64)
    values = np.asarray(values, np.float64)
    if values.ndim == 1:
        values = values[:, None]
    check_table(codes, values)
    return TabulatedResponse(codes, values / values[-1], method=method, info=dict(info or {}))


# --------------------------------------------------------------------------
# Calibration data
# --------------------------------------------------------------------------

def _calibration_data(codes, exposures, max_code: float, usable):
    """(c (P, N, C) float in [0, 1], w (P, N, C) hat weights with unusable values at 0, t (P,)) after the checks."""
    z = np.asarray(codes)
    if z.ndim < 3:
        raise ResponseError(f"frame codes need shape (frames, ..., channels), got {z.shape}")
    p, ch = z.shape[0], z.shape[-1]
    if ch not in (1, 3):
        raise ResponseError(f"frames have {ch} channels; a response is calibrated on 1 or 3")
    if p < 2:
        raise ResponseError(f"a calibration needs at least 2 frames of different exposure, got {p}")
    t = np.asarray(exposures, np.float64).reshape(-1)
    if t.shape != (p,):
        raise ResponseError(f"{t.size} exposure(s) for {p} frames")
    if not (np.isfinite(t).all() and (t > 0).all()):
        raise ResponseError(f"exposures must be positive and finite, got {t.tolist()}")
    if t.max() / t.min() < MIN_EXPOSURE_RATIO:
        raise ResponseError("the frames have equal exposures; a calibration needs frames of different exposure")
    if not max_code > 0:
        raise ResponseError(f"max_code must be positive, got {max_code}")
    c = z.reshape(p, -1, ch).astype(np.float64) / float(max_code)
    w = hat_weight(c)
    if usable is not None:
        u = np.asarray(usable, bool)
        if u.shape != z.shape:
            raise ResponseError(f"usable mask of shape {u.shape} for codes of shape {z.shape}")
        w = np.where(u.reshape(p, -1, ch), w, 0.0)
    return c, w, t


def _useful(w: np.ndarray, t: np.ndarray, name: str, c: np.ndarray) -> np.ndarray:
    """Pixels (N,) of one channel well exposed in two frames of different exposure; ResponseError when too few."""
    seen = w > 0
    tmax = np.where(seen, t[:, None], 0.0).max(0)
    tmin = np.where(seen, t[:, None], np.inf).min(0)
    useful = seen.sum(0) >= 2
    useful &= tmax >= MIN_EXPOSURE_RATIO * tmin
    n = int(useful.sum())
    if n < MIN_CALIBRATION_PIXELS:
        raise ResponseError(f"channel {name}: only {n} pixel(s) are well exposed in two frames of different exposure; "
                            f"a calibration needs at least {MIN_CALIBRATION_PIXELS} (a bracket with more overlap)")
    cv = c[:, useful][seen[:, useful]]
    span = float(cv.max() - cv.min())
    if span < MIN_CODE_SPAN:
        raise ResponseError(f"channel {name}: the well-exposed values span only codes {cv.min():.2f} .. {cv.max():.2f}; "
                            f"a calibration needs a span of at least {MIN_CODE_SPAN:g} of full scale")
    return useful


def _interp_rows(c: np.ndarray, levels: int) -> tuple[np.ndarray, np.ndarray]:
    """Lower level index (int) and the fraction toward the next, same shape as c: c = (k0 + f) / (levels - 1)."""
    s = np.clip(c, 0.0, 1.0) * (levels - 1)
    k0 = np.minimum(np.floor(s).astype(np.int64), levels - 2)
    return k0, s - k0


def _spread_sample(c: np.ndarray, w: np.ndarray, useful: np.ndarray, n_max: int, rng) -> np.ndarray:
    """Indices of up to n_max useful pixels spread over brightness: in each frame, pixels well exposed there are
    binned by their code (64 bins) and the same number drawn from every bin."""
    idx = np.flatnonzero(useful)
    if idx.size <= n_max:
        return idx
    p = c.shape[0]
    n_bins = 64
    per = max(1, n_max // (p * n_bins))
    chosen = []
    for j in range(p):
        ok = idx[w[j, idx] > 0]
        if ok.size == 0:
            continue
        b = np.minimum((c[j, ok] * n_bins).astype(np.int64), n_bins - 1)
        order = rng.permutation(ok.size)
        ok, b = ok[order], b[order]
        # the first `per` pixels (in random order) of every bin
        sort = np.argsort(b, kind="stable")
        ok, b = ok[sort], b[sort]
        first = np.searchsorted(b, b, side="left")
        rank = np.arange(b.size) - first
        chosen.append(ok[rank < per])
    sel = np.unique(np.concatenate(chosen)) if chosen else idx[:0]
    if sel.size > n_max:
        sel = np.sort(rng.choice(sel, n_max, replace=False))
    return sel


def constant_exposure_ratio(exposures) -> float | None:
    """The common ratio of consecutive distinct exposures when they step by one factor (a +-n EV bracket), else None.

    With one ratio ``r`` between all frames, a response is known from the frames only up to a ripple periodic in
    ``ln X`` with period ``ln r`` (the data compare ``X`` with ``r^k X`` only): Grossberg & Nayar 2003, "What can be
    known about the radiometric response from images?", the fractal ambiguity. Debevec's smoothness term picks
    the smoothest such curve; Robertson's method has none, so on such a bracket its curve ripples (29-32 % on the
    tests' 4x bracket).

    Args:
        exposures: relative exposures, shape (P,). [relative]

    Returns:
        The ratio (> 1), or None when the steps differ by more than :data:`CONSTANT_RATIO_TOL`.
    """
    t = np.unique(np.asarray(exposures, np.float64))
    steps = []
    for a, b in zip(t[:-1], t[1:]):
        if b >= MIN_EXPOSURE_RATIO * a:
            steps.append(math.log(b / a))
    if not steps:
        return None
    steps = np.array(steps)
    mean = float(steps.mean())
    return math.exp(mean) if float(np.abs(steps - mean).max()) <= CONSTANT_RATIO_TOL * mean else None


# --------------------------------------------------------------------------
# Debevec & Malik 1997
# --------------------------------------------------------------------------

def _debevec_channel(c: np.ndarray, w: np.ndarray, t: np.ndarray, levels: int, smoothness: float):
    """g = ln X on the levels for one channel: c, w of shape (P, S) (selected pixels), t (P,). Returns (g, rms)."""
    p, s = c.shape
    k0, f = _interp_rows(c, levels)
    lt = np.log(t)[:, None]
    w2 = w * w
    big_w = w2.sum(0)                                       # (S,)
    keep = big_w > 0
    c, w, w2, k0, f, big_w = c[:, keep], w[:, keep], w2[:, keep], k0[:, keep], f[:, keep], big_w[keep]
    s = c.shape[1]
    # Eq. 2 rows w_ij (a_ij . g - ln E_i - ln t_j) with a_ij the interpolation row of Z_ij. ln E_i enters only its
    # own pixel's rows, so it is eliminated exactly: ln E_i = sum_j w_ij^2 (a_ij . g - ln t_j) / sum_j w_ij^2, and
    # the rows become w_ij ((a_ij - abar_i) . g - (ln t_j - lbar_i)): a dense (P S, levels) least-squares problem.
    pix = np.broadcast_to(np.arange(s), (p, s))
    abar = np.zeros((s, levels))
    np.add.at(abar, (pix.ravel(), k0.ravel()), (w2 * (1 - f)).ravel())
    np.add.at(abar, (pix.ravel(), (k0 + 1).ravel()), (w2 * f).ravel())
    abar /= big_w[:, None]
    lbar = (w2 * lt).sum(0) / big_w
    rows = np.flatnonzero((w > 0).ravel())                  # (P S,) flattened (j, i): only measured samples
    jj, ii = np.unravel_index(rows, (p, s))
    wr = w[jj, ii]
    a = -abar[ii] * wr[:, None]
    r_idx = np.arange(rows.size)
    a[r_idx, k0[jj, ii]] += wr * (1 - f[jj, ii])
    a[r_idx, k0[jj, ii] + 1] += wr * f[jj, ii]
    b = wr * (lt[jj, 0] - lbar[ii])
    norm = 1.0 / math.sqrt(rows.size)                       # the data term as a mean: lambda does not scale with S
    # Smoothness (eq. 3 with eq. 4's weights): sqrt(lambda h) w(u_k) (g_{k-1} - 2 g_k + g_{k+1}) / h^2, k = 1..K-2.
    h = 1.0 / (levels - 1)
    u = np.arange(1, levels - 1) * h
    sm = np.zeros((levels - 2, levels))
    k = np.arange(levels - 2)
    coef = math.sqrt(smoothness * h) * hat_weight(u) / h**2
    sm[k, k], sm[k, k + 1], sm[k, k + 2] = coef, -2 * coef, coef
    # The gauge: data and smoothness are blind to g + const; fix g(mid) = 0 (Debevec & Malik's g(Z_mid) = 0).
    gauge = np.zeros((1, levels))
    gauge[0, levels // 2] = 1.0
    lhs = np.vstack([a * norm, sm, gauge])
    rhs = np.concatenate([b * norm, np.zeros(levels - 2), [0.0]])
    g = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    resid = (a @ g - b) / wr                                # ln residual of eq. 2 per sample
    rms = float(np.sqrt(np.sum(wr**2 * resid**2) / np.sum(wr**2)))
    return g, rms


def debevec_response(codes, exposures, *, max_code: float = 255, usable=None, levels: int = CALIBRATION_LEVELS,
                     smoothness: float = DEBEVEC_SMOOTHNESS, pixels: int = DEBEVEC_PIXELS, seed: int = 0) -> TabulatedResponse:
    """Inverse response by Debevec & Malik 1997 (eqs. 2-5), per channel.

    Pixels well exposed in two frames of different exposure are sampled spread over brightness
    (:data:`DEBEVEC_PIXELS`); ``g = ln X`` on ``levels`` code levels and the pixels' log radiances
    minimise the hat-weighted squared residuals of eq. 2 (a sample between two levels reads ``g``
    linearly interpolated) plus ``smoothness`` times the weighted squared second derivative of ``g``
    (module constant :data:`DEBEVEC_SMOOTHNESS`); the log radiances are eliminated in closed form and
    ``g`` solved by dense least squares with ``g(0.5) = 0``. Then ``X = exp(g)`` is made monotone
    (cumulative maximum) and scaled to ``X(1) = 1``.

    Args:
        codes: frame codes, shape (P, ..., C) with P >= 2 frames and C in (1, 3), in 0 .. max_code.
        exposures: relative exposure of each frame, shape (P,). [relative]
        max_code: code of full scale (255 for 8 bits, 65535 for 16). [1]
        usable: False where a value must not be used (clipped, black, masked), shape of ``codes``.
        levels: code levels of the result. [1]
        smoothness: lambda of eq. 3 in this module's normalisation (:data:`DEBEVEC_SMOOTHNESS`). [1]
        pixels: pixels per channel in the system. [1]
        seed: of the pixel sample.

    Returns:
        A :class:`TabulatedResponse` with ``levels`` nodes and C channels; ``info`` holds the pixels
        used and the weighted rms residual of eq. 2 per channel (ln units).

    Raises:
        ResponseError: fewer than 2 frames, equal exposures, or a channel with fewer than
            :data:`MIN_CALIBRATION_PIXELS` pixels well exposed in two frames of different exposure, or
            whose well-exposed values span less than :data:`MIN_CODE_SPAN`.
    """
    c, w, t = _calibration_data(codes, exposures, max_code, usable)
    if not smoothness >= 0 or levels < 3:
        raise ResponseError(f"smoothness must be >= 0 and levels >= 3, got {smoothness}, {levels}")
    names = CHANNEL_NAMES if c.shape[-1] == 3 else ("X",)
    gs, info = [], {"method": "Debevec & Malik 1997", "smoothness": smoothness, "levels": levels, "frames": int(c.shape[0]),
                    "constant_ratio": constant_exposure_ratio(t), "pixels": {}, "rms_log_residual": {}}
    for k, name in enumerate(names):
        ck, wk = c[..., k], w[..., k]
        useful = _useful(wk, t, name, ck)
        sel = _spread_sample(ck, wk, useful, pixels, np.random.default_rng(seed))  # one seed per channel: a channel's
        # curve does not depend on the others
        g, rms = _debevec_channel(ck[:, sel], wk[:, sel], t, levels, smoothness)
        gs.append(g)
        info["pixels"][name] = int(sel.size)
        info["rms_log_residual"][name] = rms
    x = _monotone_unit(np.exp(np.stack(gs, -1)))
    return TabulatedResponse(np.linspace(0.0, 1.0, levels), x, method="debevec", info=info)


def _monotone_unit(x: np.ndarray) -> np.ndarray:
    """Cumulative maximum along the levels (a response does not decrease), then divided by the value at code 1."""
    x = np.maximum.accumulate(x, axis=0)
    return x / x[-1]


# --------------------------------------------------------------------------
# Robertson, Borman & Stevenson 2003
# --------------------------------------------------------------------------

def _fill_log(ln_i: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """ln I at every level: measured levels kept, gaps interpolated linearly, the ends extrapolated linearly from
    the nearest 8 measured levels (a least-squares line), as Debevec's smoothness term extrapolates g."""
    k = np.arange(ln_i.size)
    km = k[measured]
    out = np.interp(k, km, ln_i[measured])
    for side in (slice(0, 8), slice(-8, None)):
        ks = km[side]
        if ks.size >= 2:
            slope, icpt = np.polyfit(ks, ln_i[ks], 1)
            ends = (k < km[0]) if side.start == 0 else (k > km[-1])
            out[ends] = icpt + slope * k[ends]
    return out


def _robertson_operator(c: np.ndarray, w: np.ndarray, t: np.ndarray, levels: int):
    """One Robertson iteration on one channel as a matrix: I_new = M I on the measured levels.

    c, w of shape (P, S); t (P,). A sample (j, i) reads I between its two levels with the interpolation row a_ij.
    The radiance x_i = sum_j w_ij t_j a_ij . I / sum_j w_ij t_j^2 and the update I_m = sum a_ijm t_j x_i / sum a_ijm
    are both linear in I, so M = C^-1 A^T T G D^-1 G^T W T A (A: samples x levels interpolation, T, W: diag of t_j,
    w_ij; G: samples -> pixels; D, C: the two denominators). Returns (M restricted to the measured levels, mask).
    """
    from scipy import sparse  # here: scipy loads in ~0.5 s, only calibrations need it

    s = c.shape[1]
    k0, f = _interp_rows(c, levels)
    jj, ii = np.nonzero(w > 0)
    n = jj.size
    rows = np.concatenate([np.arange(n), np.arange(n)])
    a = sparse.csr_matrix((np.concatenate([1 - f[jj, ii], f[jj, ii]]), (rows, np.concatenate([k0[jj, ii], k0[jj, ii] + 1]))),
                          shape=(n, levels))
    ts, ws = t[jj], w[jj, ii]
    g = sparse.csr_matrix((np.ones(n), (np.arange(n), ii)), shape=(n, s))
    d = np.bincount(ii, ws * ts * ts, s)
    radiance = sparse.diags(1.0 / np.where(d > 0, d, 1.0)) @ (g.T @ sparse.diags(ws * ts) @ a)   # (S, levels): x = R I
    cnt = np.asarray(a.sum(0)).ravel()
    measured = cnt > 1e-9
    m = (a.T @ sparse.diags(ts) @ g) @ radiance.toarray()                                     # (levels, levels)
    m = m[measured][:, measured] / cnt[measured, None]
    return m, measured


def _robertson_channel(c: np.ndarray, w: np.ndarray, t: np.ndarray, levels: int, iterations: int):
    """I on the levels for one channel (c, w of shape (P, S); t (P,)).

    Robertson's iteration, normalised at every step, is a power iteration of the non-negative matrix M of
    :func:`_robertson_operator`: it converges to M's Perron vector at the rate of M's second eigenvalue,
    which is close to 1 when a level's update is dominated by its own sample (a pixel's brightest
    well-exposed frame weighs t^2): 0.93-0.97 on the tests' 7 frames at irregular ratios, 0.9996-0.9999 on
    their 6 frames 4x apart, i.e. hundreds to thousands of steps. The Perron vector is
    therefore taken directly (np.linalg.eig of the <= 256 x 256 matrix), then ``iterations`` of the
    published update are applied (their last relative change is reported: ~1e-14 shows it is the fixed point).
    Returns (I scaled to I(1) = 1 after filling unmeasured levels, last change).
    """
    m, measured = _robertson_operator(c, w, t, levels)
    vals, vecs = np.linalg.eig(m)
    top = int(np.argmax(vals.real))
    v = vecs[:, top].real
    v = v * np.sign(v[np.argmax(np.abs(v))])
    if not (v > 0).all():
        raise ResponseError(f"{int((v <= 0).sum())} code level(s) are not linked to the others by any pixel seen in two "
                            "frames; a calibration needs a bracket whose frames overlap in brightness")
    delta = 0.0
    for _ in range(iterations):
        new = m @ v
        new *= v.sum() / new.sum()
        delta = float(np.max(np.abs(new / v - 1)))
        v = new
    ln_i = np.full(levels, np.nan)
    ln_i[measured] = np.log(v)
    ln_i = _fill_log(ln_i, measured)
    return np.exp(ln_i - ln_i[-1]), delta


def robertson_response(codes, exposures, *, max_code: float = 255, usable=None, levels: int = CALIBRATION_LEVELS,
                       iterations: int = ROBERTSON_ITERATIONS, pixels: int = ROBERTSON_PIXELS,
                       seed: int = 0) -> TabulatedResponse:
    """Inverse response by Robertson, Borman & Stevenson 2003 (§3), per channel.

    Robertson et al. alternate the weighted least-squares radiance of every pixel,
    ``x_i = sum_j w_ij t_j I(y_ij) / sum_j w_ij t_j^2``, and the response at every level,
    ``I_m = mean of t_j x_i over the samples with y_ij = m`` (here a sample between two levels counts
    for both in proportion), normalising ``I`` after each step. Both steps are linear in ``I``, so the
    iteration is a power iteration of a non-negative matrix and converges to its Perron vector; that
    vector is computed directly and ``iterations`` steps of the update applied to it
    (:func:`_robertson_channel` says why: the plain iteration needs thousands of steps). The weights are
    Debevec & Malik's hat (:func:`hat_weight`; Robertson et al. use a Gaussian bump in the same role).
    Levels no sample reaches are interpolated in ``ln I``, the ends extrapolated linearly. Then ``I`` is
    made monotone (cumulative maximum) and scaled to ``I(1) = 1``.

    Args:
        codes, exposures, max_code, usable, levels, seed: as :func:`debevec_response`.
        iterations: steps of the published update applied to the fixed point (:data:`ROBERTSON_ITERATIONS`). [1]
        pixels: most pixels per channel (:data:`ROBERTSON_PIXELS`; a random subset of those usable). [1]

    Returns:
        A :class:`TabulatedResponse`; ``info`` holds the pixels and the last step's largest relative
        change of ``I`` per channel.

    Raises:
        ResponseError: as :func:`debevec_response`, and code levels no pixel links to the others.
    """
    c, w, t = _calibration_data(codes, exposures, max_code, usable)
    if levels < 3 or iterations < 0:
        raise ResponseError(f"levels must be >= 3 and iterations >= 0, got {levels}, {iterations}")
    names = CHANNEL_NAMES if c.shape[-1] == 3 else ("X",)
    curves = []
    info = {"method": "Robertson, Borman & Stevenson 2003", "levels": levels, "frames": int(c.shape[0]),
            "iterations": iterations, "constant_ratio": constant_exposure_ratio(t), "pixels": {}, "last_change": {}}
    for k, name in enumerate(names):
        ck, wk = c[..., k], w[..., k]
        idx = np.flatnonzero(_useful(wk, t, name, ck))
        if idx.size > pixels:
            idx = np.sort(np.random.default_rng(seed).choice(idx, pixels, replace=False))
        i_curve, delta = _robertson_channel(ck[:, idx], wk[:, idx], t, levels, iterations)
        curves.append(i_curve)
        info["pixels"][name] = int(idx.size)
        info["last_change"][name] = delta
    x = _monotone_unit(np.stack(curves, -1))
    return TabulatedResponse(np.linspace(0.0, 1.0, levels), x, method="robertson", info=info)


__all__ = [
    "CALIBRATION_LEVELS",
    "DEBEVEC_SMOOTHNESS",
    "ResponseError",
    "TabulatedResponse",
    "check_table",
    "constant_exposure_ratio",
    "debevec_response",
    "hat_weight",
    "robertson_response",
    "table_response",
]

"""Memory and time a job will need, estimated from its sizes before any work (docs/reliability.md).

A render, a table precomputation, a fit or a sampling run costs in proportion to sizes the user
gives: pixels, wavelengths, view-ray samples, the optical-depth integrator's inner samples,
scattering orders, table texels, walkers x steps. :func:`check` refuses an :class:`Estimate`
that needs more memory than this machine has available or would run longer than
:data:`MAX_SECONDS`, with the estimate and the sizes behind it in one line; commands offer
``--force`` to run anyway.

The time constants are nominal rates of the project's 2-core CPU (float32, two threads, an idle
machine), measured with ``skyfit render`` and :func:`skyfit.scattering.multiple.precompute`;
a faster machine finishes sooner, a busy one later. On an accelerator the rates are divided by
:data:`ACCELERATOR_SPEEDUP`. The estimates are meant to catch sizes off by orders of
magnitude (a typo, an exponent too many), not to predict run times to a few percent.
"""
from __future__ import annotations

import dataclasses
import math
import os

GiB: float = float(2**30)

MAX_SECONDS: float = 3600.0
"""Longest estimated render or table precomputation accepted without ``--force`` [s]."""
MAX_RUN_SECONDS: float = 86400.0
"""Longest estimated fit or sampling run accepted without ``--force`` [s]: those are long by nature."""
BASE_MEMORY_BYTES: float = 0.5 * GiB
"""A skyfit process before its arrays: the interpreter, torch, numpy [bytes]."""
SECONDS_PER_RAY_UNIT: float = 5e-9
"""Single scattering: seconds per view-ray sample and per unit of work there (6 per wavelength
+ 24 + the integrator's inner samples; skyfit.scattering.single's working-set count) [s]."""
SECONDS_PER_TEXEL_ORDER: float = 5e-6
"""Bruneton's tables: seconds per scattering texel, wavelength and order (the density over 16 x 32
directions and the 50-sample view integral of each order) [s]."""
ACCELERATOR_SPEEDUP: float = 50.0
"""Rates on a CUDA device relative to the CPU (an H200 built the default tables in 4 s, docs/benchmarks.md)."""
CHUNK_BYTES: float = 128e6
"""The renderers' working memory per chunk of rays or texels on the CPU [bytes]."""
TEMPORARIES: float = 3.0
"""Working memory per chunk relative to the chunk's nominal size (temporaries of the expressions)."""
AUTOGRAD: float = 3.0
"""Memory of a differentiated evaluation relative to the working set of a plain one (saved activations;
2.8 measured for a 20,096-pixel float64 fit) [1]."""
QUADRATURE_INTEGRATORS = ("trapezoid", "midpoint", "simpson", "gauss")


class ResourceError(ValueError):
    """A job too large for this machine (memory) or too long to run unasked (time)."""


@dataclasses.dataclass(frozen=True)
class Estimate:
    """Memory and time of a job.

    Attributes:
        what: the job, for messages ("render", "export-lut tables").
        memory_bytes: peak memory. [bytes]
        seconds: run time on this machine. [s]
        detail: the sizes the estimate comes from, for messages.
    """

    what: str
    memory_bytes: float
    seconds: float
    detail: str = ""

    def __add__(self, other: "Estimate") -> "Estimate":
        """Two stages in a row: the larger memory, the summed time."""
        detail = "; ".join(d for d in (self.detail, other.detail) if d)
        return Estimate(self.what, max(self.memory_bytes, other.memory_bytes), self.seconds + other.seconds, detail)


def format_bytes(n: float) -> str:
    """``n`` bytes as MiB, GiB, TiB ... with three significant digits."""
    for unit, size in (("EiB", 2**60), ("PiB", 2**50), ("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{n / 2**20:.2g} MiB"


def format_seconds(s: float) -> str:
    """``s`` seconds as s, min, h, days or years."""
    if s < 120:
        return f"{s:.3g} s"
    if s < 7200:
        return f"{s / 60:.3g} min"
    if s < 2 * 86400:
        return f"{s / 3600:.3g} h"
    if s < 2 * 365 * 86400:
        return f"{s / 86400:.3g} days"
    return f"{s / (365 * 86400):.3g} years"


def available_memory(device: str = "cpu") -> float | None:
    """Memory a job can use now [bytes]: MemAvailable of /proc/meminfo (else the physical memory)
    on the CPU, the device's free memory on CUDA; None when unknown."""
    dev = str(device)
    if dev.startswith("cuda"):
        try:
            import torch  # only for a CUDA device (this module is otherwise free of torch)

            free, _total = torch.cuda.mem_get_info(torch.device(dev))
            return float(free)
        except Exception:  # no CUDA here, or an unknown index: the device check reports it
            return None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except (OSError, ValueError, IndexError):
        pass
    try:
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def _speed(device: str) -> float:
    return 1.0 if str(device).split(":")[0] == "cpu" else ACCELERATOR_SPEEDUP


def integrator_cost(settings: dict | None) -> tuple[float, float, str]:
    """(inner work per view-ray sample, one-off setup work, description) of an integrator's settings.

    Quadrature integrators integrate each optical depth with ``samples`` inner nodes per view
    sample and layer; ``bruneton_lut`` builds a mu_size x r_size table with ``samples`` nodes per
    texel, ``spline`` a height_points x distance_points grid; the closed forms cost nothing extra.
    """
    s = dict(settings or {})
    name = s.get("name", "")
    if name in QUADRATURE_INTEGRATORS:
        n = float(s.get("samples", 64))
        return 16.0 * n, 0.0, f"{name} with {n:.0f} inner samples"
    if name == "bruneton_lut":
        cells = float(s.get("mu_size", 256)) * float(s.get("r_size", 64)) * float(s.get("samples", 500))
        return 0.0, 40.0 * cells, f"bruneton_lut of {cells:.3g} table samples"
    if name == "spline":
        cells = float(s.get("height_points", 50)) * float(s.get("distance_points", 20))
        return 0.0, 4000.0 * cells, ""
    return 0.0, 0.0, ""


def single_scattering_estimate(rays: float, wavelengths: int, view_samples: int, integrator: dict | None = None, *,
                               dtype_bytes: int = 4, evaluations: float = 1.0, autograd: bool = False,
                               device: str = "cpu", what: str = "render") -> Estimate:
    """A single-scattering render of ``rays`` view rays (skyfit.scattering.single's working-set count).

    Args:
        rays: view directions rendered. [1]
        wavelengths: W. [1]
        view_samples: nodes of the view-ray integral. [1]
        integrator: the optical-depth integrator's settings (``integrator.settings()``).
        dtype_bytes: 4 (float32) or 8 (float64).
        evaluations: renders of the same rays (a fit's function evaluations). [1]
        autograd: the renders are differentiated (memory of every chunk is kept).
    """
    inner, setup, idesc = integrator_cost(integrator)
    per_sample = 6.0 * wavelengths + 24.0 + inner
    per_ray = view_samples * per_sample * dtype_bytes
    if autograd:
        work_bytes = rays * per_ray * AUTOGRAD
    else:
        work_bytes = max(per_ray, min(CHUNK_BYTES, rays * per_ray)) * TEMPORARIES
    out_bytes = rays * wavelengths * dtype_bytes * 3.0  # the spectra, their copy into the image, XYZ/RGB and the output
    memory = BASE_MEMORY_BYTES + work_bytes + out_bytes
    units = rays * view_samples * per_sample * evaluations * (3.0 if autograd else 1.0) + setup
    detail = f"{rays:.4g} rays x {view_samples} view samples x {wavelengths} wavelengths"
    if idesc:
        detail += f", {idesc}"
    if evaluations != 1:
        detail += f", about {evaluations:.3g} evaluations"
    return Estimate(what, memory, units * SECONDS_PER_RAY_UNIT / _speed(device), detail)


def tables_estimate(table_sizes, wavelengths: int, orders: int, *, dtype_bytes: int = 4, device: str = "cpu",
                    what: str = "scattering tables") -> Estimate:
    """Bruneton's precomputed tables (:func:`skyfit.scattering.multiple.precompute`) of ``orders`` orders.

    Args:
        table_sizes: (R, MU, MUS, NU) of the 4-D scattering table.
        wavelengths: W. [1]
        orders: scattering orders >= 1. [1]
    """
    texels = float(math.prod(int(v) for v in table_sizes))
    values = texels * wavelengths
    # single Rayleigh and Mie, the running sum, Delta J and Delta S of the order at hand, its predecessor
    memory = BASE_MEMORY_BYTES + 6.0 * values * dtype_bytes + CHUNK_BYTES * TEMPORARIES
    seconds = values * max(orders, 1) * SECONDS_PER_TEXEL_ORDER / _speed(device)
    sizes = "x".join(str(int(v)) for v in table_sizes)
    return Estimate(what, memory, seconds, f"{sizes} texels x {wavelengths} wavelengths x {orders} orders")


def chain_estimate(walkers: int, steps: int, ndim: int, *, what: str = "sample") -> Estimate:
    """The emcee chain in memory: positions and log-probabilities of every walker at every step."""
    memory = BASE_MEMORY_BYTES + float(walkers) * float(steps) * (ndim + 1) * 8.0 * 2.0
    return Estimate(what, memory, 0.0, f"{walkers} walkers x {steps} steps x {ndim} parameters")


def check(estimate: Estimate, *, force: bool = False, hint: str = "", max_seconds: float = MAX_SECONDS,
          memory_bytes: float | None = None, device: str = "cpu") -> Estimate:
    """``estimate`` when it fits; ResourceError with the estimate and its sizes otherwise.

    Args:
        force: accept any estimate (the user's ``--force``).
        hint: what to change, appended to the message (e.g. "reduce --view-samples or add --force").
        max_seconds: longest accepted run. [s]
        memory_bytes: memory available (default :func:`available_memory` of ``device``). [bytes]
    """
    if force:
        return estimate
    tail = f"; {hint}" if hint else ""
    avail = available_memory(device) if memory_bytes is None else memory_bytes
    if avail is not None and estimate.memory_bytes > avail:
        raise ResourceError(f"{estimate.what} would need about {format_bytes(estimate.memory_bytes)} of memory "
                            f"({estimate.detail}), more than the {format_bytes(avail)} available{tail}")
    if estimate.seconds > max_seconds:
        raise ResourceError(f"{estimate.what} would take about {format_seconds(estimate.seconds)} on this machine "
                            f"({estimate.detail}), more than the {format_seconds(max_seconds)} accepted unasked{tail}")
    return estimate

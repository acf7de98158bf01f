"""Prior densities of the fit parameters for ``skyfit sample`` (docs/uncertainty.md).

Defaults (:data:`DEFAULT_PRIORS`) come from the parameter table: each
:class:`~skyfit.fit.parameters.ParameterSpec`'s ``prior`` (log-uniform for the positive scale
parameters, uniform over the physical range for the bounded ones); the config's
``sample: priors:`` section overrides any (``{name: {kind: uniform|loguniform|normal|lognormal, ...}}``).
Outside a prior's support log p = -inf (STYLE.md, sampler boundaries); NaN is an error.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Mapping

import torch
from torch import Tensor

from .model import FitProblem
from .parameters import PARAMETERS, FitError, ParameterSpec


class SampleError(FitError):
    """A sampling run that cannot start or resume as asked (one-line message, exit status 2).

    Defined here, below every sampling module that raises it; :mod:`skyfit.fit.sample` re-exports it."""


PRIOR_KINDS = ("uniform", "loguniform", "normal", "lognormal")


@dataclasses.dataclass(frozen=True)
class Prior:
    """Prior density of one physical parameter.

    Attributes:
        kind: ``uniform`` (lo, hi), ``loguniform`` (lo, hi > lo > 0; density ~ 1/v),
            ``normal`` (mean, sd) or ``lognormal`` (mean and sd of log v).
        lo, hi: support of the uniform kinds. [parameter unit]
        mean, sd: of the normal kinds. [unit, or log unit]
    """

    kind: str
    lo: float = -math.inf
    hi: float = math.inf
    mean: float = 0.0
    sd: float = 1.0

    def __post_init__(self):
        if self.kind not in PRIOR_KINDS:
            raise SampleError(f"unknown prior kind {self.kind!r}; valid: {', '.join(PRIOR_KINDS)}")
        if self.kind in ("uniform", "loguniform") and not (self.lo < self.hi and math.isfinite(self.lo) and math.isfinite(self.hi)):
            raise SampleError(f"{self.kind} prior needs finite lo < hi, got lo={self.lo}, hi={self.hi}")
        if self.kind == "loguniform" and not self.lo > 0:
            raise SampleError(f"loguniform prior needs lo > 0, got {self.lo}")
        if self.kind in ("normal", "lognormal") and not self.sd > 0:
            raise SampleError(f"{self.kind} prior needs sd > 0, got {self.sd}")

    def log_density(self, v: Tensor) -> Tensor:
        """log pi(v) (normalised), -inf outside the support, same shape as v."""
        ninf = torch.full_like(v, -math.inf)
        if self.kind == "uniform":
            inside = (v > self.lo) & (v < self.hi)
            return torch.where(inside, torch.full_like(v, -math.log(self.hi - self.lo)), ninf)
        if self.kind == "loguniform":
            inside = (v > self.lo) & (v < self.hi)
            safe = torch.where(inside, v, torch.ones_like(v))
            return torch.where(inside, -torch.log(safe) - math.log(math.log(self.hi / self.lo)), ninf)
        if self.kind == "normal":
            return -0.5 * ((v - self.mean) / self.sd) ** 2 - math.log(self.sd * math.sqrt(2 * math.pi))
        pos = v > 0
        lv = torch.log(torch.where(pos, v, torch.ones_like(v)))
        val = -0.5 * ((lv - self.mean) / self.sd) ** 2 - math.log(self.sd * math.sqrt(2 * math.pi)) - lv
        return torch.where(pos, val, ninf)

    def settings(self) -> dict:
        if self.kind in ("uniform", "loguniform"):
            return {"kind": self.kind, "lo": self.lo, "hi": self.hi}
        return {"kind": self.kind, "mean": self.mean, "sd": self.sd}


def default_prior(spec: ParameterSpec) -> Prior | None:
    """The default prior of a parameter from its table entry (``ParameterSpec.prior``): a kind alone
    spans the parameter's range (lo, hi); (kind, lo, hi) gives its own support; None: no default."""
    if spec.prior is None:
        return None
    if isinstance(spec.prior, str):
        return Prior(spec.prior, spec.lo, spec.hi)
    kind, lo, hi = spec.prior
    return Prior(kind, lo, hi)


DEFAULT_PRIORS: dict[str, Prior] = {n: default_prior(s) for n, s in PARAMETERS.items() if s.prior is not None}
"""Default prior of each parameter (physical units, docs/uncertainty.md), derived from :data:`PARAMETERS`
(:func:`default_prior`): the transform's range (log-uniform for positive scale parameters) where that range
is physical, else a wide one. ``ground_albedo_scale``'s upper bound is replaced by 1 / max(config albedo)
in :func:`make_priors`."""


def make_priors(problem: FitProblem, overrides: Mapping | None = None) -> dict[str, Prior]:
    """Priors of the free parameters: :data:`DEFAULT_PRIORS` with the config's ``sample.priors`` overrides."""
    p = problem.param
    out = {}
    overrides = dict(overrides or {})
    unknown = [n for n in overrides if n not in PARAMETERS]
    if unknown:
        raise SampleError(f"unknown parameter(s) {unknown} in sample.priors; valid: {', '.join(PARAMETERS)}")
    for n in p.free:
        if n not in DEFAULT_PRIORS and n not in overrides:
            raise SampleError(f"{n} has no default prior; give one in the config's sample.priors.{n}")
        pr = DEFAULT_PRIORS.get(n)
        if n == "ground_albedo_scale":
            pr = dataclasses.replace(pr, hi=p._albedo_scale_hi)
        if n in overrides:
            spec = overrides[n]
            if not isinstance(spec, Mapping) or "kind" not in spec:
                raise SampleError(f"sample.priors.{n} must be a mapping with a 'kind' ({', '.join(PRIOR_KINDS)})")
            extra = set(spec) - {"kind", "lo", "hi", "mean", "sd"}
            if extra:
                raise SampleError(f"sample.priors.{n}: unknown key(s) {sorted(extra)}; valid: kind, lo, hi, mean, sd")
            try:
                pr = Prior(str(spec["kind"]), **{k: float(v) for k, v in spec.items() if k != "kind"})
            except (TypeError, ValueError) as e:
                raise SampleError(f"sample.priors.{n}: {e}") from None
        out[n] = pr
    return out

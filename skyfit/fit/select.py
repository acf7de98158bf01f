"""Model selection: fit a ladder of nested sky models and keep the one the data require.

``skyfit fit --select`` (docs/selection.md). The ladder is :data:`RUNGS`, data rather than
code: each rung names the model component it adds and the parameters it frees,

=================  =====================================================  ===========================================
rung               what changes                                           parameters freed
=================  =====================================================  ===========================================
``rayleigh``       Rayleigh only: aerosol and ozone off, single scat.     rayleigh_scale (+ the instrument's nuisance)
``mie``            + aerosol (the config's Mie, then fitted)              mie_aod_550, mie_g, mie_angstrom_alpha
``ozone``          + ozone absorption of the config                       ozone_column where that parameter exists
``multiple``       + multiple scattering (SkyModel ``orders`` 1 -> 2)      --
``ground_albedo``  + a fitted grey ground albedo                          ground_albedo
``scale_heights``  free instead of fixed scale heights                    rayleigh_scale_height, mie_scale_height
``two_term_hg``    + a backward lobe: f HG(g1) + (1 - f) HG(g2)           mie_g2, mie_hg_weight
``lognormal_mie``  phase, spectrum and albedo of a log-normal Mie aerosol  mie_median_radius, mie_geometric_sigma
                   instead of g and the Angstrom exponent                 (fixes mie_g, mie_angstrom_alpha, mie_g2,
                                                                          mie_hg_weight: derived)
``coarse_mode``    + a coarse log-normal mode of the same spheres         mie_coarse_radius, mie_fine_fraction
                   (AERONET's two modes; its sigma_g stays 1.9)
``boundary_layer`` + aerosol density 1 up to h_mix, exponential above     mie_mixing_height
``height_fog``     flat-Earth height-fog optical depth (Ishiyama 2018)    -- (only where the scene qualifies)
=================  =====================================================  ===========================================

The ladder is climbed by forward selection in this fixed order: each rung is the *best
model so far* plus its component, fitted warm-started from that model's optimum (new
parameters, and bounded ones the smaller model drove to a bound, :func:`at_bound`, start
at the config's values). A rung is accepted when it lowers BIC by more than
:data:`MIN_DELTA_BIC` (2) below the best so far; a rejected rung's component is left out of
every later rung ("the ladder drops it"). Then, backward, each component of the best model
is removed in turn while that does not raise BIC by 2 or more (a component taken early as a
stand-in for a later one is dropped again). Every rung is nested in the rungs built on it
(Mie off is beta_M = 0, ozone off is a zero column, single scattering is the multiple term
switched off; the two-term phase is the single lobe at f -> 1 and the boundary layer the exponential
at h_mix -> 0, limits of their open ranges). ``lognormal_mie`` is the one rung that is not nested: it
replaces g and alpha (and a two-term lobe) by the two parameters of the size distribution, from which
Mie theory derives them (Rung ``drops``); ``coarse_mode`` is nested in it (fine fraction 1), so it is compared with the best model so far at equal or
smaller k, by the same BIC margin. The chosen model is the last accepted one: the lowest BIC, unless a bigger
model is lower by less than 2.

Criterion (Schwarz 1978)::

    BIC = 2 nll + k ln n,    n = used training elements (sample x channel)

with the Gaussian negative log-likelihood of :mod:`skyfit.fit.losses` (``rho = squared``:
loss = r^2 / 2 per element, r = residual / sigma_eff, sigma_eff = sigma for the ``linear``
residual, sigma / o for ``log``, o for ``relative``)::

    sigma="known":   nll = n L + C                             k = free parameters
    sigma="scaled":  nll = n / 2 (1 + ln(2 L)) + C             k = free parameters + 1

L the mean loss per element at the optimum (noise_scale 1) and C = sum ln sigma_eff +
(n / 2) ln 2 pi, the same for every rung. ``scaled`` (the default) treats sigma as known
only up to one common factor s, profiled in closed form (s^2 = 2 L: for rho = squared the
optimum in the other parameters does not depend on s); ``known`` trusts sigma as given,
right for synthetic data whose noise is known, while on real skies, where model error
dwarfs the noise, it favours ever larger models. Robust losses (huber, cauchy) are not
likelihoods and are refused.

Held-out pixels: a deterministic random ``heldout`` fraction (default 20 %) of each
observation's used samples (seeded; all channels of a sample go together) is masked out of
every fit and scored afterwards: the held-out loss (mean r^2 / 2, the prediction error) and
the predictive Gaussian nll per element (``scaled``: with the training s, so it also judges
how well s was calibrated). The held-out choice is the fitted rung of lowest held-out loss;
the report says whether it agrees with BIC and, when not, the summed held-out loss
difference with its paired standard error.

Height fog: the ``height_fog`` integrator is the flat-Earth column of Ishiyama 2018 and
refuses rays whose flat-Earth error would exceed 1 % (:mod:`skyfit.transmittance.fog`).
The rung is fitted only when that check passes for every used view ray at the start point
(a ground observer looking along short, steep rays); otherwise it is reported as skipped
with the integrator's reason. A sky dome seen from the ground never qualifies (its
low-elevation rays are hundreds of km long).
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Mapping, Sequence

import torch

from ..atmosphere import Atmosphere
from .data import Observation
from .losses import Loss
from .model import FitProblem, SkyModel
from .optimise import FitOptions, OptimiseResult, fit
from .parameters import (COARSE_MODE, LOGNORMAL_DERIVED, LOGNORMAL_MIE, NUISANCE, ORIENTATION, PARAMETERS, FitError,
                         Parameterisation, inside_bounds)
from .problem import atmosphere_config, fit_settings, initial_values, prepare
from .results import check_result_path, write_result

SIGMA_MODES = ("scaled", "known")
MIN_DELTA_BIC: float = 2.0
"""The bigger of two nested models must have a BIC lower by more than this to be preferred: an addition is
accepted when it lowers BIC by more than 2, a removal when it raises BIC by less than 2. Below 2 Kass & Raftery
1995 (Sec. 3.2) call the evidence "not worth more than a bare mention"; it also absorbs the optimiser's round-off
between equivalent models (the height-fog column against Chapman's on steep rays, ozone in a renderer without it)."""
HELDOUT_DEFAULT: float = 0.2
"""Fraction of each observation's used samples held out of the fits and scored afterwards [1]."""


@dataclasses.dataclass(frozen=True)
class Rung:
    """One rung of the ladder.

    Attributes:
        name: label in reports.
        adds: one line: what the rung changes.
        free: parameters the rung frees (names not in :data:`PARAMETERS` are ignored, and
            ``mie_*`` names while the aerosol is off).
        changes: model state the rung sets: ``mie`` / ``ozone`` (bool: component on),
            ``orders`` (SkyModel orders), ``integrator`` (optical-depth integrator name).
        drops: parameters the rung fixes again because its component derives them (lognormal_mie: g, alpha).
    """

    name: str
    adds: str
    free: tuple[str, ...] = ()
    changes: Mapping[str, object] = dataclasses.field(default_factory=dict)
    drops: tuple[str, ...] = ()


RUNGS: tuple[Rung, ...] = (
    Rung("rayleigh", "Rayleigh scattering only (no aerosol, no ozone), single scattering", ("rayleigh_scale",),
         {"mie": False, "ozone": False, "orders": 1}),
    Rung("mie", "+ aerosol (Mie): optical depth, asymmetry and Angstrom exponent fitted",
         ("mie_aod_550", "mie_g", "mie_angstrom_alpha"), {"mie": True}),
    Rung("ozone", "+ ozone absorption (the config's tent layer)", ("ozone_column",), {"ozone": True}),
    Rung("multiple", "+ multiple scattering (SkyModel orders 2)", (), {"orders": 2}),
    Rung("ground_albedo", "+ fitted grey ground albedo (else the config's)", ("ground_albedo",)),
    Rung("scale_heights", "free Rayleigh and aerosol scale heights (else the config's)",
         ("rayleigh_scale_height", "mie_scale_height")),
    Rung("two_term_hg", "+ a backward lobe of the aerosol phase: two-term Henyey-Greenstein (g1 = mie_g)",
         ("mie_g2", "mie_hg_weight")),
    Rung("lognormal_mie", "aerosol phase, Angstrom exponent and albedo from a log-normal size distribution (Mie theory) "
         "instead of fitted g and alpha", ("mie_median_radius", "mie_geometric_sigma"),
         drops=("mie_g", "mie_angstrom_alpha", "mie_g2", "mie_hg_weight")),
    Rung("coarse_mode", "+ a coarse log-normal mode of the same spheres (AERONET's fine and coarse modes): its median "
         "radius and the fine mode's share of the 550 nm extinction", ("mie_coarse_radius", "mie_fine_fraction"),
         drops=("mie_g", "mie_angstrom_alpha", "mie_g2", "mie_hg_weight")),
    Rung("boundary_layer", "+ a well-mixed aerosol layer: density 1 up to a mixing height, exponential above",
         ("mie_mixing_height",)),
    Rung("height_fog", "flat-Earth height-fog optical depth (Ishiyama 2018), short-range scenes only", (),
         {"integrator": "height_fog"}),
)
"""The ladder in the order it is climbed (module table)."""


AT_BOUND: float = 1e-3
"""A bounded parameter whose position u in its range (sigmoid(x) of the interval transforms) is within this of 0
or 1 is *at its bound*: its gradient is ~u (1 - u) times smaller, so a warm start there cannot leave it [1]."""


def at_bound(name: str, value) -> bool:
    """True when ``value`` of the ``interval``/``loginterval`` parameter ``name`` lies within AT_BOUND of a bound."""
    spec = PARAMETERS[name]
    if spec.transform not in ("interval", "loginterval") or not math.isfinite(spec.hi):
        return False
    vals = value if isinstance(value, (list, tuple)) else [value]
    for v in vals:
        u = ((v - spec.lo) / (spec.hi - spec.lo) if spec.transform == "interval"
             else math.log(v / spec.lo) / math.log(spec.hi / spec.lo))
        if not AT_BOUND < u < 1 - AT_BOUND:
            return True
    return False


def evidence_label(delta_bic: float) -> str:
    """Kass & Raftery 1995 (Sec. 3.2) scale for a BIC difference in favour of a model."""
    d = abs(delta_bic)
    return "weak" if d < 2 else "positive" if d < 6 else "strong" if d < 10 else "very strong"


def heldout_split(observations: Sequence[Observation], fraction: float, seed: int = 0
                  ) -> tuple[list[Observation], list[Observation] | None]:
    """(training, held-out) copies of ``observations`` with complementary masks.

    Each used sample is held out with probability ``fraction`` (a seeded draw per
    observation, so the split depends only on ``seed`` and the data's order); 0 holds
    out nothing (held-out None).
    """
    if not 0 <= fraction < 1:
        raise FitError(f"held-out fraction must be in [0, 1), got {fraction}")
    if fraction == 0:
        return list(observations), None
    gen = torch.Generator().manual_seed(int(seed))
    train, held = [], []
    for o in observations:
        u = torch.rand(o.mask.shape[0], generator=gen, dtype=torch.float64).to(o.mask.device)
        h = o.mask & (u < fraction)
        t = o.mask & ~h
        if not bool(h.any()) or not bool(t.any()):
            raise FitError(f"{o.source}: {o.n_samples} used sample(s) are too few to hold out {fraction:.0%}")
        train.append(dataclasses.replace(o, mask=t))
        held.append(dataclasses.replace(o, mask=h))
    return train, held


def log_sigma_sum(observations: Sequence[Observation], loss: Loss) -> tuple[float, int]:
    """(sum of ln sigma_eff over the used elements, their number n): the constant C of the nll is
    this + (n / 2) ln 2 pi (module docstring)."""
    total, n = 0.0, 0
    for o in observations:
        m = o.mask
        s, v = o.sigma[m], o.values[m]
        if loss.residual == "log":
            s = s / v
        elif loss.residual == "relative":
            s = v
        total += float(torch.log(s).sum())
        n += int(s.numel())
    return total, n


def gaussian_nll(mean_loss: float, n: int, log_sigma: float, sigma: str) -> tuple[float, float]:
    """(nll, noise scale s) of ``n`` elements whose mean loss (r^2 / 2) is ``mean_loss`` (module docstring)."""
    c = log_sigma + 0.5 * n * math.log(2 * math.pi)
    if sigma == "known":
        return n * mean_loss + c, 1.0
    s2 = max(2.0 * mean_loss, 1e-300)
    return 0.5 * n * (1.0 + math.log(s2)) + c, math.sqrt(s2)


@dataclasses.dataclass
class _State:
    mie: bool = False
    ozone: bool = False
    orders: int = 1
    integrator: str | None = None
    free: tuple[str, ...] = ()
    applied: tuple[str, ...] = ()  # names of the rungs this model is built of, in ladder order

    def components(self) -> list[str]:
        out = ["rayleigh"] + (["mie"] if self.mie else []) + (["ozone"] if self.ozone else [])
        out += ["multiple"] if self.orders > 1 else []
        return out + ([self.integrator] if self.integrator else [])

    def same_model(self, other: "_State") -> bool:
        return (self.mie, self.ozone, self.orders, self.integrator, set(self.free)) == (
            other.mie, other.ozone, other.orders, other.integrator, set(other.free))


class OutsideDomain(ValueError):
    """A parameter vector whose atmosphere is invalid (a bounded transform saturated in floating point)."""


class _LadderProblem(FitProblem):
    """A FitProblem whose invalid-atmosphere points are *outside the domain* (a plain ValueError), so that the
    optimiser steps back from them as from a point the integrator refuses, instead of stopping the fit.

    When a component is not in the data its shape parameters are unidentified (the aerosol
    asymmetry g once the aerosol optical depth tends to 0): quasi-Newton steps along such a flat
    direction saturate the interval transform, and g = lo + (hi - lo) sigmoid(x) rounds to -1 exactly.
    """

    def spectra(self, phys: dict, atm: Atmosphere | None = None) -> list:
        if atm is None:
            try:
                atm = self.param.atmosphere(phys)
            except FitError as e:
                raise OutsideDomain(str(e)) from None
        return super().spectra(phys, atm)


class Ladder:
    """Builds and fits the rungs of :data:`RUNGS` for one set of observations.

    Args:
        atmosphere: the config's full atmosphere (aerosol and ozone as configured).
        model: renderer settings; its ``orders`` is the ladder's (1 below ``multiple``).
        observations: the data (their masks: the samples to use).
        loss: a Gaussian loss (``rho = squared``).
        nuisance_free: instrument parameters fitted in every rung (e.g. exposure).
        per_observation: nuisance names with one value per observation.
        initial: user starting values (physical, SI) of any parameter.
        options: optimiser settings of each rung's fit.
        sigma: ``"scaled"`` or ``"known"`` (module docstring).
        heldout: fraction of samples held out (0: none).
        seed: seed of the held-out split.
        base_sun_distance_au: as :class:`~skyfit.fit.model.FitProblem`.
        rungs: the ladder (default :data:`RUNGS`).
        min_delta_bic: BIC margin a bigger model needs (:data:`MIN_DELTA_BIC`).
    """

    def __init__(self, atmosphere: Atmosphere, model: SkyModel, observations: Sequence[Observation], loss: Loss, *,
                 nuisance_free: Sequence[str] = ("exposure",), per_observation: Sequence[str] | None = None,
                 initial: Mapping | None = None, options: FitOptions | None = None, sigma: str = "scaled",
                 heldout: float = HELDOUT_DEFAULT, seed: int = 0, base_sun_distance_au: float = 1.0,
                 rungs: Sequence[Rung] = RUNGS, min_delta_bic: float = MIN_DELTA_BIC):
        if sigma not in SIGMA_MODES:
            raise FitError(f"unknown sigma mode {sigma!r}; valid: {', '.join(SIGMA_MODES)}")
        if loss.rho != "squared":
            raise FitError(f"model selection needs a Gaussian likelihood (loss squared, log or relative), "
                           f"got {loss.name!r}: a robust loss has no BIC")
        bad = [n for n in nuisance_free if n not in NUISANCE or n == "noise_scale"]
        if bad:
            raise FitError(f"selection fits the atmosphere's parameters itself; the free list may only add "
                           f"exposure and sun offsets, got {bad} (noise_scale: see the sigma mode)")
        self.atmosphere = atmosphere
        self.model = model
        self.observations = list(observations)
        self.loss = loss
        self.nuisance_free = tuple(nuisance_free)
        self.per_observation = per_observation
        self.initial = dict(initial or {})
        self.options = options or FitOptions(starts=1)
        self.sigma = sigma
        self.heldout = heldout
        self.rungs = tuple(rungs)
        if not min_delta_bic >= 0:
            raise FitError(f"min_delta_bic must be >= 0, got {min_delta_bic}")
        self.min_delta_bic = float(min_delta_bic)
        self.base_sun_distance_au = base_sun_distance_au
        self.train, self.held = heldout_split(self.observations, heldout, seed)
        self.log_sigma_train, self.n_train = log_sigma_sum(self.train, loss)
        self.log_sigma_held, self.n_held = log_sigma_sum(self.held, loss) if self.held else (0.0, 0)

    # -- building ---------------------------------------------------------------------
    def base_for(self, st: _State) -> Atmosphere:
        """The config atmosphere with the components that ``st`` has off removed."""
        atm, kw = self.atmosphere, {}
        if not st.mie:
            kw["mie_extinction"] = torch.zeros_like(atm.mie_extinction)
            kw["mie_scattering"] = torch.zeros_like(atm.mie_scattering)
        if not st.ozone:
            kw["ozone_absorption"] = None
        if atm.mie_phase == "lognormal_mie" and not set(st.free) & {*LOGNORMAL_MIE, *COARSE_MODE}:
            # below the lognormal_mie rung g and alpha are fitted: Henyey-Greenstein with the distribution's g (550 nm)
            kw["mie_phase"] = "henyey_greenstein"
        return atm.replace(**kw) if kw else atm

    def model_for(self, st: _State) -> SkyModel:
        m = dataclasses.replace(self.model, orders=st.orders)
        if st.integrator is not None:
            from ..transmittance import make_integrator

            m = dataclasses.replace(m, integrator=make_integrator(st.integrator))
        return m

    def _param(self, st: _State, values: Mapping) -> Parameterisation:
        base = self.base_for(st)
        init = {n: v for n, v in self.initial.items() if st.mie or not n.startswith("mie_")}
        if set(st.free) & {*LOGNORMAL_MIE, *COARSE_MODE}:  # the size distribution derives these
            init = {n: v for n, v in init.items() if n not in LOGNORMAL_DERIVED}
        if st.mie and "mie_aod_550" in st.free and "mie_aod_550" not in init and "mie_beta_550" not in init:
            if not float(base.mie_extinction.max()) > 0:  # a config without aerosol: start from AOD 0.1
                base = self.atmosphere.replace(mie_extinction=torch.full_like(base.mie_extinction, 0.1 / float(base.mie_scale_height)),
                                               mie_scattering=torch.full_like(base.mie_extinction, 0.09 / float(base.mie_scale_height)))
        if "mie_aod_550" in st.free:
            init.pop("mie_beta_550", None)  # one of the two
        return Parameterisation(base, list(st.free), len(self.observations), self.per_observation, {**init, **values})

    def problem(self, st: _State, values: Mapping, observations: Sequence[Observation] | None = None) -> FitProblem:
        """The FitProblem of state ``st`` starting at physical ``values`` (default data: the training split)."""
        obs = self.train if observations is None else observations
        return _LadderProblem(self._param(st, values), self.model_for(st), obs, self.loss, self.base_sun_distance_au)

    def _child(self, parent: _State, rung: Rung) -> tuple[_State, list[str]]:
        ch = dict(rung.changes)
        st = dataclasses.replace(parent, mie=bool(ch.get("mie", parent.mie)), ozone=bool(ch.get("ozone", parent.ozone)),
                                 orders=int(ch.get("orders", parent.orders)),
                                 integrator=ch.get("integrator", parent.integrator))  # type: ignore[arg-type]
        added = [n for n in rung.free if n in PARAMETERS and n not in parent.free and (st.mie or not n.startswith("mie_"))]
        kept = parent.free if not added else tuple(n for n in parent.free if n not in rung.drops)
        st.free = tuple(kept) + tuple(added)
        st.applied = tuple(parent.applied) + (rung.name,)
        return st, added

    def _build(self, names: Sequence[str]) -> _State:
        """The model of the rungs ``names`` applied in ladder order to the starting model."""
        st = _State(free=tuple(self.nuisance_free))
        by = {r.name: r for r in self.rungs}
        for n in names:
            st, _ = self._child(st, by[n])
        return st

    def _skip_reason(self, parent: _State, st: _State) -> str | None:
        if st.same_model(parent):
            return "changes nothing on top of the best model so far"
        if st.ozone and not parent.ozone and self.atmosphere.ozone_absorption is None:
            return "the config has no ozone"
        return None  # height fog: the integrator's own regime check decides (_fog_check)

    # -- climbing -----------------------------------------------------------------------
    def run(self, progress: bool = False) -> dict:
        """Fit the ladder; the selection report (module docstring) with ``_best`` = (state, OptimiseResult, problem).

        Forward: each rung on top of the best model so far. Backward: then each component of
        the best model is removed in turn (warm-started from it) while that lowers BIC, so that
        a component accepted early only as a stand-in for a later one (aerosol absorbing the
        ozone band, say) is dropped again (stepwise selection).
        """
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=len(self.rungs), desc="select", unit="rung", leave=False)
        self._rows: list[dict] = []
        self._fits: dict[str, tuple[_State, OptimiseResult, FitProblem]] = {}
        self._best: str | None = None
        self._best_bic = math.inf
        start = _State(free=tuple(self.nuisance_free))  # the first rung's changes define the starting model
        try:
            for rung in self.rungs:
                parent = start if self._best is None else self._fits[self._best][0]
                st, added = self._child(parent, rung)
                self._try(rung.name, rung.adds, "add", parent, st, added, check=self._best is not None)
                if bar is not None:
                    bar.update(1)
                    if "bic" in self._rows[-1]:
                        bar.set_postfix_str(f"{rung.name} BIC {self._rows[-1]['bic']:.1f}")
            improved = True
            while improved:
                improved = False
                best_state = self._fits[self._best][0]
                for name in best_state.applied[1:]:
                    st = self._build([n for n in best_state.applied if n != name])
                    label = f"{self._best} - {name}"
                    if label in self._fits or any(r["name"] == label for r in self._rows):
                        continue
                    removed = [n for n in best_state.free if n not in st.free]
                    if self._try(label, f"without {name}", "remove", best_state, st, removed, check=True):
                        improved = True
                        break
        finally:
            if bar is not None:
                bar.close()
        rows, best_name, best_bic = self._rows, self._best, self._best_bic
        if best_name is None:
            raise FitError("no rung of the ladder could be fitted")
        for r in rows:
            if "bic" in r:
                r["delta_bic"] = r["bic"] - best_bic
        fitted = [r for r in rows if "bic" in r]
        held_choice = min(fitted, key=lambda r: r["heldout_loss"])["name"] if self.held else None
        return {
            "criterion": "BIC = 2 nll + k ln n",
            "sigma": self.sigma,
            "loss": self.loss.settings(),
            "n_train": self.n_train,
            "n_heldout": self.n_held,
            "heldout_fraction": self.heldout,
            "rungs": rows,
            "chosen": best_name,
            "components": self._fits[best_name][0].components(),
            "heldout_choice": held_choice,
            "heldout_agrees": None if held_choice is None else held_choice == best_name,
            "heldout_margin": None if held_choice is None else self._heldout_margin(best_name, held_choice),
            "why": self._why(rows, best_name),
            "_best": self._fits[best_name],
        }

    def _try(self, name: str, adds: str, step: str, parent: _State, st: _State, changed: list[str], check: bool) -> bool:
        """Fit model ``st`` warm-started from ``parent``'s optimum; record its row; True when it becomes the best."""
        parent_name = self._best
        row = {"name": name, "adds": adds, "step": step, "parent": parent_name, "components": st.components(),
               "free": list(st.free), ("added" if step == "add" else "removed"): changed, "orders": st.orders,
               "integrator": st.integrator or self.model.integrator.settings().get("name")}
        reason = self._skip_reason(parent, st) if check else None
        same = next((n for n, (other, _, _) in self._fits.items() if other.same_model(st)), None)
        if reason is None and same is not None:
            reason = f"the same model as '{same}', fitted already (BIC {next(r['bic'] for r in self._rows if r['name'] == same):.1f})"
        problem = None
        if reason is None:
            warm = {} if parent_name is None else self._fits[parent_name][1].parameters
            values = {n: warm[n] for n in st.free if n in warm and n in parent.free}
            stuck = [n for n, v in values.items() if at_bound(n, v)]
            for n in stuck:  # a bounded parameter the parent drove to its bound restarts at the config's value
                del values[n]
            if stuck:
                row["restarted"] = stuck
            try:
                problem = self.problem(st, values)
            except (FitError, ValueError) as e:
                reason = str(e).splitlines()[0]
            if problem is not None and st.integrator == "height_fog":
                reason = self._fog_check(problem)
        if reason is not None:
            self._rows.append({**row, "skipped": reason, "accepted": False})
            return False
        t0, c0 = time.perf_counter(), time.process_time()
        # Rungs are compared by BIC, so each needs its global optimum: with the optimiser left at auto the ladder
        # uses Adam + L-BFGS; Levenberg-Marquardt from the same start stopped in a local minimum of the HG rung
        # on a plain-HG sky (loss 2.30 against 1.72 for the nested two-term rung: 848 in BIC the wrong way)
        opts = self.options if self.options.method != "auto" else dataclasses.replace(self.options, method="lbfgs")
        try:
            res = fit(problem, opts)
        except (FitError, ValueError, RuntimeError) as e:  # the rung's fit left the model's domain
            self._rows.append({**row, "failed": str(e).splitlines()[0], "accepted": False,
                               "seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0})
            return False
        seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
        self._fits[name] = (st, res, problem)
        row.update(self._score(st, res, problem))
        row.update(seconds=seconds, cpu_seconds=cpu, convergence={k: res.convergence.get(k) for k in (
            "converged", "reason", "iterations", "evaluations_total", "grad_norm")})
        best = self._best_bic
        row["delta_bic_parent"] = None if parent_name is None else row["bic"] - best
        margin = self.min_delta_bic if step == "add" else -self.min_delta_bic
        row["accepted"] = parent_name is None or row["bic"] < best - margin
        if row["accepted"]:
            self._best, self._best_bic = name, row["bic"]
        self._rows.append(row)
        return row["accepted"]

    def _heldout_margin(self, chosen: str, other: str) -> dict | None:
        """Held-out loss (r^2 / 2 per element) of ``chosen`` minus ``other``, summed over the held-out elements,
        with its paired standard error sqrt(n) std(d): is the held-out preference for ``other`` beyond noise?"""
        if chosen == other:
            return None
        d = self._heldout_elements(chosen) - self._heldout_elements(other)
        return {"versus": other, "loss_difference": float(d.sum()), "standard_error": float(d.std() * math.sqrt(d.numel())),
                "n": int(d.numel())}

    def _heldout_elements(self, name: str) -> torch.Tensor:
        """Per-element loss of rung ``name``'s optimum on the held-out pixels, shape (n_heldout,)."""
        st, res, problem = self._fits[name]
        hp = FitProblem(problem.param, problem.model, self.held, self.loss, self.base_sun_distance_au)
        with torch.no_grad():
            preds = hp.predict(res.x)
            vals = [self.loss(p, o.values[o.mask], o.sigma[o.mask], reduction="none").reshape(-1)
                    for p, o in zip(preds, hp.observations)]
        return torch.cat(vals)

    def _fog_check(self, problem: FitProblem) -> str | None:
        try:
            with torch.no_grad():
                problem.objective(problem.param.initial_vector(problem.param.base.dtype, problem.param.base.device))
        except ValueError as e:
            return f"the scene is outside the flat-Earth regime: {str(e).splitlines()[0]}"
        return None

    def _score(self, st: _State, res: OptimiseResult, problem: FitProblem) -> dict:
        k = problem.param.size + (1 if self.sigma == "scaled" else 0)
        nll, s = gaussian_nll(res.loss, self.n_train, self.log_sigma_train, self.sigma)
        out = {"k": k, "n": self.n_train, "loss": res.loss, "nll": nll, "noise_scale": s,
               "bic": 2 * nll + k * math.log(self.n_train), "parameters": {n: res.parameters[n] for n in st.free},
               "all_parameters": res.parameters}
        if self.held:
            hp = FitProblem(problem.param, problem.model, self.held, self.loss, self.base_sun_distance_au)
            with torch.no_grad():
                lh = float(hp.objective(res.x))
            # predictive nll per element: r^2 / (2 s^2) + ln s + ln sigma_eff + ln(2 pi) / 2
            out["heldout_loss"] = lh
            out["heldout_nll"] = lh / s**2 + math.log(s) + (self.log_sigma_held + 0.5 * self.n_held * math.log(2 * math.pi)) / self.n_held
        return out

    @staticmethod
    def _why(rows: list[dict], chosen: str) -> str:
        by = {r["name"]: r for r in rows}
        c = by[chosen]
        lowest = min((r for r in rows if "bic" in r), key=lambda r: r["bic"])
        parts = [f"'{chosen}' ({' + '.join(c['components'])}): BIC {c['bic']:.1f}, k = {c['k']}"
                 + (", the lowest" if lowest is c else f"; '{lowest['name']}' is {c['bic'] - lowest['bic']:.1f} lower, "
                    f"less than the {MIN_DELTA_BIC:g} a bigger model needs")]
        if c["parent"] is not None:
            d = by[c["parent"]]["bic"] - c["bic"]
            size = "smaller" if c.get("step") == "add" else "bigger"
            parts.append(f"{d:+.1f} against the {size} model '{c['parent']}' ({evidence_label(d)})")
        for r in rows:
            if r.get("parent") == chosen and "bic" in r:
                d = r["bic"] - c["bic"]
                what = "adding" if r.get("step") == "add" else "dropping"
                comp = r["name"] if r.get("step") == "add" else r["name"].split(" - ")[-1]
                parts.append(f"{what} '{comp}': ΔBIC {d:+.1f} ({evidence_label(d)})")
        skipped = [f"'{r['name']}' skipped ({r['skipped']})" for r in rows if "skipped" in r]
        skipped += [f"'{r['name']}' failed ({r['failed']})" for r in rows if "failed" in r]
        return "; ".join(parts + skipped)


def strip_private(report: dict) -> dict:
    """The report without its in-memory entries (for JSON); ``all_parameters`` dropped from the rung rows."""
    out = {k: v for k, v in report.items() if not k.startswith("_")}
    out["rungs"] = [{k: v for k, v in r.items() if k != "all_parameters"} for r in report["rungs"]]
    return out


def format_table(report: dict) -> str:
    """The rung table as aligned text (one line per rung)."""
    head = f"{'rung':22s} {'k':>3s} {'loss':>11s} {'held-out':>11s} {'BIC':>12s} {'dBIC':>9s} {'cpu s':>7s}  status"
    lines = [head]
    for r in report["rungs"]:
        if "bic" not in r:
            why = f"skipped: {r['skipped']}" if "skipped" in r else f"failed: {r['failed']}"
            lines.append(f"{r['name']:22s} {'':>3s} {'':>11s} {'':>11s} {'':>12s} {'':>9s} {'':>7s}  {why}")
            continue
        status = "chosen" if r["name"] == report["chosen"] else "accepted" if r["accepted"] else "rejected"
        held = r.get("heldout_loss")
        lines.append(f"{r['name']:22s} {r['k']:3d} {r['loss']:11.5g} {'' if held is None else format(held, '11.5g'):>11s} "
                     f"{r['bic']:12.1f} {r['delta_bic']:+9.1f} {r['cpu_seconds']:7.1f}  {status}")
    return "\n".join(lines)


def selected_config(config: dict, components: Sequence[str]) -> dict:
    """The config of the chosen model: aerosol (angstrom_beta 0) and ozone removed when the ladder dropped them,
    so that ``skyfit evaluate`` rebuilds the chosen atmosphere."""
    cfg = atmosphere_config(config)
    if "mie" not in components:
        mie = dict(cfg.get("mie") or {})
        mie.pop("extinction_550", None)
        mie["angstrom_beta"] = 0.0
        cfg["mie"] = mie
    if "ozone" not in components:
        cfg.pop("ozone", None)
    return cfg


SELECT_NUISANCE = ("exposure",) + ORIENTATION


def run_select(data, config: dict, out, *, overrides: dict | None = None, config_source: str = "",
               kider_site: dict | None = None, plots: bool = True, progress: bool = False, laplace: bool = False,
               device="cpu") -> dict:
    """``skyfit fit --select``: climb the ladder on DATA, refit the chosen model on every pixel, write RESULT.json.

    Same arguments and RESULT.json as :func:`skyfit.fit.run.run_fit`, plus ``result["selection"]``
    (every rung: loss, held-out loss, k, BIC, delta BIC, parameters, time; the choice and why).
    The result's ``config``, ``model``, ``integrator`` and ``free`` are the chosen model's, so
    ``skyfit evaluate`` rebuilds it. Of the flags' free list only the instrument's parameters
    (exposure, sun offsets) are used: the ladder frees the atmosphere's. The config's ``orders``
    is ignored (the ``multiple`` rung decides it); its ``multiple`` method and LUT sizes are kept.
    """
    t0 = time.perf_counter()
    out = check_result_path(out)
    prep = prepare(data, config, fit_settings(config.get("fit"), overrides), kider_site=kider_site, orders=1,
                   device=device)
    s, observations = prep.settings, prep.observations
    rings = any("ring" in o.metadata for o in observations)
    nuisance = [n for n in (s.free or []) if n in SELECT_NUISANCE] if s.free is not None else \
        ["exposure"] + (["sun_azimuth_offset"] if rings else [])
    per = s.per_observation
    options = s.options()
    sigma = getattr(s, "select_sigma", "scaled")
    heldout = getattr(s, "select_heldout", HELDOUT_DEFAULT)
    ladder = Ladder(prep.base, prep.model, observations, prep.loss, nuisance_free=nuisance, per_observation=per,
                    initial=initial_values(s, observations, nuisance, per), options=options, sigma=sigma,
                    heldout=heldout, seed=s.seed, base_sun_distance_au=prep.base_dist)
    report = ladder.run(progress=progress)
    st, res_train, _ = report["_best"]
    # the chosen model on every pixel, warm-started from its fit on the training pixels
    problem = ladder.problem(st, {n: inside_bounds(n, res_train.parameters[n]) for n in st.free}, observations)
    res = fit(problem, dataclasses.replace(options, starts=1, progress=progress))
    settings = dataclasses.asdict(s)
    settings.update(free=list(st.free), orders=st.orders,
                    initial={k: v for k, v in (s.initial or {}).items() if k in st.free})
    return write_result(problem, res, out, command="fit --select", settings=settings,
                        config=selected_config(config, st.components()), config_source=config_source,
                        base_dist=prep.base_dist, dtype=s.dtype, t0=t0, laplace=laplace, plots=plots,
                        extra={"selection": strip_private(report)})

"""Model adapters: one interface for every BRDF the driver can fit.

:class:`AbstractAdapter` (an equinox abstract class; the concrete adapters are final) says what
the driver needs of a model under a fixed static configuration:

- ``evaluate(params, wi, wo) -> (..., C)``: the BRDF without the cosine (1/sr);
- ``evaluate_grid(params, convention)``: the same on the whole MERL grid, ``(90, 90, 180, C)``;
- ``to_unconstrained(params)`` / ``from_unconstrained(u)``: the bijection to unconstrained space;
- ``starts(stats) -> list[(label, params)]``: initial guesses placed with :class:`DataStats`;
- ``params_to_dict`` / ``params_from_dict`` and ``config_to_dict``: the JSON record;
- ``field_names``, ``separable_fields``, ``diffraction``: what the fit's layout, Jacobian
  colouring and nested starts need;
- ``factorised``: whether the model also splits into per-bin terms and a per-cell part
  (``bin_terms``, ``evaluate_cells``), which the fit's passes then use.

:class:`TwoScaleAdapter` wraps :func:`twoscale.brdf` with a :class:`twoscale.ModelConfig`;
:class:`CookTorranceAdapter` the baseline of :mod:`twoscale.baselines`.
"""

from __future__ import annotations

import abc
import dataclasses
import itertools
import math
from typing import ClassVar

import equinox as eqx
import jax
import numpy as np

from twoscale.baselines import (
    ALPHA_RANGE,
    E_MAX,
    M_BOUND,
    CookTorranceConfig,
    CookTorranceParams,
    cook_torrance,
)
from twoscale.fit.starts import DataStats, conductor_k_for_f0, dielectric_eta_for_f0
from twoscale.model import PAPER_KNEE
from twoscale.params import CHANNEL_FIELDS, bounds_for

# Start grid of docs/model.md §8.
START_P = (0.5, 1.0, 2.0)
START_C = (1.5, 2.5)
START_A_SPEC = (0.3, 0.7)
#: Start value of the nano-scale correlation length b (µm): B = b/λ ≈ 2 in the green channel,
#: a diffraction halo of half-width ≈ 15° in θ_h.
START_B = 1.0
#: Start value of MERL's apparatus exponent (fits of the stand-ins end near 0.5–1).
START_E = 0.5
#: Start value of the apparatus knee exponent: the paper's form, L(θ) = [1 − (2θ/π)²]^e.
START_M = PAPER_KNEE

#: Largest extinction coefficient of a conductor start (k's range ends at 10; F0 = 0.944 at
#: η = 1.2). A brighter measured peak asks for k beyond the range; capping it here keeps the
#: start a valid value where the bound's sigmoid still responds (the generic guard,
#: :func:`twoscale.fit.candidates.inside_bounds`, only moves it 1e-3 of the range off the bound).
START_K_MAX = 9.0

#: Lobe names of the two-scale model, in the order of :meth:`TwoScaleAdapter.evaluate_lobes`.
LOBES = ("specular", "diffraction", "diffuse")


def lobes_of(config) -> tuple[str, ...]:
    """The lobes of :data:`LOBES` a two-scale configuration switches on, in that order."""
    on = {
        "specular": config.specular,
        "diffraction": config.diffraction,
        "diffuse": getattr(config, "has_diffuse", False),
    }
    return tuple(n for n in LOBES if on[n])


class AbstractAdapter(eqx.Module):
    """What the driver needs of a model under a fixed (static, hashable) configuration."""

    # Every adapter has ``config``, its configuration (a field, or a property of the fields):
    # not declared here, where an abstract attribute would become a dataclass field of every
    # subclass, property or not.
    #: The model splits into per-(θ_h, θ_d)-bin terms and a per-cell part (``bin_terms``,
    #: ``evaluate_cells``), which the fit's passes use.
    factorised: ClassVar[bool] = False

    @property
    @abc.abstractmethod
    def name(self) -> str:
        """The model's name in the record (``"two-scale"``, ``"ggx"``, ...)."""

    @property
    @abc.abstractmethod
    def material(self) -> str:
        """The material type (``"conductor"``, ``"plastic"``, ... or ``"baseline"``)."""

    @property
    @abc.abstractmethod
    def field_names(self) -> tuple[str, ...]:
        """The parameter fields this configuration uses (for ``fixed=`` and errors)."""

    @property
    @abc.abstractmethod
    def separable_fields(self) -> tuple[str, ...]:
        """Per-channel fields whose element c changes output channel c only (Jacobian colouring)."""

    @abc.abstractmethod
    def field_range(self, name: str) -> tuple[float, float]:
        """The closed valid range ``(lo, hi)`` of field ``name`` (what its unconstrained map
        reaches; a held value outside it would be clamped)."""

    @abc.abstractmethod
    def field_sizes(self, name: str) -> tuple[int, ...]:
        """How many values field ``name`` may be given (1: shared; per channel also the count
        of channels)."""

    @property
    def diffraction(self) -> bool:
        """The model has a diffraction lobe (so it has a diffraction-off special case)."""
        return False

    @abc.abstractmethod
    def evaluate(self, params, wi, wo):
        """The BRDF without the cosine (1/sr) at unit directions, ``(..., C)``."""

    @abc.abstractmethod
    def evaluate_grid(self, params, convention: str = "lower"):
        """The BRDF on the whole MERL grid, ``(90, 90, 180, C)``."""

    @abc.abstractmethod
    def to_unconstrained(self, params): ...

    @abc.abstractmethod
    def from_unconstrained(self, u): ...

    @abc.abstractmethod
    def params_to_dict(self, params) -> dict: ...

    @abc.abstractmethod
    def params_from_dict(self, d: dict): ...

    @abc.abstractmethod
    def config_to_dict(self) -> dict: ...

    @abc.abstractmethod
    def starts(self, stats: DataStats) -> list[tuple[str, object]]:
        """Initial guesses ``[(label, params)]`` placed from the data's summary numbers."""


class CookTorranceAdapter(AbstractAdapter):
    """Cook-Torrance (GGX or Beckmann) + Lambert baseline."""

    config: CookTorranceConfig = CookTorranceConfig()

    @property
    def name(self) -> str:
        return self.config.name

    @property
    def material(self) -> str:
        return "baseline"

    @property
    def field_names(self) -> tuple[str, ...]:
        return self.config.param_names

    #: Per-channel fields whose element c changes output channel c only (Jacobian colouring).
    separable_fields: ClassVar[tuple[str, ...]] = ("f0", "rho_d")

    def field_range(self, name: str) -> tuple[float, float]:
        return {
            "alpha": ALPHA_RANGE,
            "f0": (0.0, 1.0),
            "rho_d": (0.0, 1.0),
            "e": (0.0, E_MAX),
            "m": (M_BOUND.lo, M_BOUND.hi),
        }[name]

    def field_sizes(self, name: str) -> tuple[int, ...]:
        return (1, 3) if name in ("f0", "rho_d") else (1,)

    def evaluate(self, params, wi, wo):
        return cook_torrance(params, wi, wo, self.config)

    def evaluate_grid(self, params, convention: str = "lower"):
        from twoscale.fit.evaluation import evaluate_at
        from twoscale.merl import SHAPE, grid_directions

        wi, wo = grid_directions(convention)
        out = evaluate_at(self.evaluate, params, wi, wo, self.config.n_channels)
        return out.reshape(*SHAPE, self.config.n_channels)

    def to_unconstrained(self, params):
        return params.to_unconstrained()

    def from_unconstrained(self, u):
        return CookTorranceParams.from_unconstrained(u)

    def params_to_dict(self, params) -> dict:
        return params.to_dict()

    def params_from_dict(self, d: dict):
        return CookTorranceParams.from_dict(d)

    def config_to_dict(self) -> dict:
        return {"model": "cook-torrance", **self.config.to_dict()}

    def starts(self, stats: DataStats) -> list[tuple[str, CookTorranceParams]]:
        # GGX falls to 1/e of its peak at tan θ = α √(√e − 1) ≈ 0.80 α; Beckmann at tan θ = α.
        scale = 1.0 / math.sqrt(math.sqrt(math.e) - 1.0) if self.config.distribution == "ggx" else 1
        alpha0 = float(np.clip(stats.beta * scale, 2e-3, 1.0))
        rho_d = floor_albedo_start(stats)
        out = []
        for factor in (0.6, 1.0, 1.6):
            alpha = float(np.clip(alpha0 * factor, 2e-3, 1.5))
            d0 = 1.0 / (math.pi * alpha * alpha)
            f0 = np.clip(4.0 * np.maximum(stats.peak - stats.floor, 0.0) / d0, 0.01, 0.98)
            e = START_E if self.config.apparatus else None
            m = START_M if self.config.fits_knee else None
            out.append((f"alpha={alpha:.3g}", CookTorranceParams(alpha, f0, rho_d, e, m)))
        return out


def floor_albedo_start(stats: DataStats) -> np.ndarray:
    """A Lambertian floor's start ``ρ_d = π ρ_floor`` per channel, from the data's floor level
    (the baselines' body, a conductor's floor), kept inside ``[1e-3, 0.95]``."""
    return np.clip(np.pi * np.asarray(stats.floor, np.float64), 1e-3, 0.95)


def _epd_d0(beta: float, p: float) -> float:
    """EPD peak ``p / (π β² Γ(1/p))`` (host-side, for start placement)."""
    return p / (math.pi * beta * beta * math.gamma(1.0 / p))


def _renorm_at_normal(big_b: float, c: float) -> float:
    """``R(0; B, c) = 1 − (1 + B²)^{−(c−1)/2}`` (docs/model.md §3.5)."""
    return 1.0 - (1.0 + big_b * big_b) ** (-(c - 1.0) / 2.0)


def sigma_s_for_a_spec(a_spec: float, b: float, c: float, wavelength: float) -> float:
    """σ_s (µm) with ``A_spec(θ_d = 0) = a_spec`` at ``wavelength`` (µm).

    ``A_spec(0) = exp[−(4π σ_s √R(0; B, c) / λ)²]``, ``B = b/λ``.
    """
    r0 = _renorm_at_normal(b / wavelength, c)
    return wavelength * math.sqrt(-math.log(a_spec)) / (4.0 * math.pi * math.sqrt(r0))


class TwoScaleAdapter(AbstractAdapter):
    """The two-scale model :func:`twoscale.brdf` under a fixed :class:`twoscale.ModelConfig`.

    ``model_config`` is static (part of every compiled function's identity). A dielectric coat's
    Fresnel form is not: :func:`adapter_for` gives such a configuration ``fresnel="exact"``
    there and the form as the array ``schlick`` (a leaf, passed to the model as its ``schlick``
    selector), so that a fit's exact and Schlick twins share one compiled solve, one grid
    evaluation and one persistent-cache entry instead of compiling each form (``--preview`` of
    pvc with an empty cache 18.0–19.2 → 16.2–17.1 s, docs/model.md §8). :attr:`config` is the
    configuration with its form, as the fit reports and records it.
    """

    model_config: object  # twoscale.ModelConfig (hashable; static)
    schlick: np.ndarray | None = None  # dielectric coats: the Fresnel form (True: Schlick's)
    factorised: ClassVar[bool] = True

    @property
    def config(self):
        """The configuration this adapter fits, its ``fresnel`` the selected form. (Inside a
        traced function, where the form is not known, ``model_config``: the same but for it.)"""
        s = self.schlick
        if s is None or isinstance(s, jax.core.Tracer) or not bool(s):
            return self.model_config
        return dataclasses.replace(self.model_config, fresnel="schlick")

    @property
    def diffraction(self) -> bool:
        return bool(self.config.diffraction)

    @property
    def name(self) -> str:
        return "two-scale"

    @property
    def material(self) -> str:
        return self.config.material

    @property
    def field_names(self) -> tuple[str, ...]:
        return tuple(self.config.param_names)

    def field_range(self, name: str) -> tuple[float, float]:
        b = bounds_for(name, self.config.material)
        return b.lo, b.hi

    def field_sizes(self, name: str) -> tuple[int, ...]:
        if name in CHANNEL_FIELDS:
            return tuple(sorted({1, self.config.n_wavelengths}))
        return (1,)

    @property
    def separable_fields(self) -> tuple[str, ...]:
        """Per-channel fields whose element c changes output channel c only.

        RGB configurations: a conductor's η and k (each channel is its own Fresnel term) and its
        floor's ρ_d; a dielectric's ρ_d, and its η where the diffuse layer does not depend on
        the luminance mean η̄ of all channels (no diffuse layer, or a Lambertian body: the MERL
        protocol's plastic, whose passes then push 9 seeds instead of 11: a pass over 1.1 M cells
        477 → 405 ms on the 2-core machine). Spectral configurations mix wavelengths into RGB:
        none.
        """
        cfg = self.config
        if cfg.is_spectral:
            return ()
        if cfg.material == "conductor":
            return ("eta", "k", "rho_d") if cfg.has_diffuse else ("eta", "k")
        if not cfg.has_diffuse or cfg.lambertian_body:
            return ("eta", "rho_d")
        return ("rho_d",)

    def evaluate(self, params, wi, wo):
        from twoscale.model import brdf

        return brdf(params, wi, wo, self.model_config, schlick=self.schlick)

    def bin_terms(self, params):
        """Per-bin factors of the model on the MERL grid (lower bin edges, as the fit's cells):
        :func:`twoscale.model.half_diff_factors`, the factors of ``θ_d``, of ``θ_h`` and of
        both, left unmultiplied (each pass differentiates them once, and each cell multiplies
        its own: cheaper than differentiating their products on all 8 100 bins)."""
        from twoscale.model import half_diff_factors, merl_grid

        return half_diff_factors(
            params, merl_grid("lower"), self.model_config, schlick=self.schlick
        )

    def evaluate_cells(self, params, terms, cells):
        """The model at MERL cells (``cells``: ``hd`` = 90 ih + jd, ``cos`` = (cos θ_i, cos θ_o),
        ``phi``) from :meth:`bin_terms`: equal to :meth:`evaluate` at their directions."""
        from twoscale.model import brdf_from_factors

        cos = cells["cos"]
        ih, jd = cells["hd"] // 90, cells["hd"] % 90
        return brdf_from_factors(
            params,
            terms,
            ih,
            jd,
            cos[..., 0],
            cos[..., 1],
            cells["phi"],
            self.model_config,
            schlick=self.schlick,
        )

    def evaluate_grid(self, params, convention: str = "lower"):
        """The model on the whole MERL grid, ``(90, 90, 180, C)`` (:func:`twoscale.model.brdf_merl`)."""
        from twoscale.model import brdf_merl

        return brdf_merl(params, self.model_config, convention, schlick=self.schlick)

    def evaluate_lobes(self, params, wi, wo):
        """The lobes stacked on the last axis: ``[specular, diffraction, diffuse]`` × C (0 if off)."""
        import jax.numpy as jnp

        from twoscale.model import lobes

        out = lobes(params, wi, wo, self.model_config, schlick=self.schlick)
        ref = next(iter(out.values()))
        return jnp.concatenate([out.get(n, jnp.zeros_like(ref)) for n in LOBES], axis=-1)

    def to_unconstrained(self, params):
        return params.to_unconstrained()

    def from_unconstrained(self, u):
        from twoscale.params import TwoScaleParams

        return TwoScaleParams.from_unconstrained(u)

    def params_to_dict(self, params) -> dict:
        return params.to_dict()

    def params_from_dict(self, d: dict):
        from twoscale.params import TwoScaleParams

        return TwoScaleParams.from_dict(d)

    def config_to_dict(self) -> dict:
        return {"model": "two-scale", **config_to_dict(self.config)}

    def starts(self, stats: DataStats) -> list[tuple[str, object]]:
        from twoscale.params import TwoScaleParams

        cfg = self.config
        wl = float(np.median(np.asarray(cfg.wavelengths)))
        beta = stats.beta
        spec_peak = np.maximum(stats.peak - (stats.floor if cfg.has_diffuse else 0), 0)
        diffraction = bool(cfg.diffraction)
        grid_c = START_C if diffraction else (None,)
        grid_a = START_A_SPEC if diffraction else (None,)
        out = []
        for p, c, a_spec in itertools.product(START_P, grid_c, grid_a):
            f0 = np.clip(4.0 * spec_peak / _epd_d0(beta, p), 0.02, 0.97)
            extra = {}
            label = f"p={p:g}"
            if diffraction:
                extra = dict(
                    sigma_s=sigma_s_for_a_spec(a_spec, START_B, c, wl),
                    b=START_B,
                    c=c,
                )
                label += f" c={c:g} A_spec(0)={a_spec:g}"
            if cfg.apparatus:
                extra["e"] = START_E
                if cfg.apparatus_knee:
                    extra["m"] = START_M
            if cfg.material == "conductor":
                eta = np.full(3, 1.2)
                k = np.minimum(conductor_k_for_f0(f0, 1.2), START_K_MAX)
                params = TwoScaleParams.conductor(beta, p, eta, k, **extra)
                if cfg.has_diffuse:
                    params = params.replace(rho_d=floor_albedo_start(stats))
            else:
                f0_d = np.clip(f0, 0.02, 0.1)  # dielectric coats: F0 of a few %
                eta = np.clip(dielectric_eta_for_f0(f0_d), 1.2, 2.2)
                rho_d = np.clip(np.pi * stats.floor / 0.9, 1e-3, 0.95)
                make = (
                    TwoScaleParams.plastic
                    if cfg.material == "plastic"
                    else TwoScaleParams.subsurface
                )
                params = make(beta, p, eta, rho_d, **extra)
            out.append((label, params.for_config(cfg)))
        return out


def config_to_dict(config) -> dict:
    """JSON-friendly dict of a :class:`twoscale.ModelConfig`."""
    out = {}
    for f in dataclasses.fields(config):
        v = getattr(config, f.name)
        out[f.name] = list(v) if isinstance(v, tuple) else v
    return out


def config_from_dict(d: dict):
    """Rebuild a configuration saved by an adapter's ``config_to_dict`` (two-scale or baseline).

    Fields a record does not have take their defaults (records written before a field existed).
    """
    d = dict(d)
    model = d.pop("model", "two-scale")
    if model == "cook-torrance":
        return CookTorranceConfig.from_dict(d)
    from twoscale.config import ModelConfig

    names = {f.name for f in dataclasses.fields(ModelConfig)}
    kwargs = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items() if k in names}
    return ModelConfig(**kwargs)


def compile_key(adapter: AbstractAdapter):
    """What a compiled function of the adapter depends on besides array shapes: its static
    configuration (a two-scale adapter's ``model_config``: Fresnel twins share it)."""
    return getattr(adapter, "model_config", adapter.config)


def adapter_for(config) -> AbstractAdapter:
    """The adapter for a configuration object (a dielectric coat's Fresnel form as an array, see
    :class:`TwoScaleAdapter`)."""
    if isinstance(config, CookTorranceConfig):
        return CookTorranceAdapter(config)
    if not config.coat_form_selectable:
        return TwoScaleAdapter(config)
    return TwoScaleAdapter(
        dataclasses.replace(config, fresnel="exact"), np.asarray(config.fresnel == "schlick")
    )

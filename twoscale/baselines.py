"""Baseline BRDFs for comparison fits: Cook-Torrance (GGX or Beckmann) + Lambert.

``ρ(i, o) = ρ_d/π + F(θ_d) D(h) G(i, o) / (4 cos θ_i cos θ_o)``, per RGB channel, with

- ``F = F0 + (1 − F0)(1 − cos θ_d)^5`` (Schlick 1994), ``F0`` per channel in (0, 1);
- ``D``: GGX / Trowbridge-Reitz ``α² / (π cos⁴θ_h (α² + tan²θ_h)²)`` (Walter et al. 2007), or
  Beckmann ``exp(−tan²θ_h/α²) / (π α² cos⁴θ_h)``; one roughness ``α`` shared by the channels;
- ``G = 1/(1 + Λ(θ_i) + Λ(θ_o))``, the height-correlated Smith term (Heitz 2014, Eq. 99) with the
  distribution's own ``Λ``: GGX ``(√(1 + α² tan²θ) − 1)/2``, Beckmann
  ``(erf μ − 1)/2 + e^{−μ²}/(2μ√π)``, ``μ = 1/(α tan θ)``; with
  ``CookTorranceConfig(shadowing="uncorrelated")`` the product ``G1(i) G1(o)``,
  ``G1 = 1/(1 + Λ)``.

Seven parameters (α, F0 ×3, ρ_d ×3), the usual "microfacet + Lambert" model that a measured BRDF is
compared against. With ``CookTorranceConfig(apparatus=True)`` the specular term is multiplied by
MERL's apparatus factor ``L(θ_i) L(θ_o)``, ``L(θ) = [1 − (2θ/π)²]^e``, exactly as in the two-scale
model (one more parameter, ``e``), so both are fitted to MERL data under the same protocol. The fitting driver (:mod:`twoscale.fit`) fits it with the same metric and
schedule as the two-scale model: pass ``config=CookTorranceConfig("ggx")``.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.scipy.special import erfc

from twoscale._numerics import safe_sqrt, tiny
from twoscale.config import APPARATUS_ANGLES, SHADOWING
from twoscale.geometry import unit
from twoscale.model import PAPER_KNEE, apparatus_weight
from twoscale.params import bounds_for

__all__ = [
    "CookTorranceConfig",
    "CookTorranceParams",
    "cook_torrance",
    "ALPHA_RANGE",
]

#: Roughness range kept by the reparametrisation (log-scaled sigmoid).
ALPHA_RANGE = (1e-3, 2.0)
#: Upper bound of the apparatus exponent: the two-scale model's (one range for both models).
E_MAX = bounds_for("e", None).hi
#: The apparatus knee exponent's range and map: the two-scale model's (log-scaled sigmoid).
M_BOUND = bounds_for("m", None)
_DISTRIBUTIONS = ("ggx", "beckmann")


@dataclasses.dataclass(frozen=True)
class CookTorranceConfig:
    """Static configuration of the baseline.

    Fields:
        distribution: the microfacet distribution, ``"ggx"`` or ``"beckmann"``.
        apparatus: multiply the specular term by MERL's ``L(θ_i) L(θ_o)``,
            ``L(θ) = [1 − (2θ/π)^m]^e`` (adds ``e``; m = 2).
        apparatus_knee: with ``apparatus``, also fit the knee exponent ``m`` (adds ``m``), as
            the two-scale model's MERL protocol does.
        apparatus_angles: ``"theta_io"`` (``L(θ_i) L(θ_o)``; default) or ``"theta_d"``
            (``L(θ_d)²``), as the two-scale model's switch of the same name.
        shadowing: ``"correlated"`` (height-correlated Smith, ``1/(1 + Λ_i + Λ_o)``) or
            ``"uncorrelated"`` (``G1(i) G1(o)``), as the two-scale model's switch of the same
            name (docs/model.md §3.3), so that a comparison can give both models the same form.
    """

    distribution: str = "ggx"
    apparatus: bool = False
    apparatus_knee: bool = False
    shadowing: str = "correlated"
    apparatus_angles: str = "theta_io"

    def __post_init__(self):
        if self.distribution not in _DISTRIBUTIONS:
            raise ValueError(
                f"distribution must be one of {_DISTRIBUTIONS}, got {self.distribution!r}"
            )
        for name in ("apparatus", "apparatus_knee"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be a bool, got {getattr(self, name)!r}")
        if self.shadowing not in SHADOWING:
            raise ValueError(f"shadowing must be one of {SHADOWING}, got {self.shadowing!r}")
        if self.apparatus_angles not in APPARATUS_ANGLES:
            raise ValueError(
                f"apparatus_angles must be one of {APPARATUS_ANGLES}, got {self.apparatus_angles!r}"
            )

    @property
    def fits_knee(self) -> bool:
        """The knee exponent ``m`` is a parameter (``apparatus`` and ``apparatus_knee``)."""
        return self.apparatus and self.apparatus_knee

    @property
    def name(self) -> str:
        return f"cook-torrance-{self.distribution}"

    @property
    def n_channels(self) -> int:
        return 3

    @property
    def param_names(self) -> tuple[str, ...]:
        names = ("alpha", "f0", "rho_d")
        if self.apparatus:
            names += ("e", "m") if self.apparatus_knee else ("e",)
        return names

    def to_dict(self) -> dict:
        return {
            "distribution": self.distribution,
            "apparatus": self.apparatus,
            "apparatus_knee": self.apparatus_knee,
            "shadowing": self.shadowing,
            "apparatus_angles": self.apparatus_angles,
        }

    @classmethod
    def from_dict(cls, d: dict) -> CookTorranceConfig:
        return cls(
            distribution=d.get("distribution", "ggx"),
            apparatus=bool(d.get("apparatus", False)),
            apparatus_knee=bool(d.get("apparatus_knee", False)),
            shadowing=d.get("shadowing", "correlated"),
            apparatus_angles=d.get("apparatus_angles", "theta_io"),
        )


def _sigmoid(u):
    return jax.nn.sigmoid(u)


def _logit(x):
    return jnp.log(x) - jnp.log1p(-x)


class CookTorranceParams(eqx.Module):
    """Parameters of the Cook-Torrance + Lambert baseline (physical units).

    | field | symbol | unit | range |
    | --- | --- | --- | --- |
    | ``alpha`` | α | — | [1e-3, 2] (shape ()) |
    | ``f0`` | F0 | — | (0, 1) per channel (3,) |
    | ``rho_d`` | ρ_d | — | (0, 1) per channel (3,) |
    | ``e`` | e | — | [0, 5] (shape ()), apparatus exponent; None without the apparatus factor |
    | ``m`` | m | — | [1, 20] (shape ()), apparatus knee exponent; None: m = 2 |
    """

    alpha: jax.Array
    f0: jax.Array
    rho_d: jax.Array
    e: jax.Array | None = None
    m: jax.Array | None = None

    def __init__(self, alpha, f0, rho_d, e=None, m=None):
        self.alpha = jnp.asarray(alpha, dtype=jnp.result_type(float))
        self.f0 = jnp.broadcast_to(jnp.asarray(f0, dtype=jnp.result_type(float)), (3,))
        self.rho_d = jnp.broadcast_to(jnp.asarray(rho_d, dtype=jnp.result_type(float)), (3,))
        self.e = None if e is None else jnp.asarray(e, dtype=jnp.result_type(float))
        self.m = None if m is None else jnp.asarray(m, dtype=jnp.result_type(float))

    def to_unconstrained(self) -> CookTorranceParams:
        """Map to unconstrained values: α by a log-scaled logit, F0, ρ_d and e/5 by logit, m by
        :data:`M_BOUND`'s map."""
        lo, hi = math.log(ALPHA_RANGE[0]), math.log(ALPHA_RANGE[1])
        t = (jnp.log(self.alpha) - lo) / (hi - lo)
        eps = 1e-12  # keep the logit finite for values on the boundary
        return CookTorranceParams(
            _logit(jnp.clip(t, eps, 1 - eps)),
            _logit(jnp.clip(self.f0, eps, 1 - eps)),
            _logit(jnp.clip(self.rho_d, eps, 1 - eps)),
            None if self.e is None else _logit(jnp.clip(self.e / E_MAX, eps, 1 - eps)),
            None if self.m is None else M_BOUND.inverse(self.m),
        )

    @staticmethod
    def from_unconstrained(u: CookTorranceParams) -> CookTorranceParams:
        """Inverse of :meth:`to_unconstrained`; every real input maps inside the valid range."""
        lo, hi = math.log(ALPHA_RANGE[0]), math.log(ALPHA_RANGE[1])
        alpha = jnp.exp(lo + (hi - lo) * _sigmoid(u.alpha))
        e = None if u.e is None else E_MAX * _sigmoid(u.e)
        m = None if u.m is None else M_BOUND.forward(u.m)
        return CookTorranceParams(alpha, _sigmoid(u.f0), _sigmoid(u.rho_d), e, m)

    def to_dict(self) -> dict:
        out = {
            "alpha": float(self.alpha),
            "f0": [float(x) for x in self.f0],
            "rho_d": [float(x) for x in self.rho_d],
        }
        if self.e is not None:
            out["e"] = float(self.e)
        if self.m is not None:
            out["m"] = float(self.m)
        return out

    @classmethod
    def from_dict(cls, d: dict) -> CookTorranceParams:
        return cls(d["alpha"], d["f0"], d["rho_d"], d.get("e"), d.get("m"))


def _lambda_ggx(tan2, alpha):
    """Smith Λ of GGX: ``(√(1 + α² tan²θ) − 1)/2`` written without cancellation."""
    x = alpha * alpha * tan2
    return 0.5 * x / (1.0 + jnp.sqrt(1.0 + x))


def _lambda_beckmann(tan2, alpha):
    """Smith Λ of Beckmann, ``μ = 1/(α tanθ)``: ``−erfc(μ)/2 + e^{−μ²}/(2μ√π)``; 0 at normal incidence."""
    fl = tiny(jnp.result_type(tan2, alpha))
    t = alpha * safe_sqrt(tan2)
    pos = t > fl
    mu = 1.0 / jnp.where(pos, t, 1.0)  # double where: μ = ∞ at θ = 0, where Λ = 0 exactly
    lam = -0.5 * erfc(mu) + jnp.exp(-mu * mu) / (2.0 * mu * math.sqrt(math.pi))
    return jnp.where(pos, lam, 0.0)


def cook_torrance(params: CookTorranceParams, wi, wo, config=CookTorranceConfig()):
    """Evaluate the Cook-Torrance + Lambert baseline (BRDF without the cosine, 1/sr).

    Args:
        params: :class:`CookTorranceParams`.
        wi, wo: directions ``(..., 3)`` pointing away from the surface (normal = z), of any
            length (scaled to unit length; a zero vector counts as below the horizon).
        config: :class:`CookTorranceConfig` (the distribution).
    Returns:
        ``(..., 3)``; 0 where either direction is at or below the horizon.
    """
    wi = jnp.asarray(wi)
    wo = jnp.asarray(wo)
    dtype = jnp.result_type(wi, wo, params.alpha)
    wi, wo = unit(wi.astype(dtype)), unit(wo.astype(dtype))  # any length: their unit vectors
    fl = tiny(dtype)
    cos_i = wi[..., 2]
    cos_o = wo[..., 2]
    above = (cos_i > 0.0) & (cos_o > 0.0)
    ci = jnp.where(above, cos_i, 1.0)  # double where: the lobe divides by the cosines
    co = jnp.where(above, cos_o, 1.0)
    hv = wi + wo
    hn = jnp.sqrt(jnp.maximum(jnp.sum(hv * hv, axis=-1, keepdims=True), fl))
    h = hv / hn
    cos_h = jnp.clip(h[..., 2], fl, 1.0)
    cos_d = jnp.clip(jnp.sum(wi * h, axis=-1), 0.0, 1.0)
    alpha = params.alpha
    a2 = alpha * alpha
    tan2_h = (1.0 - cos_h) * (1.0 + cos_h) / (cos_h * cos_h)
    tan2_i = (1.0 - ci) * (1.0 + ci) / (ci * ci)
    tan2_o = (1.0 - co) * (1.0 + co) / (co * co)
    cos4_h = (cos_h * cos_h) ** 2
    if config.distribution == "ggx":
        d = a2 / (jnp.pi * cos4_h * (a2 + tan2_h) ** 2)
        lam_i, lam_o = _lambda_ggx(tan2_i, alpha), _lambda_ggx(tan2_o, alpha)
    else:
        d = jnp.exp(-tan2_h / a2) / (jnp.pi * a2 * cos4_h)
        lam_i, lam_o = _lambda_beckmann(tan2_i, alpha), _lambda_beckmann(tan2_o, alpha)
    if config.shadowing == "correlated":
        g = 1.0 / (1.0 + lam_i + lam_o)
    else:
        g = 1.0 / ((1.0 + lam_i) * (1.0 + lam_o))
    spec = d * g / (4.0 * ci * co)
    if config.apparatus:
        if params.e is None:
            raise ValueError("CookTorranceConfig(apparatus=True) needs the parameter e")
        if config.fits_knee and params.m is None:
            raise ValueError("CookTorranceConfig(apparatus_knee=True) needs the parameter m")
        m = params.m if config.fits_knee else PAPER_KNEE
        spec = spec * apparatus_weight(ci, co, cos_d, params.e, m, config.apparatus_angles)
    schlick = (1.0 - cos_d) ** 5
    f = params.f0 + (1.0 - params.f0) * schlick[..., None]
    rho = params.rho_d / jnp.pi + f * spec[..., None]
    return jnp.where(above[..., None], rho, 0.0)

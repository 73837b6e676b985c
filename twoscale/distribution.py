"""Exponential power distribution (EPD) of microfacet normals [HP17 Eq. 34-35].

``D(θ) = χ(θ < π/2) · P22(tan²θ) / cos⁴θ``, ``P22(x) = d0 · exp[−(x/β²)^p]``,
``d0 = p / (π β² Γ(1/p))``. ``p = 1`` is Beckmann with ``α = β``; ``p > 1`` is flat-topped and
``p < 1`` sharply peaked with heavy tails. Normalised: ``∫ D(m) cos θ_m dω_m = 1``.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax.scipy.special import gammaln

from twoscale._numerics import safe_log, tiny


def log_d0(beta, p):
    """``log d0 = log p − log π − 2 log β − lgamma(1/p)`` (Γ(1/p) overflows for small p: trap 3)."""
    return jnp.log(p) - jnp.log(jnp.pi) - 2.0 * jnp.log(beta) - gammaln(1.0 / p)


def d0(beta, p):
    """Peak value ``D(0) = P22(0) = p / (π β² Γ(1/p))`` (1/sr)."""
    return jnp.exp(log_d0(beta, p))


def log_ndf(cos_theta_h, beta, p):
    """``log D``; at and below the horizon a finite stand-in far below any representable ``D``."""
    dtype = jnp.result_type(cos_theta_h, beta, p)
    fl = tiny(dtype)
    c = jnp.clip(cos_theta_h, 0.0, 1.0)
    # Below sqrt(tiny) cos² underflows and D is zero to machine precision for every β ≤ 1:
    # treat it as the horizon (double where: log 0 and inf − inf would poison gradients, trap 2).
    above = c > jnp.sqrt(fl)
    cs = jnp.where(above, c, 1.0)
    log_c = jnp.log(cs)
    # log(tan²θ/β²) in logs so that it cannot overflow at grazing for tiny β; safe_log keeps the
    # normal-incidence value (tan θ = 0) finite with a zero gradient (trap 1).
    log_x = safe_log((1.0 - cs) * (1.0 + cs)) - 2.0 * log_c - 2.0 * jnp.log(beta)
    # (tan²θ/β²)^p, capped at 1e4: exp(−1e4)·cos⁻⁴ underflows to 0 anyway, and the cap (a double
    # where) keeps exp(z) from overflowing to inf and its gradient from becoming 0·inf.
    z = p * log_x
    cap = jnp.log(1e4)
    expo = jnp.exp(jnp.where(z < cap, z, cap))
    val = log_d0(beta, p) - expo - 4.0 * log_c
    # Below the horizon: log of a value far under any representable D (exp gives exactly 0).
    return jnp.where(above, val, 2.0 * jnp.log(fl))


def ndf(cos_theta_h, beta, p):
    """Normalised EPD ``D(θ_h)`` in 1/sr [HP17 Eq. 34-35].

    Args:
        cos_theta_h: cosine of the angle between the microfacet normal and the surface normal.
            Values ≤ 0 (below the horizon) give 0.
        beta: roughness β > 0 (≈ the RMS slope scale; β = α of Beckmann at p = 1).
        p: shape ("kurtosis") exponent p > 0.
    Returns:
        D ≥ 0, same dtype as the inputs. Evaluated in log space so that ``1/cos⁴θ`` times the
        underflowing exponential never makes ``0·inf``.
    """
    c = jnp.asarray(cos_theta_h)
    return jnp.where(c > 0.0, jnp.exp(log_ndf(c, beta, p)), 0.0)

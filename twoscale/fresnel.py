"""Unpolarised Fresnel reflectance (exact, and Schlick's form of a dielectric's) and the diffuse
Fresnel fit [HP17 §3.1, §3.9].

All functions are elementwise, broadcast over their arguments, and keep the input dtype.
"""

from __future__ import annotations

import math

import jax.numpy as jnp

from twoscale._numerics import safe_sqrt, tiny


def _ratio(num, den, limit):
    """``num/den`` where ``den > 0``, else ``limit``; double where so the gradient stays finite.

    A (near-)zero denominator only happens at grazing with ``η = 1, k = 0`` (index matched), where the
    reflectance tends to 1.
    """
    # The floor √tiny (not 0) keeps the discarded branch's derivative −num/den² finite: with
    # den ≈ 1e-160 (cos θ ≈ 1e-160 at η = 1) den² underflows and 0·inf would give NaN.
    ok = den > math.sqrt(tiny(jnp.result_type(den)))
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), limit)


def dielectric(cos_theta, eta):
    """Unpolarised Fresnel reflectance of a dielectric interface (outside index 1).

    ``F = (r_s² + r_p²)/2`` with ``g = sqrt(η² − sin²θ)``,
    ``r_s = (cosθ − g)/(cosθ + g)``, ``r_p = (g − η² cosθ)/(η² cosθ + g)``.
    Total internal reflection (``η < 1`` and ``sin θ > η``) gives ``F = 1``.

    Args:
        cos_theta: cosine of the incidence angle, in [0, 1].
        eta: relative index of refraction (inside/outside), > 0.
    Returns:
        F in [0, 1], 1 at ``cos_theta = 0``.
    """
    cos_theta = jnp.clip(cos_theta, 0.0, 1.0)
    eta2 = eta * eta
    sin2 = (1.0 - cos_theta) * (1.0 + cos_theta)
    g2 = eta2 - sin2
    tir = g2 <= 0.0
    g = safe_sqrt(g2)
    rs = _ratio(cos_theta - g, cos_theta + g, -1.0)
    rp = _ratio(g - eta2 * cos_theta, eta2 * cos_theta + g, 1.0)
    f = 0.5 * (rs * rs + rp * rp)
    # At cos θ = 0 with g > 0 both ratios are exactly −1 and +1: F = 1, no special case needed.
    return jnp.where(tir, 1.0, jnp.clip(f, 0.0, 1.0))


def schlick(cos_theta, eta):
    """Schlick's form of a dielectric's reflectance: ``F = F0 + (1 − F0)(1 − cos θ)⁵`` with the
    normal-incidence value of the exact one, ``F0 = ((η − 1)/(η + 1))²`` [docs/model.md §3.1].

    Equal to :func:`dielectric` at normal and grazing incidence; in between it stays flatter up
    to θ ≈ 70° and rises more steeply after (η = 1.97, F0 = 0.107: 0.135 instead of 0.158 at
    60°, 0.673 instead of 0.630 at 85°). ``ModelConfig(fresnel="schlick")`` uses it for a
    dielectric coat; measured materials can follow it more closely than the exact curve
    (docs/model.md §8).

    Args:
        cos_theta: cosine of the incidence angle, in [0, 1].
        eta: relative index of refraction (inside/outside), > 0.
    Returns:
        F in [0, 1], 1 at ``cos_theta = 0``.
    """
    cos_theta = jnp.clip(cos_theta, 0.0, 1.0)
    f0 = ((eta - 1.0) / (eta + 1.0)) ** 2
    m = 1.0 - cos_theta
    m2 = m * m
    return f0 + (1.0 - f0) * (m2 * m2 * m)


def conductor(cos_theta, eta, k):
    """Unpolarised Fresnel reflectance of a conductor with complex index ``η + ik`` (outside 1).

    ``c1 = η² − k² − sin²θ``, ``c0 = sqrt(c1² + 4η²k²)``, ``a² = (c0+c1)/2``, ``b² = (c0−c1)/2``,
    ``R_s = (a²+b² − 2a cosθ + cos²θ)/(a²+b² + 2a cosθ + cos²θ)``,
    ``R_p = R_s (a²+b² − 2a sinθ tanθ + sin²θ tan²θ)/(a²+b² + 2a sinθ tanθ + sin²θ tan²θ)``.
    ``R_p``'s ratio is multiplied through by ``cos²θ`` so that it stays finite at grazing
    (where it tends to 1). With ``k = 0`` this equals :func:`dielectric` for ``η ≥ 1``.

    Args:
        cos_theta: cosine of the incidence angle, in [0, 1].
        eta: real part of the relative index, > 0.
        k: extinction coefficient, ≥ 0.
    Returns:
        F in [0, 1].
    """
    cos_theta = jnp.clip(cos_theta, 0.0, 1.0)
    cos2 = cos_theta * cos_theta
    sin2 = (1.0 - cos_theta) * (1.0 + cos_theta)
    eta2, k2 = eta * eta, k * k
    c1 = eta2 - k2 - sin2
    ek2 = eta2 * k2  # = a² b²
    c0 = safe_sqrt(c1 * c1 + 4.0 * ek2)
    # a² and b² without cancellation: the large one from (c0 ± c1)/2, the other from a²b² = η²k².
    pos = c1 >= 0.0
    big = 0.5 * (c0 + jnp.abs(c1))
    small = _ratio(ek2, big, 0.0)
    a2 = jnp.where(pos, big, small)
    b2 = jnp.where(pos, small, big)
    a = safe_sqrt(a2)
    s = a2 + b2
    rs = _ratio(s - 2.0 * a * cos_theta + cos2, s + 2.0 * a * cos_theta + cos2, 1.0)
    # R_p/R_s multiplied by cos²θ above and below: sinθ tanθ cos² = sin²θ cosθ, sin²tan²cos² = sin⁴.
    sin4 = sin2 * sin2
    num = s * cos2 - 2.0 * a * sin2 * cos_theta + sin4
    den = s * cos2 + 2.0 * a * sin2 * cos_theta + sin4
    rp = rs * _ratio(num, den, 1.0)
    return jnp.clip(0.5 * (rs + rp), 0.0, 1.0)


def diffuse_fresnel(eta):
    """Hemispherical-average diffuse Fresnel reflectance ``F_dr(η)`` (polynomial fit, §3.9).

    ``η < 1``: ``−1.4399η² + 0.7099η + 0.6681 + 0.0636/η``;
    ``η ≥ 1``: ``−1.36881/η⁵ + 4.98554/η⁴ − 7.80989/η³ + 6.75335/η² − 3.4793/η + 0.919317``.
    The plastic layer uses ``F_dr(1/η̄)`` and the subsurface one ``F_dr(η̄)``.

    Args:
        eta: relative index, > 0.
    """
    low = eta < 1.0
    x_lo = jnp.where(low, eta, 0.5)  # double where: each branch sees a value in its own domain
    x_hi = jnp.where(low, 1.0, eta)
    f_lo = -1.4399 * x_lo**2 + 0.7099 * x_lo + 0.6681 + 0.0636 / x_lo
    r = 1.0 / x_hi
    f_hi = ((((-1.36881 * r + 4.98554) * r - 7.80989) * r + 6.75335) * r - 3.4793) * r + 0.919317
    return jnp.where(low, f_lo, f_hi)

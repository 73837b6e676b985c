"""The convolution ``(S*D)(θ_h)`` of the small-scale function with the EPD [HP17 Eq. 39-41, 61-64].

``S(μ) = μ² [1 + 4u²(1 − μ²)]^{−(c+1)/2}`` with ``μ = h·m`` and ``u = B cos θ_d``;
``(S*D)(θ_h) = ∫_Ω S(h·m) D(m) dω_m`` over the upper hemisphere of microfacet normals ``m``
(``D`` is the normalised EPD of :mod:`twoscale.distribution`, zero below the horizon).

Integration range of ``S``. ``S`` is even in ``μ`` and defined on ``μ ∈ [−1, 1]``. The integral
above runs over every ``m`` of the upper hemisphere, including normals with ``h·m < 0`` (possible
when ``θ_h + θ_m > π/2``); there ``S`` takes its value at ``−μ``. In zonal harmonics this is
``S_l = 2π ∫_{−1}^{1} S Y_l dμ`` (Funk-Hecke needs the whole range: only even ``l`` survive), while
``D_l = 2π ∫_0^1 D Y_l dμ`` since ``D`` vanishes below the horizon. Truncating ``S`` to ``μ ≥ 0``
(``∫_0^1``, as docs/model.md §3.8 writes ``f_l``) would compute a different integral, with
``χ(h·m > 0)`` inserted; it differs only where ``D`` has mass beyond ``π/2 − θ_h``.

Two evaluation paths (``path=``):

``"exact"``
    Direct quadrature of the 2-D integral in coordinates ``(θ_m, φ)`` around the normal:
    ``∫_0^{π/2} sin θ_m D(θ_m) ∫_0^{2π} S(μ(θ_m, φ)) dφ dθ_m``,
    ``μ = cos θ_h cos θ_m + sin θ_h sin θ_m cos φ``. Every sharp feature sits at an end of an
    integration interval, where tanh-sinh (double exponential) quadrature resolves all scales:
    the ``θ_m`` range is split at ``θ_h`` (the peak of ``S``'s ring integral) and at
    ``atan β`` (the shoulder of ``D``, sharp for large ``p``), so ``D``'s peak (at 0), its
    shoulder, ``S``'s peak and ``D``'s spike at the horizon (small ``p``, large ``β``) are all
    interval ends; the ``φ`` range ``[0, π]`` (the integrand is even in ``φ``) has ``S``'s peak
    at ``φ = 0`` and its antipodal peak (``μ → −1``) at ``φ = π``. ``1 ∓ μ`` are formed without
    cancellation (``1 − μ = 2 sin²(Δ/2) + 2 sin θ_h sin θ_m sin²(φ/2)``, ``Δ = θ_h − θ_m``;
    ``1 + μ = 2 cos²(Σ/2) + 2 sin θ_h sin θ_m cos²(φ/2)``, ``Σ = θ_h + θ_m``). Fixed nodes, so it
    is differentiable in every argument. The reference of this module.

``"tables"``
    Tabulated values of ``log L − log(cos²θ_h + k sin²θ_h)`` on a 5-D grid over
    ``(ln β, ln(p − 0.1), ln(c − 0.7), asinh(u/0.25), t)``, ``t`` a normalised angle that maps ``θ_h ∈ [0, π/2]``
    onto ``[0, 1]`` for every parameter set, interpolated by the C² spline of
    :mod:`twoscale.tables` (see :class:`LobeSlice` and ``tablegen/CONVOLUTION.md``).
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from twoscale import tables
from twoscale._numerics import asinh_nonneg, float_dtype, safe_log, safe_sqrt
from twoscale.distribution import log_d0
from twoscale.tables import Spline

#: What users call: the convolved lobe (either path) and its per-parameter-set slice. The table
#: plumbing (``lobe_table``, ``map_params``, ``normalised_angle``, ...) stays importable for the
#: table generators and tests, but is not part of the interface.
__all__ = ["lobe", "lobe_exact", "lobe_spline", "LobeSlice"]

#: tanh-sinh truncation: at |t| = 3.2 the node sits 2e-17 (relative) from the interval end.
_TS_T = 3.2


@functools.cache
def tanh_sinh(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tanh-sinh nodes on [0, 1]: ``(x, 1 − x, w)``, with ``1 − x`` computed without cancellation."""
    t = np.linspace(-_TS_T, _TS_T, n)
    h = t[1] - t[0]
    z = 0.5 * np.pi * np.sinh(t)
    xm = 1.0 / (1.0 + np.exp(2.0 * z))
    x = 1.0 / (1.0 + np.exp(-2.0 * z))
    w = h * 0.25 * np.pi * np.cosh(t) / np.cosh(z) ** 2
    for a in (x, xm, w):
        a.setflags(write=False)
    return x, xm, w


def small_scale(mu, c, u):
    """``S(μ) = μ² [1 + 4u²(1 − μ²)]^{−(c+1)/2}`` [HP17 §3.8; slides]."""
    one_m_mu2 = jnp.clip((1.0 - mu) * (1.0 + mu), 0.0, None)
    return mu * mu * jnp.exp(-0.5 * (c + 1.0) * jnp.log1p(4.0 * u * u * one_m_mu2))


def _log_ndf_tan(log_sin, log_cos, beta, p):
    """``log D`` from ``log sin θ_m`` and ``log cos θ_m`` (accurate at θ_m → 0 and → π/2).

    ``(tan²θ/β²)^p = exp(2p (log sin − log cos − log β))``; the exponent is capped at 60 so
    that the stretched exponential underflows to 0 with a finite (zero) gradient instead of
    ``exp(−inf)·inf`` (docs/model.md §6 traps 1-2).
    """
    expo = jnp.minimum(2.0 * p * (log_sin - log_cos - jnp.log(beta)), 60.0)
    return log_d0(beta, p) - jnp.exp(expo) - 4.0 * log_cos


def _quadrature_geometry(theta_h, dist_h, beta, p, n_theta, n_phi):
    """Nodes of the exact quadrature for one ``θ_h`` and one ``(β, p)``.

    Returns ``(d_w, μ², (1−μ)(1+μ), φ weights)``: ``d_w`` (4, n_theta) are the ``θ_m`` weights
    times ``sin θ_m D(θ_m)``; ``μ²`` and ``1 − μ²`` are (4, n_theta, n_phi). ``dist_h = π/2 − θ_h``.
    """
    dtype = jnp.result_type(theta_h)
    x, xm, w = (jnp.asarray(a, dtype) for a in tanh_sinh(n_theta))
    px, pxm, pw = (jnp.asarray(a, dtype) for a in tanh_sinh(n_phi))
    half_pi = 0.5 * math.pi
    # Interval ends: D's shoulder (tan θ_m = β), the point where D has fallen to e^{−40} of its
    # peak (tan θ_m = β·40^{1/(2p)}: sharp for large p), and θ_h; sorted (θ_b < θ_c always).
    theta_b = jnp.arctan(beta)
    theta_c = jnp.arctan(beta * jnp.exp(jnp.log(40.0) / (2.0 * p)))
    ends = [jnp.minimum(theta_h, theta_b), jnp.clip(theta_h, theta_b, theta_c)]
    ends.append(jnp.maximum(theta_h, theta_c))
    lo = jnp.stack([jnp.zeros_like(theta_h), *ends])[:, None]
    hi = jnp.stack([*ends, jnp.full_like(theta_h, half_pi)])[:, None]
    length = hi - lo
    left = x < 0.5  # measure from the nearer end of each interval (no cancellation there)
    theta_m = jnp.where(left, lo + length * x, hi - length * xm)
    # Δ = θ_h − θ_m and π/2 − θ_m, each exact when θ_h or π/2 is that interval end.
    delta = jnp.where(left, (theta_h - lo) - length * x, (theta_h - hi) + length * xm)
    dist_m = jnp.where(left, (half_pi - lo) - length * x, (half_pi - hi) + length * xm)
    sin_m = jnp.sin(theta_m)
    cos_m = jnp.sin(dist_m)
    log_d = _log_ndf_tan(safe_log(sin_m), safe_log(cos_m), beta, p)
    d_w = jnp.exp(log_d) * sin_m * length * w

    # Inner integral over φ ∈ [0, π] (×2 by symmetry), nodes φ = π·px.
    sin2_half_phi = jnp.sin(half_pi * px) ** 2
    cos2_half_phi = jnp.sin(half_pi * pxm) ** 2
    b = (jnp.sin(theta_h) * sin_m)[..., None]
    one_m_mu = 2.0 * jnp.sin(0.5 * delta)[..., None] ** 2 + 2.0 * b * sin2_half_phi
    one_p_mu = 2.0 * jnp.sin(0.5 * (dist_h + dist_m))[..., None] ** 2 + 2.0 * b * cos2_half_phi
    mu = jnp.where(one_m_mu < 1.0, 1.0 - one_m_mu, one_p_mu - 1.0)
    return d_w, mu * mu, one_m_mu * one_p_mu, pw


def _lobe_exact_one(theta_h, dist_h, beta, p, c, u, n_theta, n_phi):
    """Scalar ``(S*D)(θ_h)`` by tanh-sinh quadrature; ``dist_h = π/2 − θ_h`` (accurate at grazing)."""
    d_w, mu2, q, pw = _quadrature_geometry(theta_h, dist_h, beta, p, n_theta, n_phi)
    s_val = mu2 * jnp.exp(-0.5 * (c + 1.0) * jnp.log1p(4.0 * u * u * q))
    ring = 2.0 * math.pi * jnp.sum(s_val * pw, axis=-1)  # ∫_0^{2π} S dφ
    return jnp.sum(d_w * ring).astype(theta_h.dtype)


def lobe_exact(cos_theta_h, beta, p, c, u, *, n_theta: int = 121, n_phi: int = 121):
    """``(S*D)(θ_h)`` by direct tanh-sinh quadrature of the 2-D integral (the reference path).

    Args:
        cos_theta_h: cosine of the half-vector angle, in [0, 1].
        beta, p: EPD roughness and shape.
        c: PSD exponent, > 1.
        u: ``B cos θ_d`` ≥ 0.
        n_theta: tanh-sinh nodes on each of the four ``θ_m`` intervals (static).
        n_phi: tanh-sinh nodes on ``φ ∈ [0, π]`` (static).
    Returns:
        The lobe (1/sr), broadcast shape of the arguments, their floating dtype. Relative error
        ≲ 1e-6 over the documented domain at the default node counts (measured in
        ``tablegen/CONVOLUTION.md``). At exactly ``cos θ_h = 1`` the derivative in ``cos θ_h`` is
        returned as 0 (``θ_h = acos`` has an infinite slope there; the lobe is even in θ_h).
    """
    dtype = float_dtype(cos_theta_h, beta, p, c, u)
    args = jnp.broadcast_arrays(*(jnp.asarray(a, dtype) for a in (cos_theta_h, beta, p, c, u)))
    shape = args[0].shape
    ct, beta, p, c, u = (a.reshape(-1) for a in args)
    ct = jnp.clip(ct, 0.0, 1.0)
    st = safe_sqrt((1.0 - ct) * (1.0 + ct))  # zero gradient at cos θ_h = 1, see docstring
    theta_h = jnp.arctan2(st, ct)
    dist_h = jnp.arctan2(ct, st)
    one = functools.partial(_lobe_exact_one, n_theta=n_theta, n_phi=n_phi)
    out = jax.lax.map(lambda a: one(*a), (theta_h, dist_h, beta, p, c, u), batch_size=16)
    return out.reshape(shape)


def lobe(cos_theta_h, beta, p, c, u, *, path: str = "tables", **kwargs):
    """``(S*D)(θ_h)`` [HP17 Eq. 39-41]; ``path`` is ``"tables"`` (default) or ``"exact"``."""
    if path == "exact":
        return lobe_exact(cos_theta_h, beta, p, c, u, **kwargs)
    if path == "tables":
        if kwargs:
            raise TypeError(f"path='tables' takes no options, got {sorted(kwargs)}")
        return lobe_table(cos_theta_h, beta, p, c, u)
    raise ValueError(f"unknown path {path!r}: use 'tables' or 'exact'")


# --------------------------------------------------------------------------------------------
# Compact table path: tabulated values of log L in a normalised angle t (see tablegen/CONVOLUTION.md).
#
# log (S*D)(θ_h) = log(cos²θ_h + k sin²θ_h) + g(ln β, ln(p − 0.1), ln(c − 0.7), asinh(u/u₀), t),
# g a 5-D C² cubic B-spline of *values*; t ∈ [0, 1] covers θ_h ∈ [0, π/2] for every parameter set.
#
# Angle coordinate (per sample, cheap):
#   a² = 1/(1 + 4u²)                      S's angular width² (sin units)
#   τ²/τ₀² = sin²θ_h / ((cos²θ_h + a²) a²) scaled angle; the a² in the bracket caps tan θ_h at the
#                                          horizon (1/a), so θ_h = π/2 sits at a finite coordinate
#   τ₀² = a²/(a² + β²),  q = smin(p, 1)   (q < 1 resolves D's cusp at θ = 0 for p < 1)
#   z = τ₀^{2q} [(1 + τ²/τ₀²)^q − 1],      ζ = log(1 + z)/(2q)   (≈ log τ in the tails)
#   s = ζ/ζ_end,  t = [λ ζ/ζ_π + (1 − λ) s (1 + s⁴)^{−1/4}] / T_max
# ζ_end: the end of the lobe's body, where D's part of the lobe or S alone, whichever reaches
# further, falls to 1e-4 of its peak (analytic, below). Not where S's faint tail ends: with D the
# wider, that point moves with c and u while the knee where D's body ends does not, and the knee
# then moved in t from node to node across the c and u axes (table version 3, errors up to 0.8).
# ζ_π = ζ(π/2); T_max = the bracket at ζ_π. About 60 % of the t nodes resolve the lobe's body
# (s ≤ 1), the rest (uniform in ζ) the tails and the horizon (lobes peaked at grazing for
# small p and large β). (log ζ_end, log ζ_π, log T_max) are smooth functions of (β, p, c, u);
# they are tabulated on the same parameter grid (extra ``map``) so that a sample pays one 1-D
# lookup instead of ~20 transcendentals, and log k on (ln β, ln(p − 0.1)) (extra ``log_k``).
# --------------------------------------------------------------------------------------------

TABLE_NAME = "convolution"

#: Share of the normalised angle t laid uniformly in ζ over the whole hemisphere.
MAP_LAMBDA = 0.4
#: Level (relative to the peak) at which the analytic end estimate ζ_end is placed.
MAP_END_LEVEL = 1e-4


#: The table's p axis is uniform in ``ln(p − P_OFFSET)``: with its 26 nodes, steps half as wide
#: at p = 0.2 as version 3's 22 in ln p (small p: D's heavy tail and grazing mass change fastest
#: with p), as wide at p = 5.
P_OFFSET = 0.1
#: The table's u axis is uniform in ``asinh(u / U_SCALE)`` (version 5): near u = 0 the lobe's
#: grazing side falls as ``[1 + 4u²(1 − μ²)]^{−(c+1)/2}``, by a factor 30 between u = 0 and 0.9
#: at c = 3.7, which version 4's steps in asinh u (0.4: nodes at u = 0, 0.41, 0.89) interpolated
#: with errors up to 0.05; with the scale those first steps are 3.5× narrower, the steps at large
#: u (in ln u there) 12 % wider, where the u axis was not the table's main error.
U_SCALE = 0.25
#: The table's c axis is uniform in ``ln(c − C_OFFSET)`` (version 6; version 5: ``ln(c − 1)``).
#: With its 14 nodes a step is 0.063 wide in c at c = 1.01 and 0.75 at c = 4.4 (version 5: 0.0046
#: and 1.6): version 5's worst errors sat between its top two nodes (c = 3.5, 5), where S's tail
#: exponent c + 1 reshapes the lobe's shoulder, and its finest steps near c = 1 bought nothing
#: (the errors of the sets with c ≤ 1.1 are the same with either axis).
C_OFFSET = 0.7
#: The p axis' first node. Below it the lookup is clamped, as on every axis (and ``p − P_OFFSET``
#: stays positive for any p).
P_TABLE_MIN = 0.2


def _coords(beta, p, c):
    # Below the first node a constant (the spline clamps there anyway, as version 3's did),
    # so that the logarithm's argument stays positive; from the node on, p itself.
    p_in = jnp.where(p >= P_TABLE_MIN, p, P_TABLE_MIN)
    return jnp.log(beta), jnp.log(p_in - P_OFFSET), jnp.log(c - C_OFFSET)


def params_of_coords(log_beta, log_p, log_c, asinh_u):
    """``(β, p, c, u)`` at table coordinates: the inverse of :func:`_coords` and of u's
    ``asinh(u / U_SCALE)`` (NumPy or Python floats; the builder's nodes, tests at a node)."""
    return (
        np.exp(log_beta),
        P_OFFSET + np.exp(log_p),
        C_OFFSET + np.exp(log_c),
        U_SCALE * np.sinh(asinh_u),
    )


def shape_exponent(p):
    """``q = smin(p, 1) = (p⁻⁴ + 1)^{−1/4}``: the exponent of the angle coordinate."""
    return (p**-4.0 + 1.0) ** -0.25


def _zeta(s2, c2, beta, q, a2):
    """``ζ`` from ``sin²θ_h``, ``cos²θ_h`` (see the comment above); finite gradients everywhere."""
    log_t02 = -jnp.log1p(beta * beta / a2)  # log τ₀²
    x = s2 / ((c2 + a2) * a2)  # τ²/τ₀² ≥ 0
    z = jnp.exp(q * log_t02) * jnp.expm1(q * jnp.log1p(x))
    return jnp.log1p(z) / (2.0 * q)


def _t_bracket(zeta, zeta_end, zeta_pi):
    s = zeta / zeta_end
    s2 = s * s
    return MAP_LAMBDA * zeta / zeta_pi + (1.0 - MAP_LAMBDA) * s * (1.0 + s2 * s2) ** -0.25


def map_params(beta, p, c, u):
    """``(log ζ_end, log ζ_π, log T_max)`` of the angle coordinate (analytic; broadcasting).

    Two-tail model of the lobe (small angles): relative to ``S(0) ∫D``, the lobe is
    ``≈ [D(θ)/d0 · ρ + S(θ)] / L₀`` with ``ρ = d0 ∫S dω`` and ``L₀ = ρ/(1 + ρ)``;
    ``∫S dω ≈ π (1 − (1+4u²)^{−(c−1)/2}) / (2(c−1)u²)``. The body ends at the larger of D's
    1e-4 point in that model (``(tan θ/β)^{2p} = ln((1+ρ)/ε)``) and S's own
    (``2u tan θ = ε^{−1/(c+1)}``), combined as a root sum of squares; ``ζ_end`` is then softly
    capped at ``ζ_π``. S's own point, not where S's tail falls to ε of the lobe's peak
    (``((1+ρ)/(ερ))^{1/(c+1)}``, table version 3): with D the wider (ρ ≪ 1) that point lies far
    out in the tail and moves with c and u, which moved D's knee in t from node to node.
    """
    a2 = 1.0 / (1.0 + 4.0 * u * u)
    q = shape_exponent(p)
    l4u = jnp.log1p(4.0 * u * u)
    big_a = 0.5 * (c - 1.0) * l4u
    safe_a = jnp.where(big_a > 0.0, big_a, 1.0)
    ratio_a = jnp.where(big_a > 0.0, -jnp.expm1(-safe_a) / safe_a, 1.0)  # (1 − e^{−A})/A
    safe_u2 = jnp.where(u > 0.0, u * u, 1.0)
    ratio_u = jnp.where(u > 0.0, l4u / (2.0 * safe_u2), 2.0)  # log(1+4u²)/(2u²)
    log_rho = log_d0(beta, p) + jnp.log(0.5 * math.pi * ratio_a * ratio_u)
    log_1p_rho = jnp.logaddexp(0.0, log_rho)
    log_eps = math.log(MAP_END_LEVEL)
    tan_d = beta * (log_1p_rho - log_eps) ** (0.5 / p)
    tan_s = jnp.sqrt(a2) * jnp.exp(-log_eps / (c + 1.0))
    tan2_end = tan_d * tan_d + tan_s * tan_s
    s2_end = tan2_end / (1.0 + tan2_end)
    zeta_raw = _zeta(s2_end, 1.0 - s2_end, beta, q, a2)
    one = jnp.ones_like(zeta_raw)
    zeta_pi = _zeta(one, 0.0 * one, beta, q, a2)
    zeta_end = (zeta_raw**-8.0 + zeta_pi**-8.0) ** -0.125  # soft min(ζ_end, ζ_π)
    t_max = _t_bracket(zeta_pi, zeta_end, zeta_pi)
    return jnp.stack([jnp.log(zeta_end), jnp.log(zeta_pi), jnp.log(t_max)], axis=-1)


def normalised_angle(cos_theta_h, u, beta, q, log_map):
    """The table's angle coordinate ``t ∈ [0, 1]`` (``log_map`` from :func:`map_params`).

    The bracket of :func:`_t_bracket` with ``ζ/ζ_end``, ``ζ/ζ_π`` and ``1/T_max`` as products by
    ``exp(−log …)`` and ``(1 + s⁴)^{−1/4}`` as ``1/√√(1 + s⁴)``: the same values to rounding,
    with square roots instead of a float64 ``pow`` and no divisions (hot path: once per sample
    and channel).
    """
    ct = jnp.clip(cos_theta_h, 0.0, 1.0)
    c2 = ct * ct
    s2 = (1.0 - ct) * (1.0 + ct)
    a2 = 1.0 / (1.0 + 4.0 * u * u)
    zeta = _zeta(s2, c2, beta, q, a2)
    inv_end, inv_pi, inv_max = (jnp.exp(-log_map[..., j]) for j in range(3))
    s = zeta * inv_end
    s4 = (s * s) * (s * s)
    root = jnp.sqrt(jnp.sqrt(1.0 + s4))
    bracket = MAP_LAMBDA * zeta * inv_pi + (1.0 - MAP_LAMBDA) * s / root
    return bracket * inv_max


def _splines(dtype):
    """``(g, log_map, log_k)``: the table's values over all 5 axes, its extra ``map`` (the angle
    coordinate's 3 parameters) over (β, p, c, u) and ``log_k`` over (β, p), from the table service."""
    return (
        tables.spline(TABLE_NAME, dtype),
        tables.spline(TABLE_NAME, dtype, "map", n_axes=4),
        tables.spline(TABLE_NAME, dtype, "log_k", n_axes=2),
    )


class LobeSlice(eqx.Module):
    """The table sliced at one ``(β, p, c)``: per sample a 1-D lookup of the angle map and a
    2-D cubic lookup (16 terms) of ``g`` in ``(asinh(u/U_SCALE), t)``. Call as ``slice(cos θ_h, u)``."""

    g: Spline
    log_map: Spline
    log_k: jax.Array
    beta: jax.Array
    q: jax.Array

    def __call__(self, cos_theta_h, u):
        au = asinh_nonneg(u * (1.0 / U_SCALE))
        t = normalised_angle(cos_theta_h, u, self.beta, self.q, self.log_map(au))
        ct = jnp.clip(cos_theta_h, 0.0, 1.0)
        base = ct * ct + jnp.exp(self.log_k) * (1.0 - ct) * (1.0 + ct)
        # On a grid (u per θ_d bin and channel, shared by every θ_h) contract along u once per u.
        shared = 4 * au.size <= t.size and self.g.coeffs.ndim == 2
        g = self.g.call_shared_first(au, t) if shared else self.g(au, t)
        return base * jnp.exp(g)


def lobe_spline(beta, p, c, dtype=jnp.float64) -> LobeSlice:
    """Slice the table at scalar ``(β, p, c)`` (once per parameter set); see :class:`LobeSlice`."""
    g, log_map, log_k = _splines(dtype)
    dt = g.dtype
    beta, p, c = (jnp.asarray(x, dt) for x in (beta, p, c))
    lb, lp, lc = _coords(beta, p, c)
    return LobeSlice(
        g.slice(lb, lp, lc), log_map.slice(lb, lp, lc), log_k(lb, lp), beta, shape_exponent(p)
    )


def lobe_from_components(lobe_slice: LobeSlice, cos_theta_h, u):
    """Evaluate a sliced table at per-sample ``cos θ_h`` and ``u`` (broadcasting)."""
    return lobe_slice(cos_theta_h, u)


def lobe_table(cos_theta_h, beta, p, c, u):
    """``(S*D)(θ_h)`` from the compact table (broadcasting; dtype of the arguments)."""
    dtype = float_dtype(cos_theta_h, beta, p, c, u)
    args = jnp.broadcast_arrays(*(jnp.asarray(a, dtype) for a in (cos_theta_h, beta, p, c, u)))
    shape = args[0].shape
    flat = [a.reshape(-1) for a in args]

    def one(a):
        ct, b, pp, cc, uu = a
        return lobe_spline(b, pp, cc, dtype)(ct, uu)

    # Sequential batches: each slice reads a 4⁵-block neighbourhood of the 5-D coefficient
    # tensor (a vmap over every point would materialise one block per point at once).
    return jax.lax.map(one, tuple(flat), batch_size=8).reshape(shape).astype(dtype)


def fit_params(beta, p, c, u, *, n_points: int = 1000, path: str = "exact"):
    """Parameters of the authors' 2-parameter form ``s [1 + (2u' sin θ_h)²]^{−(c+1)/2}`` (NumPy).

    Fitted like the authors (docs/model.md §3.8): ``n_points`` uniform in ``sin θ_h ∈ [0, 1)``,
    least squares on the lobe values. For regression checks against the authors' table, not for
    hot paths (scalar arguments).

    Returns:
        dict with ``s``, ``u_prime`` (the authors' form) and ``map`` (``log ζ_end``,
        ``log ζ_π``, ``log T_max`` of the table's angle coordinate at this point).
    """
    from scipy.optimize import least_squares

    sin_t = (np.arange(n_points) + 0.5) / n_points
    ct = np.sqrt(1.0 - sin_t**2)
    vals = np.asarray(lobe(ct, beta, p, c, u, path=path), dtype=np.float64)
    e = 0.5 * (c + 1.0)

    def resid(q):
        return q[0] * (1.0 + (2.0 * q[1] * sin_t) ** 2) ** (-e) - vals

    fit = least_squares(resid, [vals[0], max(u, 0.05)], method="lm")
    args = (jnp.float64(x) for x in (beta, p, c, u))
    return {
        "s": float(fit.x[0]),
        "u_prime": float(abs(fit.x[1])),
        "map": np.asarray(map_params(*args)),
    }

"""The convolution ``(S*D)(θ_h)`` of the small-scale function with the EPD [HP17 Eq. 39-41, 61-64].

``S(μ) = μ² [1 + 4u²(1 − μ²)]^{−(c+1)/2}`` with ``μ = h·m`` and ``u = B cos θ_d``;
``(S*D)(θ_h) = ∫_Ω S(h·m) D(m) dω_m`` over the upper hemisphere of microfacet normals ``m``
(``D`` is the normalised EPD of :mod:`twoscale.distribution`, zero below the horizon).

Integration range of ``S``. ``S`` is even in ``μ`` and defined on ``μ ∈ [−1, 1]``. The integral
above runs over every ``m`` of the upper hemisphere, including normals with ``h·m < 0`` (possible
when ``θ_h + θ_m > π/2``); there ``S`` takes its value at ``−μ``. In zonal harmonics this is
``S_l = 2π ∫_{−1}^{1} S Y_l dμ`` (Funk-Hecke needs the whole range: only even ``l`` survive), while
``D_l = 2π ∫_0^1 D Y_l dμ`` since ``D`` vanishes below the horizon. Truncating ``S`` to ``μ ≥ 0``
(``∫_0^1``, as MODEL.md §3.8 writes ``f_l``) would compute a different integral, with
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
    The compact representation (see :func:`lobe_from_components`), per-node parameters
    interpolated over ``(log β, log p, log(c−1), asinh u)`` by the C² spline of
    :mod:`twoscale.tables`.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from twoscale._numerics import float_dtype, safe_log, safe_sqrt
from twoscale.distribution import log_d0

__all__ = [
    "N_COEFFS",
    "fit_params",
    "lobe",
    "lobe_exact",
    "lobe_from_components",
    "lobe_spline",
    "lobe_table",
    "small_scale",
]

#: Chebyshev coefficients per table node (the polynomial part of the compact form).
N_COEFFS = 10

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
    ``exp(−inf)·inf`` (MODEL.md §6 traps 1-2).
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
        ``tables/CONVOLUTION.md``). At exactly ``cos θ_h = 1`` the derivative in ``cos θ_h`` is
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
# Compact table path.
#
# log (S*D)(θ_h) = log(cos²θ_h + k sin²θ_h) + P(t),  P(t) = Σ_{j<K} a_j T_j(2t − 1),
# t = ξ/ξ_end,  ξ = ½ log(1 + sin²θ_h/w²),  w² = 1/(1 + 4u²) + β²,
# and for t > 1 the linear continuation P(1) + min(P'(1), 0)(t − 1) (C¹ where P'(1) ≤ 0).
# Components per node: (log k, log ξ_end, a_0 … a_{K−1}), over (ln β, ln p, ln(c−1), asinh u).
# --------------------------------------------------------------------------------------------

TABLE_NAME = "convolution"


def _table():
    from twoscale.tables import load_table

    return load_table(TABLE_NAME)


def _coords(beta, p, c):
    return jnp.log(beta), jnp.log(p), jnp.log(c - 1.0)


def lobe_spline(beta, p, c, dtype=jnp.float64):
    """Slice the table at scalar ``(β, p, c)``: a 1-D :class:`~twoscale.tables.Spline` over ``asinh u``.

    Call it once per parameter set; evaluate per sample with :func:`lobe_from_components`
    (``comps = spline(jnp.arcsinh(u))``).
    """
    spline = _table().spline(dtype)
    return spline.slice(*_coords(beta, p, c))


def _chebyshev(t, coeffs):
    """``Σ a_j T_j(x)`` and its derivative in ``t`` (``x = 2t − 1``), by the three-term recurrence."""
    x = 2.0 * t - 1.0
    t_prev, t_cur = jnp.ones_like(x), x
    d_prev, d_cur = jnp.zeros_like(x), jnp.ones_like(x)  # dT_j/dx
    val = coeffs[..., 0] + coeffs[..., 1] * x
    der = coeffs[..., 1]
    for j in range(2, coeffs.shape[-1]):
        t_next = 2.0 * x * t_cur - t_prev
        d_next = 2.0 * t_cur + 2.0 * x * d_cur - d_prev
        val = val + coeffs[..., j] * t_next
        der = der + coeffs[..., j] * d_next
        t_prev, t_cur, d_prev, d_cur = t_cur, t_next, d_cur, d_next
    return val, 2.0 * der


def lobe_from_components(comps, cos_theta_h, beta, u):
    """Evaluate the compact form from interpolated components ``comps`` (..., 2 + K).

    ``log L = log(cos²θ_h + k sin²θ_h) + P(t)`` (see the comment above); ``beta`` and ``u``
    enter through the analytic width ``w² = 1/(1 + 4u²) + β²``.
    """
    ct = jnp.clip(cos_theta_h, 0.0, 1.0)
    c2 = ct * ct
    s2 = (1.0 - ct) * (1.0 + ct)
    log_k, log_xi_end, coeffs = comps[..., 0], comps[..., 1], comps[..., 2:]
    w2 = 1.0 / (1.0 + 4.0 * u * u) + beta * beta
    t = 0.5 * jnp.log1p(s2 / w2) * jnp.exp(-log_xi_end)
    t_in = jnp.minimum(t, 1.0)  # double where: the polynomial is only used on [0, 1]
    val_in, _ = _chebyshev(t_in, coeffs)
    val_1, der_1 = _chebyshev(jnp.ones_like(t), coeffs)
    poly = jnp.where(t <= 1.0, val_in, val_1 + jnp.minimum(der_1, 0.0) * (t - 1.0))
    return jnp.exp(jnp.log(c2 + jnp.exp(log_k) * s2) + poly)


def lobe_table(cos_theta_h, beta, p, c, u):
    """``(S*D)(θ_h)`` from the compact table (broadcasting; dtype of the arguments)."""
    dtype = float_dtype(cos_theta_h, beta, p, c, u)
    args = jnp.broadcast_arrays(*(jnp.asarray(a, dtype) for a in (cos_theta_h, beta, p, c, u)))
    ct, beta, p, c, u = args
    spline = _table().spline(dtype)

    def components(b, pp, cc, au):
        # Slice then 1-D lookup: 3 small contractions instead of the 256-term 4-D sum (whose
        # unrolled graph is slow to trace and compile).
        return spline.slice(*_coords(b, pp, cc))(au)

    flat = [a.reshape(-1) for a in (beta, p, c, jnp.arcsinh(u))]
    comps = jax.vmap(components)(*flat).reshape(*ct.shape, -1)
    return lobe_from_components(comps, ct, beta, u).astype(dtype)


def fit_params(beta, p, c, u, *, n_points: int = 1000, path: str = "exact"):
    """Parameters of the authors' 2-parameter form ``s [1 + (2u' sin θ_h)²]^{−(c+1)/2}`` (NumPy).

    Fitted like the authors (MODEL.md §3.8): ``n_points`` uniform in ``sin θ_h ∈ [0, 1)``,
    least squares on the lobe values. Also returns the compact components at this point.
    For regression checks against the authors' table, not for hot paths (scalar arguments).

    Returns:
        dict with ``s``, ``u_prime`` (the authors' form) and ``components`` (``log k``,
        ``log ξ_end``, ``a_j`` of the compact table, interpolated).
    """
    from scipy.optimize import least_squares

    sin_t = (np.arange(n_points) + 0.5) / n_points
    ct = np.sqrt(1.0 - sin_t**2)
    vals = np.asarray(lobe(ct, beta, p, c, u, path=path), dtype=np.float64)
    e = 0.5 * (c + 1.0)

    def resid(q):
        return q[0] * (1.0 + (2.0 * q[1] * sin_t) ** 2) ** (-e) - vals

    fit = least_squares(resid, [vals[0], max(u, 0.05)], method="lm")
    comps = _table().spline(jnp.float64)(*_coords(beta, p, c), jnp.arcsinh(u))
    return {"s": float(fit.x[0]), "u_prime": float(abs(fit.x[1])), "components": np.asarray(comps)}

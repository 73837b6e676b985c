"""Band-limited zonal-harmonic convolution ``(S*D)(θ_h)`` [HP17 Eq. 39-41; docs/model.md §3.8].

Both factors of ``(S*D)(θ_h) = ∫_Ω S(h·m) D(m) dω_m`` are zonal: ``D`` about the normal ``n``,
``S`` about ``h``. With ``Y_l(μ) = √((2l+1)/4π) P_l(μ)`` and the projections

    ``D_l = 2π ∫_0^1  D(μ) Y_l(μ) dμ``     (``D`` vanishes below the horizon)
    ``S_l = 2π ∫_{−1}^1 S(μ) Y_l(μ) dμ``    (``S`` is even: only even ``l`` survive)

the Funk-Hecke theorem gives ``(S*D)_l = √(4π/(2l+1)) S_l D_l`` and

    ``(S*D)(θ_h) = Σ_{l<l_max} (S*D)_l Y_l(cos θ_h) = Σ_{l<l_max} S_l D_l P_l(cos θ_h)``.

The sum is exact as ``l_max → ∞``; the authors used ``l < 100`` (docs/model.md §3.8). The range of
``S`` is the whole ``[−1, 1]`` so that the series reproduces the integral over the upper
hemisphere of ``m`` exactly as :func:`twoscale.convolution.lobe_exact` computes it (see
``tablegen/CONVOLUTION.md``, "Integration range of S"); ``half_range=True`` in
:func:`small_scale_coefficients` gives the literal ``∫_0^1`` of docs/model.md §3.8 (it inserts ``χ(h·m > 0)``).

Projections. Fixed composite Gauss-Legendre rules in ``θ ∈ [0, π/2]`` (``μ = cos θ``), so every
coefficient is a smooth function of the parameters and differentiable. The panel edges are the
union, sorted, of

* uniform edges ``jπ/(2M)``, ``M = ⌈l_max/8⌉ + 2``: every panel is at most ~2 wavelengths of
  ``P_{l_max}`` wide, so the oscillation is resolved by :data:`N_GL` nodes;
* feature edges that follow the function: for ``D``, ``tan θ = β v_k^{1/(2p)}`` with ``v_k``
  geometric in ``[10⁻³, 60]`` (``v = (tan θ/β)^{2p}`` is the Gamma(1/p)-distributed variable of
  the sampling formula, Eq. 49-50: these edges grade the flat top and sharp shoulder of large
  ``p``, the cusp of small ``p``, its heavy tail and the spike of ``D`` at the horizon for small
  ``p`` and large ``β``); for ``S``, ``sin θ = t_k/(2u)`` with ``t_k`` geometric in
  ``[0.02, 5000]`` (``S`` is a power-law peak of width ``1/(2u)``; edges beyond the horizon
  collapse on ``π/2`` and give empty panels).

Legendre polynomials come from the three-term recurrence
``(l+1) P_{l+1} = (2l+1) μ P_l − l P_{l−1}``, stable for ``|μ| ≤ 1``.

Where a band limit cannot resolve the lobe. The series converges once *either* spectrum has
decayed: ``S_l/S_0 ~ exp(−l·asinh(1/(2u)))`` (poles of ``S`` at ``sin θ = ±i/(2u)``) and, for
``p = 1``, ``D_l/D_0 ~ exp(−l²β²/4)`` (Beckmann). So the band limit follows the *wider* of S
and D, roughly ``l_max ≈ 10/max(1/(2u), β)``: it fails only when both are narrow (small β
*and* large u). Exception: D's non-smooth features (the cusp at ``θ = 0`` for ``p < 1``, where
``D_l`` decays only algebraically, ``~ (lβ)^{−2−2p}``; the sharp shoulder of large ``p``; the
horizon spike of small ``p``, large ``β``) are smoothed only by S, at scale ``1/(2u)``, so
there large ``u`` alone needs many harmonics. :func:`required_l_max` bounds the truncation
error by the spectral tail (a sufficient rule, 1-4× conservative, ``tablegen/HARMONICS.md``).
Below it, the truncated series rings (Gibbs): values oscillate
around the lobe and can be **negative** in its tail; they are returned as computed (finite,
with finite gradients), not clamped, so that the truncation stays visible.

Measured (``tablegen/HARMONICS.md``): coefficients to ≤ 3e-12 of ``D_0``/``S_0`` (2.9e-9 at
β = 1, p = 0.2); where resolved, agreement with :func:`twoscale.convolution.lobe_exact` to
1e-14 … 2e-9. At ``l_max = 100`` the fitted ``(s, u')`` of the authors' table (docs/model.md §3.8)
are reproduced to ≤ 1.3 % in ``u'``, including its saturation (p = 5, β = 0.0029, u = 30:
u' = 15.8 against the authors' 15.9 and the converged 29.5); ``s`` agrees to ≤ 1 % except a
constant ~1.22 factor at p = 5, β = 0.0029 that the band limit does not explain.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from twoscale._numerics import float_dtype, gauss_legendre
from twoscale.distribution import log_d0

__all__ = [
    "N_GL",
    "convolution_coefficients",
    "legendre",
    "legendre_coefficients",
    "lobe_harmonic",
    "ndf_coefficients",
    "required_l_max",
    "small_scale_coefficients",
    "zonal_sum",
]

#: Gauss-Legendre nodes per panel of the projections.
N_GL = 12

#: Geometric feature levels: ``v = (tan θ/β)^{2p}`` for D, ``t = 2u sin θ`` for S.
_V_LEVELS = np.geomspace(1e-3, 60.0, 16)
_T_LEVELS = np.geomspace(0.02, 5000.0, 20)

#: Parameter sets whose coefficients are computed together (bounds the (batch, nodes) arrays).
_BATCH = 32


def _check_l_max(l_max) -> int:
    if isinstance(l_max, bool) or not isinstance(l_max, int | np.integer):
        raise TypeError(f"l_max must be a concrete int (static), got {type(l_max).__name__}")
    if l_max < 1:
        raise ValueError(f"l_max must be ≥ 1, got {l_max}")
    return int(l_max)


def _n_uniform(l_max: int) -> int:
    return -(-l_max // 8) + 2


def legendre(x, l_max: int):
    """``P_0(x) … P_{l_max−1}(x)`` stacked on a new last axis, by the three-term recurrence.

    ``(l+1) P_{l+1} = (2l+1) x P_l − l P_{l−1}``, ``P_0 = 1``, ``P_1 = x`` (stable on
    ``|x| ≤ 1``). Shape ``x.shape + (l_max,)``, dtype of ``x``.
    """
    l_max = _check_l_max(l_max)
    x = jnp.asarray(x)
    dtype = float_dtype(x)
    x = x.astype(dtype)

    def step(carry, l):
        p_prev, p_cur = carry
        p_next = ((2.0 * l + 1.0) * x * p_cur - l * p_prev) / (l + 1.0)
        return (p_cur, p_next), p_cur

    init = (jnp.zeros_like(x), jnp.ones_like(x))
    _, ps = jax.lax.scan(step, init, jnp.arange(l_max, dtype=dtype))
    return jnp.moveaxis(ps, 0, -1)


def _moments(x, fw, l_max: int):
    """``Σ_i fw_i P_l(x_i)`` over the last axis, for ``l < l_max`` (recurrence, no P matrix)."""

    def step(carry, l):
        p_prev, p_cur = carry
        p_next = ((2.0 * l + 1.0) * x * p_cur - l * p_prev) / (l + 1.0)
        return (p_cur, p_next), jnp.sum(fw * p_cur, axis=-1)

    init = (jnp.zeros_like(x), jnp.ones_like(x))
    _, m = jax.lax.scan(step, init, jnp.arange(l_max, dtype=x.dtype))
    return jnp.moveaxis(m, 0, -1)


def _y_norm(l_max: int, dtype):
    """``√((2l+1)/4π)`` for ``l < l_max``."""
    l = jnp.arange(l_max, dtype=dtype)
    return jnp.sqrt((2.0 * l + 1.0) / (4.0 * math.pi))


def legendre_coefficients(values, cos_theta, weights, *, l_max: int):
    """Zonal projection ``f_l = 2π ∫ f(μ) Y_l(μ) dμ`` from a quadrature rule [docs/model.md §3.8].

    Args:
        values: ``f`` at the nodes, (..., n).
        cos_theta: the nodes ``μ_i`` (..., n), in [−1, 1].
        weights: quadrature weights in ``μ`` (..., n) (for a rule in ``θ``: ``w_θ sin θ``).
        l_max: number of coefficients (static).
    Returns:
        ``f_l`` for ``l = 0 … l_max−1`` on a new last axis (replacing the node axis).
    """
    l_max = _check_l_max(l_max)
    dtype = float_dtype(values, cos_theta, weights)
    x = jnp.asarray(cos_theta, dtype)
    fw = jnp.asarray(values, dtype) * jnp.asarray(weights, dtype)
    x, fw = jnp.broadcast_arrays(x, fw)
    return 2.0 * math.pi * _y_norm(l_max, dtype) * _moments(x, fw, l_max)


def _panel_rule(edges, dtype):
    """Composite Gauss-Legendre nodes and weights in θ from unsorted panel edges (..., K)."""
    e = jnp.sort(edges, axis=-1)
    lo, hi = e[..., :-1, None], e[..., 1:, None]
    gx, gw = (jnp.asarray(a, dtype) for a in gauss_legendre(N_GL))
    theta = (lo + (hi - lo) * gx).reshape(*e.shape[:-1], -1)
    w = ((hi - lo) * gw).reshape(*e.shape[:-1], -1)
    return theta, w


def _uniform_edges(l_max, dtype):
    m = _n_uniform(l_max)
    return jnp.asarray(np.linspace(0.0, 0.5 * np.pi, m + 1), dtype)


def _ndf_coeffs_flat(beta, p, l_max):
    """``D_l`` for 1-D arrays ``beta``, ``p`` (one row per parameter set)."""
    dtype = beta.dtype
    b, pp = beta[:, None], p[:, None]
    # Feature edges tan θ = β v^{1/(2p)}; the exponent is capped so that exp cannot overflow
    # for very small p (atan saturates at π/2 long before).
    log_v = jnp.asarray(np.log(_V_LEVELS), dtype)
    feat = jnp.arctan(jnp.exp(jnp.minimum(jnp.log(b) + log_v / (2.0 * pp), 60.0)))
    uni = jnp.broadcast_to(_uniform_edges(l_max, dtype), (beta.shape[0], _n_uniform(l_max) + 1))
    theta, w = _panel_rule(jnp.concatenate([uni, feat], axis=-1), dtype)
    # GL nodes are interior: 0 < θ < π/2, so sin, cos > 0 and the logs are finite.
    sin_t, cos_t = jnp.sin(theta), jnp.cos(theta)
    log_sin, log_cos = jnp.log(sin_t), jnp.log(cos_t)
    # (tan θ/β)^{2p}, capped at e^{60}: exp(−e^{60}) is 0 with a zero (not NaN) gradient, and
    # 1/cos⁴θ is applied in logs (docs/model.md §6 traps 1-2).
    expo = jnp.exp(jnp.minimum(2.0 * pp * (log_sin - log_cos - jnp.log(b)), 60.0))
    d = jnp.exp(log_d0(b, pp) - expo - 4.0 * log_cos)
    return legendre_coefficients(d, cos_t, w * sin_t, l_max=l_max)


def _small_scale_coeffs_flat(c, u, l_max, half_range):
    """``S_l`` for 1-D arrays ``c``, ``u``."""
    dtype = c.dtype
    cc, uu = c[:, None], u[:, None]
    # Feature edges sin θ = t/(2u), at the horizon where t ≥ 2u. Double where: arcsin has an
    # infinite slope at 1 and t/(2u) is infinite at u = 0, so neither may see those inputs.
    t = jnp.asarray(_T_LEVELS, dtype)
    inside = t < 2.0 * uu
    arg = jnp.where(inside, t / jnp.where(inside, 2.0 * uu, 1.0), 0.0)
    feat = jnp.where(inside, jnp.arcsin(arg), 0.5 * math.pi)
    uni = jnp.broadcast_to(_uniform_edges(l_max, dtype), (c.shape[0], _n_uniform(l_max) + 1))
    theta, w = _panel_rule(jnp.concatenate([uni, feat], axis=-1), dtype)
    sin_t, cos_t = jnp.sin(theta), jnp.cos(theta)
    s = cos_t * cos_t * jnp.exp(-0.5 * (cc + 1.0) * jnp.log1p(4.0 * uu * uu * sin_t * sin_t))
    half = legendre_coefficients(s, cos_t, w * sin_t, l_max=l_max)
    if half_range:
        return half
    # S(−μ) = S(μ) and P_l(−μ) = (−1)^l P_l(μ): ∫_{−1}^{1} = (1 + (−1)^l) ∫_0^1.
    even = jnp.asarray(np.arange(l_max) % 2 == 0, dtype)
    return 2.0 * even * half


def _per_set(fn, args, l_max):
    """Apply ``fn`` (1-D parameter arrays → (n, l_max)) over broadcast ``args`` in batches."""
    args = jnp.broadcast_arrays(*args)
    shape = args[0].shape
    flat = tuple(a.reshape(-1) for a in args)
    n = flat[0].shape[0]
    if n <= _BATCH:
        out = fn(*flat)
    else:
        pad = (-n) % _BATCH
        # Pad with a copy of the first set (a valid point: no NaN in the discarded rows).
        padded = tuple(jnp.concatenate([a, jnp.broadcast_to(a[:1], (pad,))]) for a in flat)
        batched = tuple(a.reshape(-1, _BATCH) for a in padded)
        out = jax.lax.map(lambda xs: fn(*xs), batched).reshape(-1, l_max)[:n]
    return out.reshape(*shape, l_max)


def ndf_coefficients(beta, p, *, l_max: int = 100):
    """Zonal coefficients ``D_l = 2π ∫_0^1 D(μ) Y_l(μ) dμ`` of the normalised EPD [HP17 Eq. 34-35].

    Args:
        beta: EPD roughness β > 0.
        p: EPD shape p > 0.
        l_max: number of coefficients, ``l = 0 … l_max−1`` (static).
    Returns:
        (..., l_max), broadcast shape of ``beta`` and ``p``, their floating dtype.
        ``D_1 = √(3/4π)`` exactly (normalisation ``∫ D cos θ dω = 1``); relative accuracy of
        the quadrature ~1e-12 in float64 (measured in ``tablegen/HARMONICS.md``).
    """
    l_max = _check_l_max(l_max)
    dtype = float_dtype(beta, p)
    args = (jnp.asarray(beta, dtype), jnp.asarray(p, dtype))
    return _per_set(lambda b, pp: _ndf_coeffs_flat(b, pp, l_max), args, l_max)


def small_scale_coefficients(c, u, *, l_max: int = 100, half_range: bool = False):
    """Zonal coefficients ``S_l = 2π ∫_{−1}^1 S(μ) Y_l(μ) dμ`` of the small-scale function.

    ``S(μ) = μ² [1 + 4u²(1 − μ²)]^{−(c+1)/2}`` [docs/model.md §3.8]. Odd ``l`` vanish (S is even).

    Args:
        c: PSD exponent, > 1.
        u: ``B cos θ_d`` ≥ 0.
        l_max: number of coefficients (static).
        half_range: integrate over ``μ ∈ [0, 1]`` only (the literal ``f_l`` of docs/model.md §3.8; the
            convolution then carries ``χ(h·m > 0)``). Default: the whole range (static).
    Returns:
        (..., l_max), broadcast shape of ``c`` and ``u``, their floating dtype.
    """
    l_max = _check_l_max(l_max)
    dtype = float_dtype(c, u)
    args = (jnp.asarray(c, dtype), jnp.asarray(u, dtype))
    return _per_set(
        lambda cc, uu: _small_scale_coeffs_flat(cc, uu, l_max, bool(half_range)), args, l_max
    )


def convolution_coefficients(beta, p, c, u, *, l_max: int = 100):
    """``(S*D)_l = √(4π/(2l+1)) S_l D_l`` (Funk-Hecke) [docs/model.md §3.8]; shape (..., l_max)."""
    l_max = _check_l_max(l_max)
    dtype = float_dtype(beta, p, c, u)
    d_l = ndf_coefficients(jnp.asarray(beta, dtype), jnp.asarray(p, dtype), l_max=l_max)
    s_l = small_scale_coefficients(jnp.asarray(c, dtype), jnp.asarray(u, dtype), l_max=l_max)
    return s_l * d_l / _y_norm(l_max, dtype)


def zonal_sum(coeffs, cos_theta):
    """``f(θ) = Σ_l f_l Y_l(cos θ)`` for coefficients ``f_l`` on the last axis (recurrence).

    ``coeffs`` (..., L) broadcasts against ``cos_theta`` (...). Differentiable in both; a
    polynomial in ``cos θ``, so smooth up to and including ``cos θ = ±1``.
    """
    coeffs = jnp.asarray(coeffs)
    x = jnp.asarray(cos_theta)
    dtype = float_dtype(coeffs, x)
    n_l = coeffs.shape[-1]
    scaled = coeffs.astype(dtype) * _y_norm(n_l, dtype)  # f_l Y_l = f_l √((2l+1)/4π) P_l
    shape = jnp.broadcast_shapes(scaled.shape[:-1], x.shape)
    x = jnp.broadcast_to(x.astype(dtype), shape)
    a = jnp.moveaxis(jnp.broadcast_to(scaled, (*shape, n_l)), -1, 0)

    def step(carry, inp):
        p_prev, p_cur, acc = carry
        a_l, l = inp
        p_next = ((2.0 * l + 1.0) * x * p_cur - l * p_prev) / (l + 1.0)
        return (p_cur, p_next, acc + a_l * p_cur), None

    init = (jnp.zeros_like(x), jnp.ones_like(x), jnp.zeros_like(x))
    (_, _, acc), _ = jax.lax.scan(step, init, (a, jnp.arange(n_l, dtype=dtype)))
    return acc


def lobe_harmonic(cos_theta_h, beta, p, c, u, *, l_max: int = 100):
    """``(S*D)(θ_h)`` as the band-limited zonal-harmonic sum [HP17 Eq. 39-41; docs/model.md §3.8].

    ``(S*D)(θ_h) = Σ_{l<l_max} √(4π/(2l+1)) S_l D_l Y_l(cos θ_h) = Σ_{l<l_max} S_l D_l P_l(cos θ_h)``
    with ``D_l``, ``S_l`` from :func:`ndf_coefficients`, :func:`small_scale_coefficients`.

    Args:
        cos_theta_h: cosine of the half-vector angle, in [0, 1].
        beta, p: EPD roughness and shape.
        c: PSD exponent, > 1.
        u: ``B cos θ_d`` ≥ 0.
        l_max: band limit, ``l = 0 … l_max−1`` (static; the authors used 100).
    Returns:
        The lobe (1/sr), broadcast shape of the arguments, their floating dtype. Converges to
        :func:`twoscale.convolution.lobe_exact` as ``l_max`` grows; accurate where
        ``l_max ≥ required_l_max(β, u, p)``. Below that the truncated series rings (Gibbs): it
        may be **negative** in the tail; values and gradients stay finite.

    Cost: ``D_l`` is computed once per element of the broadcast shape of ``(β, p)`` and
    ``S_l`` per element of that of ``(c, u)``, so shared parameters are projected once.
    """
    l_max = _check_l_max(l_max)
    dtype = float_dtype(cos_theta_h, beta, p, c, u)
    ct = jnp.clip(jnp.asarray(cos_theta_h, dtype), 0.0, 1.0)
    beta, p, c, u = (jnp.asarray(a, dtype) for a in (beta, p, c, u))
    d_l = ndf_coefficients(beta, p, l_max=l_max)
    s_l = small_scale_coefficients(c, u, l_max=l_max)
    # f_l Y_l with f_l = √(4π/(2l+1)) S_l D_l: the normalisations cancel to S_l D_l P_l.
    coeffs = s_l * d_l / _y_norm(l_max, dtype)
    return zonal_sum(coeffs, ct).astype(dtype)


@functools.partial(jax.jit, static_argnames="l_cap")
def _spectrum(beta, p, c, u, l_cap):
    """``|S_l D_l|`` for ``l < l_cap`` and the series' value at ``θ_h = 0``, ``Σ S_l D_l``."""
    t = small_scale_coefficients(c, u, l_max=l_cap) * ndf_coefficients(beta, p, l_max=l_cap)
    return jnp.abs(t), jnp.sum(t, axis=-1)


def required_l_max(beta, u, p=1.0, c=2.0, *, rtol: float = 1e-2, l_cap: int = 2048):
    """Smallest band limit whose truncation error is ≤ ``rtol`` where the lobe is ≥ 1e-3 of its peak.

    Rule: since ``|P_l| ≤ 1``, the error of :func:`lobe_harmonic` at any ``θ_h`` is bounded by
    the spectral tail ``Σ_{l ≥ l_max} |S_l D_l|``; this returns the smallest ``l_max`` with
    ``tail ≤ rtol · 10⁻³ · (S*D)(0)`` (the lobe at normal incidence stands in for its peak, a
    conservative choice), from the coefficients up to ``l_cap``. A sufficient condition:
    measured on 70 random points it exceeds the band limit actually needed by a factor
    1-4 (``tablegen/HARMONICS.md``).

    Scale: the product spectrum decays once either factor does, so the band limit follows the
    *wider* of S and D: ``S_l ~ exp(−l·asinh(1/(2u)))``, ``D_l ~ exp(−l²β²/4)`` (Beckmann) —
    roughly ``l_max ≈ 10/max(1/(2u), β)`` — except that D's non-smooth features (the cusp at
    ``θ = 0`` for ``p < 1``, the sharp shoulder for large ``p``, the horizon spike for small
    ``p`` and large ``β``) are smoothed only by S, at scale ``1/(2u)``; then large ``u`` alone
    needs a large band limit (β = 0.9, p = 0.2, u = 30: ``l ≈ 450``).

    Args:
        beta, u, p, c: the lobe's parameters (broadcast; NumPy or JAX arrays, concrete).
        rtol: target relative accuracy.
        l_cap: largest band limit considered (static); where the tail beyond ``3/4 l_cap``
            has not yet fallen below the target, ``l_cap + 1`` is returned (unresolved).
    Returns:
        int64 NumPy array of the broadcast shape: a value to pass (its maximum) as the static
        ``l_max``. Not traceable (it sizes a static argument).
    """
    args = np.broadcast_arrays(*(np.asarray(a, np.float64) for a in (beta, p, c, u)))
    shape = args[0].shape
    flat = [jnp.asarray(a.reshape(-1)) for a in args]
    terms, value0 = (np.asarray(a) for a in _spectrum(*flat, l_cap=int(l_cap)))
    tail = np.cumsum(terms[:, ::-1], axis=-1)[:, ::-1]  # tail[:, L] = Σ_{l ≥ L} |S_l D_l|
    ok = tail <= rtol * 1e-3 * np.abs(value0)[:, None]
    ok[:, (3 * l_cap) // 4 + 1 :] = False  # the last quarter only certifies the tail
    first = np.where(ok.any(axis=-1), ok.argmax(axis=-1), l_cap + 1)
    return np.maximum(first, 1).astype(np.int64).reshape(shape)

"""Nano-scale roughness: the K-correlation (ABC) PSD and its renormalisation [HP17 Eq. 16, 19].

PSD (docs/model.md §3.4), ``f`` in 1/µm, ``σ_s`` and ``b`` in µm, ``c > 1``::

    S_HS(f) = (c−1)/(2π) · σ_s² b² · (1 + b² f²)^{−(c+1)/2},      ∫_{R²} S_HS d²f = σ_s².

Renormalisation (docs/model.md §3.5): the part of the PSD that falls on propagating directions,
``σ_rel²(θ) = ∫_{‖o_xy‖≤1} S_HS((o_xy + i_xy)/λ) d²o_xy / λ²``, as the dimensionless ratio
``R(s; B, c) = σ_rel²/σ_s²`` with ``s = sin θ`` and ``B = b/λ``. docs/model.md §3.5 writes it as a radial
integral around the specular point::

    R = G(1−s) + ∫_{1−s}^{1+s} w(r) g(r) dr,   G(r) = 1 − (1 + B²r²)^{−a},   g = G',   a = (c−1)/2,

with ``w(r)`` the fraction of the circle of radius ``r`` inside the unit disk. ``w`` has square-root
kinks at both ends and ``g`` is sharp (width 1/B) near ``r = 0`` for large B, which makes that form
a poor quadrature target. **Derived** (checked against SciPy/mpmath quadrature of the form above):
integrating by parts and substituting ``r² = 1 + s² − 2s cos ψ`` (``ψ`` the angle, at the disk
centre, of the boundary point) turns ``−w'(r) dr`` into ``(1/π)(1 − s cos ψ)/r² dψ`` — half the
uniform measure plus half the Poisson kernel of the unit disk at ``s`` — so that::

    R(s; B, c) = (1/π) ∫_0^π (1 − s cos ψ) · G(r)/r² dψ,      r² = (1−s)² + 4 s sin²(ψ/2).

The integrand is analytic in ψ (``G(r)/r²`` is analytic in ``r²``); its only singularities are the
branch points ``1 + B² r² = 0``, at ``ψ = ±iψ_c``, ``ψ_c = acosh(1 + ((1−s)² + B⁻²)/(2s))``. The
substitution ``ψ = ψ_c sinh v`` puts them at ``Im v = ±π/2`` whatever (s, B, c), so a fixed
48-node Gauss-Legendre rule in ``v`` converges geometrically everywhere. Measured (float64): ≤ 2e-14
relative to 25-digit mpmath on 67 points including the corners ``s ∈ {0, 1}``, ``B ∈ {1e-2, 1e4}``,
``c ∈ {1.01, 10}``; ≤ 7e-13 against the SciPy reference of ``tablegen/check_renorm.py`` (the
reference's own accuracy). 32 nodes already give ≤ 3e-12.

Stable scaled form (docs/model.md §6 traps 4-5). Dividing by the small-B asymptote ``(c−1)B²/2 = aB²``::

    ρ(s; B, c) = R/(aB²) = (1/π) ∫_0^π (1 − s cos ψ) · ℓ(B²r²) · φ(−a log(1 + B²r²)) dψ,

    ℓ(x) = log(1+x)/x,   φ(z) = (eᶻ − 1)/z        (both → 1 at 0, evaluated with series there)

is finite and smooth for all ``B ≥ 0``, ``c ≥ 1`` and tends to 1 as ``B → 0`` (for every s and c).
Hence ``R = aB² ρ`` and the ratio the diffraction lobe needs is ``(c−1)B²/R = 2/ρ``.

Small-B asymptote (derived from the series of G): ``R = aB² [1 − (c+1)(1+2s²) B²/4 + O(B⁴)]``, so
``(c−1)B²/R → 2 [1 + (c+1)(1+2s²) B²/4]`` as B → 0 (exactly 2 in the limit, for all s, c).
Large-B limit: ``R → 1`` for s < 1 and ``R → 1/2`` at s = 1 (the specular point on the disk edge).

Table path (``path="tables"``, the default): ``twoscale/data/renormalisation.npz`` built by
``python -m tablegen.build_renorm``. It stores the smooth, bounded quantity::

    q̃ = (1 + B⁻²) · log[R(s; B, c) / R(0; B, c)],     R(0; B, c) = 1 − (1+B²)^{−a}  (closed form)

on a uniform grid in ``(log10 B, log10(c−1), x)`` with the s coordinate last,
``x = asinh(B(1−s))/asinh(B)``: it resolves the transition of width ~1/B at s → 1 for large B,
is ≈ 1−s for small B, maps s = 1 to 0 and s = 0 to 1. ``q̃`` is 0 at s = 0, bounded, and tends to
``−(c+1)s²/2`` as B → 0. Interpolation is the C² cubic B-spline of :mod:`twoscale.tables` on a
63 × 33 × 99 grid (1.5 MB). Measured by ``python -m tablegen.check_renorm`` (20 000 random points,
30 % of them with ``1 − s`` log-uniform in [1e-8, 1], plus the domain's corners): maximum relative
error in R (and in ``(c−1)B²/R``) 2.9e-5, 99th percentile 4e-6; log-derivatives agree with the
exact path to ≲ 1e-4. The grid extends one step beyond the physical domain on every axis, so
that the domain's edges (``s ∈ {0, 1}``, ``B = 1e-2``, ``c = 1.01``) are interior points of the
spline and keep its full gradient (a clamp there would halve or zero it); beyond the ends of
``x`` the grid holds the analytic continuation of the ψ integral (s > 1) and the even extension
R(−s) = R(s).

Outside the table (documented rule, all continuous):

* ``B < B_lo`` (10^−2.1): ``q = q̃(s, B_lo, c) · B²/(1+B²)`` — the small-B asymptote above, with
  its coefficient read from the table edge (relative error in R ≲ 1e-8 there).
* ``B > B_hi`` (10^4.1): ``q̃`` is read from the ``B_hi`` slice at the same ``x`` (computed with
  the true B), so R(0) stays exact, the s → 1 edge narrows with 1/B and ``R → 1`` as ``B → ∞``
  for s < 1 (for c → 1 that limit is reached only like 1/log B). This is a limit rule, not an
  accurate extrapolation: measured median relative error 1e-4 - 3e-4 for B ∈ [1e4, 1e6], but up
  to 5-9 % within a few 1/B of s = 1. (b > 1e4 λ ≈ 5 mm is far outside physical use.)
* ``c`` outside ``[c_lo, c_hi]`` (≈ [1.008, 12.3]): ``q̃`` is clamped in c; ``R(0; B, c)`` and the
  prefactor ``(c−1)`` stay exact, so ``R → 0`` and ``(c−1)B²/R`` stays finite as c → 1.
* ``s`` is clamped to [0, 1] (both paths): the model only uses ``s = sin θ_d``.

Hot paths: :func:`renormalisation_slice` fixes (B, c) once per channel and returns a 1-D lookup
in s (:class:`RenormalisationSlice`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from twoscale import tables
from twoscale._numerics import asinh_nonneg, float_dtype, gauss_legendre
from twoscale.tables import Spline, _weights, load_table

__all__ = [
    "k_correlation",
    "renormalisation",
    "diffraction_ratio",
    "renormalisation_slice",
    "RenormalisationSlice",
    "scaled_channels",
    "TABLE_NAME",
]

TABLE_NAME = "renormalisation"

# Gauss-Legendre nodes of the exact path (in v, ψ = ψ_c sinh v). 32 already give ≤ 3e-12
# relative error; 48 leave margin for derivatives (measured in tablegen/check_renorm.py).
N_NODES = 48

# Series thresholds of ℓ(x) = log1p(x)/x and φ(z) = expm1(z)/z: below them the 4-term Taylor
# series is exact to ~1e-14 relative; above, log1p and expm1 are accurate to rounding anyway.
_SERIES = 1e-3


def _log1p_ratio(x):
    """``ℓ(x) = log(1+x)/x`` for ``x ≥ 0`` (1 at 0), finite value and gradient at 0."""
    small = x < _SERIES
    xs = jnp.where(small, 1.0, x)  # double where: the unused branch never sees 0/0
    series = 1.0 - x * (1.0 / 2.0 - x * (1.0 / 3.0 - x / 4.0))
    return jnp.where(small, series, jnp.log1p(xs) / xs)


def _expm1_ratio(z):
    """``φ(z) = (eᶻ − 1)/z`` (1 at 0), finite value and gradient at 0."""
    small = jnp.abs(z) < _SERIES
    zs = jnp.where(small, 1.0, z)
    series = 1.0 + z * (1.0 / 2.0 + z * (1.0 / 6.0 + z / 24.0))
    return jnp.where(small, series, jnp.expm1(zs) / zs)


# dtype rule: float_dtype(..., default=float). float32 arrays stay float32 (Python scalars are
# weak); unlike the model's float32 default, all-scalar or integer inputs give JAX's default float
# (float64 under ``jax_enable_x64``), as the kernels document.


def _clamp_s(s):
    """``s`` clamped to [0, 1] with strict comparisons, so the gradient at 0 and 1 is not halved."""
    s = jnp.where(s < 0.0, 0.0, s)
    return jnp.where(s > 1.0, 1.0, s)


def _scaled_normal(B, c):
    """``ρ(0; B, c) = R(0; B, c)/(aB²) = ℓ(B²) · φ(−a log(1+B²))`` (closed form, a = (c−1)/2)."""
    x = B * B
    return _log1p_ratio(x) * _expm1_ratio(-0.5 * (c - 1.0) * jnp.log1p(x))


def k_correlation(f, sigma_s, b, c):
    """Evaluate the K-correlation (ABC) power spectral density [HP17 Eq. 16].

    ``S_HS(f) = (c−1)/(2π) · σ_s² b² · (1 + b² f²)^{−(c+1)/2}``; ``∫_{R²} S_HS d²f = σ_s²``.

    Args:
        f: spatial frequency magnitude ``|f|`` in 1/µm (f = |i_xy + o_xy|/λ, Eq. 9).
        sigma_s: RMS height of the nano-scale roughness σ_s in µm.
        b: correlation length scale b in µm.
        c: fall-off exponent, c > 1.
    Returns:
        ``S_HS`` in µm⁴ (µm² height² per 1/µm² of frequency), input dtype.
    """
    dtype = float_dtype(f, sigma_s, b, c, default=float)
    f, sigma_s, b, c = (jnp.asarray(v, dtype) for v in (f, sigma_s, b, c))
    bf = b * f
    return (
        (c - 1.0)
        / (2.0 * jnp.pi)
        * (sigma_s * b) ** 2
        * jnp.exp(-0.5 * (c + 1.0) * jnp.log1p(bf * bf))
    )


# --- exact path -------------------------------------------------------------------------------


def _scaled_exact(s, B, c, n_nodes: int = N_NODES):
    """``ρ(s; B, c) = R/(aB²)`` by Gauss-Legendre quadrature of the ψ form (module docstring).

    ``s`` must already lie in [0, 1] (or slightly beyond, for the table's analytic continuation).
    """
    dtype = jnp.result_type(s, B, c)
    s, B, c = jnp.broadcast_arrays(s, B, c)
    a = 0.5 * (c - 1.0)
    d = 1.0 - s
    # Scale of the sinh map: ψ_c = acosh(1 + X), X = ((1−s)² + B⁻²)/(2s) = (1 + B²d²)/(2sB²),
    # capped at π (beyond, the map is nearly linear and the singularities are far). The nodes
    # are constants for autodiff: the quadrature then differentiates the integrand, which
    # converges as fast, and s = 0 or B = 0 (X = ∞) cannot leak a NaN into a gradient.
    sg, Bg = jax.lax.stop_gradient(jnp.abs(s)), jax.lax.stop_gradient(B)
    num = 1.0 + (Bg * d) ** 2
    den = 2.0 * sg * Bg * Bg
    x_cap = float(np.cosh(np.pi) - 1.0)
    far = den * x_cap <= num  # X ≥ cosh(π) − 1, including s = 0 and B = 0
    X = jnp.where(far, x_cap, num / jnp.where(far, 1.0, den))
    psi_c = jax.lax.stop_gradient(jnp.log1p(X + jnp.sqrt(X * (X + 2.0))))  # acosh(1 + X)
    length = jnp.arcsinh(jnp.pi / psi_c)

    t, w = gauss_legendre(n_nodes, 0.0, 1.0)
    t, w = jnp.asarray(t, dtype), jnp.asarray(w, dtype)
    v = length[..., None] * t
    psi = psi_c[..., None] * jnp.sinh(v)
    dpsi = (psi_c * length)[..., None] * jnp.cosh(v) * w
    sin_half = jnp.sin(0.5 * psi)
    sh2 = sin_half * sin_half
    s_, d_, B_, a_ = s[..., None], d[..., None], B[..., None], a[..., None]
    r2 = d_ * d_ + 4.0 * s_ * sh2  # 1 + s² − 2s cos ψ without cancellation at s → 1, ψ → 0
    one_minus_scos = d_ + 2.0 * s_ * sh2  # 1 − s cos ψ
    x = B_ * B_ * r2
    integrand = one_minus_scos * _log1p_ratio(x) * _expm1_ratio(-a_ * jnp.log1p(x))
    return jnp.sum(integrand * dpsi, axis=-1) / jnp.pi


# --- table path -------------------------------------------------------------------------------


def _axis_bounds():
    """(log10 B_lo, log10 B_hi, log10(c_lo − 1), log10(c_hi − 1)) of the table."""
    ax = load_table(TABLE_NAME).axes
    return ax[0].lo, ax[0].hi, ax[1].lo, ax[1].hi


def _table_coords(B, c):
    """Table coordinates of (B, c), clamped with double where (no NaN for B ≤ 0 or c ≤ 1).

    Returns ``(log10 B_t, log10(c_t − 1), B_x, qscale)``: the clamped coordinates for the lookup,
    the B used in the s coordinate (the true B above the table, B_lo below it) and the factor
    ``B²/(1+B²)`` (true B) that turns q̃ into q.
    """
    lb_lo, lb_hi, lc_lo, lc_hi = _axis_bounds()
    b_lo, b_hi = 10.0**lb_lo, 10.0**lb_hi
    c_lo, c_hi = 1.0 + 10.0**lc_lo, 1.0 + 10.0**lc_hi
    B_x = jnp.where(B < b_lo, b_lo, B)  # small-B asymptote: the s coordinate of the edge slice
    B_t = jnp.where(B_x > b_hi, b_hi, B_x)
    c_t = jnp.where(c < c_lo, c_lo, jnp.where(c > c_hi, c_hi, c))
    qscale = B * B / (1.0 + B * B)
    return jnp.log10(B_t), jnp.log10(c_t - 1.0), B_x, qscale


def _s_coord(s, B_x):
    """``x = asinh(B(1−s))/asinh(B)``: 0 at s = 1, 1 at s = 0, resolves the 1/B-wide s → 1 edge.

    Both arguments are ≥ 0 (``s ≤ 1``, ``B_x > 0``): :func:`asinh_nonneg`, one ``log1p`` each."""
    return asinh_nonneg(B_x * (1.0 - s)) / asinh_nonneg(B_x)


def _lookup(spline: Spline, *coords):
    """Evaluate a tensor-product cubic B-spline with **one** gather of the 4^d coefficient block
    per point, then contract it with the per-axis weights.

    Same values as ``Spline.__call__`` (which gathers the 4^d coefficients one by one). Measured
    for the 3-D table on CPU: jit compile 0.5 s (forward) / 0.8 s (gradient) here against 4.5 s /
    19 s with 64 separate gathers; the run time is ~1 µs per point either way (0.1 s vs 0.02 s
    per 1e5 points) — hot paths use :func:`renormalisation_slice` instead.
    """
    c = spline.coeffs
    xs = jnp.broadcast_arrays(*[jnp.asarray(x, c.dtype) for x in coords])
    shape = xs[0].shape
    iw = [
        _weights(x.reshape(-1), lo, st, n)
        for x, lo, st, n in zip(xs, spline.lo, spline.step, spline.n, strict=True)
    ]
    d = len(iw)
    dims = jax.lax.GatherDimensionNumbers(
        offset_dims=tuple(range(1, d + 1)), collapsed_slice_dims=(), start_index_map=tuple(range(d))
    )
    # In bounds by construction: _weights clips the first index to [0, n−2] and coeffs has n+2.
    block = jax.lax.gather(
        c,
        jnp.stack([i for i, _ in iw], axis=-1),
        dims,
        slice_sizes=(4,) * d,
        mode=jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS,
    )
    for k in range(d - 1, -1, -1):  # contract the last axis with its weights, k+1 axes left
        w = iw[k][1].reshape((-1,) + (1,) * k + (4,))
        block = jnp.sum(block * w, axis=-1)
    return block.reshape(shape)


def _scaled_tables(s, B, c):
    """``ρ(s; B, c)`` from the table: ``ρ(0) · exp(q̃ · B²/(1+B²))``."""
    dtype = jnp.result_type(s, B, c)
    lb, lc, B_x, qscale = _table_coords(B, c)
    q_tilde = _lookup(tables.spline(TABLE_NAME, dtype), lb, lc, _s_coord(s, B_x))
    return _scaled_normal(B, c) * jnp.exp(q_tilde * qscale)


class RenormalisationSlice(eqx.Module):
    """The renormalisation table restricted to one (B, c): a 1-D lookup in ``s = sin θ``.

    Build it with :func:`renormalisation_slice` once per channel (the 3-D → 1-D contraction
    costs one 4×4 coefficient block); each lookup then touches 4 coefficients.
    Same accuracy and out-of-table rules as ``renormalisation(..., path="tables")``.
    """

    spline: Spline  # 1-D cubic B-spline of q̃ in x = asinh(B_x(1−s))/asinh(B_x)
    B: jax.Array
    c: jax.Array
    B_x: jax.Array
    qscale: jax.Array  # B²/(1+B²)
    scaled_normal: jax.Array  # ρ(0; B, c)

    def scaled(self, sin_theta):
        """``ρ(s) = R/((c−1)B²/2)``."""
        s = _clamp_s(jnp.asarray(sin_theta, self.spline.coeffs.dtype))
        q_tilde = self.spline(_s_coord(s, self.B_x))
        return self.scaled_normal * jnp.exp(q_tilde * self.qscale)

    def renormalisation(self, sin_theta):
        """``R(s; B, c) = σ_rel²/σ_s²``."""
        return 0.5 * (self.c - 1.0) * self.B * self.B * self.scaled(sin_theta)

    def diffraction_ratio(self, sin_theta):
        """``(c−1)B²/R(s; B, c) = 2/ρ(s)``."""
        return 2.0 / self.scaled(sin_theta)

    __call__ = renormalisation


def renormalisation_slice(B, c, *, dtype=None) -> RenormalisationSlice:
    """Fix the table at one (B, c) (scalars) and return the 1-D lookup in s.

    Args:
        B: b/λ, a scalar (use ``jax.vmap`` over channels).
        c: PSD exponent c > 1, a scalar.
        dtype: float32 or float64; default: the dtype of (B, c).
    Returns:
        A :class:`RenormalisationSlice`; call it (or ``.renormalisation``) on ``sin θ`` for R, or
        ``.diffraction_ratio`` for ``(c−1)B²/R``.
    """
    dtype = jnp.dtype(dtype or float_dtype(B, c, default=float))
    B, c = jnp.asarray(B, dtype), jnp.asarray(c, dtype)
    if B.ndim or c.ndim:
        raise ValueError("renormalisation_slice takes scalar B and c (vmap over channels)")
    lb, lc, B_x, qscale = _table_coords(B, c)
    spline = tables.spline(TABLE_NAME, dtype).slice(lb, lc)
    return RenormalisationSlice(spline, B, c, B_x, qscale, _scaled_normal(B, c))


def scaled_channels(sin_theta, B, c):
    """``ρ(s; B_j, c)`` of every channel at once: ``(..., C)`` for ``s`` ``(...)``, ``B`` ``(C,)``.

    The table is sliced once per channel (:func:`renormalisation_slice`, vmapped over ``B``);
    each sample then does one 1-D cubic lookup per channel, as flat scalar gathers from the
    stacked slices (elementwise code that fuses; a vmap of the slices' lookups gathers per
    channel with batch dimensions instead). The same terms in the same order as
    :meth:`RenormalisationSlice.scaled`.
    """
    slices = jax.vmap(lambda bb: renormalisation_slice(bb, c))(B)
    sp = slices.spline
    coeffs = sp.coeffs  # (C, m)
    n_ch, m = coeffs.shape
    s = _clamp_s(jnp.asarray(sin_theta, coeffs.dtype))[..., None]
    i, w = _weights(_s_coord(s, slices.B_x), sp.lo[0], sp.step[0], sp.n[0])
    idx = i + jnp.arange(n_ch, dtype=jnp.int32) * m
    flat = coeffs.reshape(-1)
    q_tilde = jnp.zeros(idx.shape, coeffs.dtype)
    for k in range(4):
        q_tilde = q_tilde + w[..., k] * flat.at[idx + k].get(mode="promise_in_bounds")
    return slices.scaled_normal * jnp.exp(q_tilde * slices.qscale)


# --- public API -------------------------------------------------------------------------------


def _scaled(sin_theta, B, c, path: str):
    dtype = float_dtype(sin_theta, B, c, default=float)
    s, B, c = (jnp.asarray(v, dtype) for v in (sin_theta, B, c))
    s = _clamp_s(s)
    if path == "exact":
        return _scaled_exact(s, B, c), B, c
    if path == "tables":
        return _scaled_tables(s, B, c), B, c
    raise ValueError(f"path must be 'tables' or 'exact', got {path!r}")


def renormalisation(sin_theta, B, c, *, path: str = "tables"):
    """Renormalisation ratio ``R(s; B, c) = σ_rel²/σ_s²`` [HP17 Eq. 19; docs/model.md §3.5].

    ``R = ∫_{‖o_xy‖≤1} S_HS((o_xy + i_xy)/λ) d²o_xy / (λ² σ_s²)``: the fraction of the nano-scale
    roughness variance on propagating directions. ``R(0) = 1 − (1+B²)^{−(c−1)/2}``, R → 1 as
    B → ∞, ``R ≈ (c−1)B²/2`` as B → 0.

    Args:
        sin_theta: ``s = sin θ`` of the incident direction (the model uses θ_d), in [0, 1]
            (clamped).
        B: ``b/λ`` ≥ 0 (dimensionless). Tables cover [10^−2.1, 10^4.1], asymptotes beyond.
        c: PSD exponent c > 1. Tables cover [1.008, 12.3], clamped beyond (module docstring).
        path: ``"tables"`` (C² spline, ≤ 1e-4 relative) or ``"exact"`` (48-node quadrature,
            ~1e-14 relative in float64). Both are differentiable in all arguments.
    Returns:
        R, broadcast shape of the inputs, their floating dtype.
    """
    rho, B, c = _scaled(sin_theta, B, c, path)
    return 0.5 * (c - 1.0) * B * B * rho


def diffraction_ratio(sin_theta, B, c, *, path: str = "tables"):
    """The stable ratio ``(c−1) B² / R(s; B, c)`` of the diffraction lobe (docs/model.md §2, §6 traps 4-5).

    Both ``(c−1)B²`` and R tend to 0 as c → 1 or B → 0; the ratio is ``2/ρ`` with
    ``ρ = R/((c−1)B²/2)`` evaluated directly (module docstring), so it is finite, with finite
    gradients, for all ``B ≥ 0`` and ``c ≥ 1``. Limits: 2 as B → 0 (for all s and c; next term
    ``2[1 + (c+1)(1+2s²)B²/4]``), and ``(c−1)B²`` as B → ∞ with s < 1 (R → 1).

    Args and path: as :func:`renormalisation`.
    Returns:
        ``(c−1)B²/R`` (dimensionless), broadcast shape of the inputs, their floating dtype.
    """
    rho, _, _ = _scaled(sin_theta, B, c, path)
    return 2.0 / rho

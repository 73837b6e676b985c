"""The default two-scale model (conductor, specular + diffraction, ``Q = 2F``, correlated
shadowing, RGB, ``path="tables"``) written in NumPy, for the SciPy comparison.

Independent of JAX: it reads the library's table *files* (their grid values and axes, through
:func:`twoscale.tables.load_table`) and evaluates the same C² cubic B-splines in NumPy: the
coefficients are solved by :func:`twoscale.tables.bspline_coefficients` (pure NumPy), then sliced
at the parameters and looked up per sample exactly as the library's hot path does (slice the
parameter axes once, 1-D lookups per sample). The formulas are those of ``docs/model.md`` §2-3 as
composed in ``twoscale/model.py``, with the same guards; constants of the table coordinates come
from the library modules (they are data, not code). Agreement with ``twoscale.brdf`` is tested in
``tests/test_benchmarks.py`` (≤ 1e-6 relative; measured ≈ 1e-13).

Exception: the convolution lobe is ported for the compact Chebyshev table (version 1) only; with
another table format it is evaluated by the library (see :func:`_lobe`).

Not covered (not needed by the comparison): dielectrics, spectral configurations, the exact path.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy.special import gammaln

from twoscale import shadowing
from twoscale.spectral import RGB_WAVELENGTHS
from twoscale.tables import bspline_coefficients, load_table

__all__ = ["brdf", "PARAM_NAMES", "pack", "unpack"]

#: Order of the 11 parameters in the flat vector of :func:`pack` / :func:`unpack`.
PARAM_NAMES = ("beta", "p", "sigma_s", "b", "c", "eta", "k")

_EPS = np.finfo(np.float64).eps
_TINY = np.finfo(np.float64).tiny


# ------------------------------------------------------------------------------ splines in NumPy
@functools.cache
def _coeffs(name: str):
    table = load_table(name)
    axes = table.axes
    return (
        bspline_coefficients(table.values, len(axes)),
        tuple(a.lo for a in axes),
        tuple(a.step for a in axes),
        tuple(a.n for a in axes),
    )


def _weights(x, lo, step, n):
    """First index and the 4 cubic B-spline weights (as ``twoscale.tables._weights``)."""
    u = (np.clip(x, lo, lo + step * (n - 1)) - lo) / step
    i = np.clip(np.floor(u), 0, n - 2)
    t = u - i
    t2, t3 = t * t, t * t * t
    w = np.stack(
        [
            (1.0 - t) ** 3 / 6.0,
            (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0,
            (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0,
            t3 / 6.0,
        ],
        axis=-1,
    )
    return i.astype(np.int64), w


def _slice(name: str, *coords):
    """Fix the leading axes of table ``name`` at scalar coordinates: ``(coeffs, lo, step, n)``."""
    c, lo, step, n = _coeffs(name)
    for k, x in enumerate(coords):
        i, w = _weights(float(x), lo[k], step[k], n[k])
        c = np.tensordot(w, c[int(i) : int(i) + 4], axes=(0, 0))
    m = len(coords)
    return c, lo[m:], step[m:], n[m:]


def _lookup_1d(sl, x):
    """Evaluate a 1-D sliced spline at ``x`` (any shape); trailing components appended."""
    c, (lo,), (step,), (n,) = sl
    i, w = _weights(x, lo, step, n)
    out = 0.0
    for k in range(4):
        wk = w[..., k].reshape(w.shape[:-1] + (1,) * (c.ndim - 1))
        out = out + wk * c[i + k]
    return out


# ------------------------------------------------------------------------------ components
def _frame(wi, wo):
    e2 = _EPS**2
    s = wi + wo
    d = wi - wo
    s_xy2 = s[..., 0] ** 2 + s[..., 1] ** 2
    s2 = s_xy2 + s[..., 2] ** 2
    s_len = np.sqrt(s2)
    ok_h = s2 > e2
    s_den = np.where(ok_h, s_len, 1.0)
    cos_h = np.where(ok_h, s[..., 2] / s_den, 1.0)
    d_len = np.sqrt(np.sum(d * d, axis=-1))
    den = np.sqrt(s2 + np.sum(d * d, axis=-1))
    cos_d, sin_d = s_len / den, d_len / den
    ix, iy, ox, oy = wi[..., 0], wi[..., 1], wo[..., 0], wo[..., 1]
    ok_phi = (ix * ix + iy * iy > e2) & (ox * ox + oy * oy > e2)
    cross = np.where(ok_phi, ix * oy - iy * ox, 0.0)
    dot = np.where(ok_phi, ix * ox + iy * oy, 1.0)
    phi = np.where(ok_phi, np.arctan2(np.abs(cross), dot), 0.0)
    return wi[..., 2], wo[..., 2], cos_h, cos_d, sin_d, phi


def _tan(c):
    return np.sqrt(np.maximum((1.0 - c) * (1.0 + c), 0.0)) / np.maximum(c, _EPS)


def _softplus(x, k):
    return np.logaddexp(0.0, k * x) / k


def _smith_lambda(a, p):
    """Λ(a; p) from the Smith table sliced at p [shadowing.py, table path]."""
    sh = shadowing
    p = float(np.clip(p, sh.P_MIN, sh.P_MAX))
    log_es = gammaln(1.5 / p) - gammaln(1.0 / p)

    def knee(eta):
        return _softplus(sh._XI_KNEE - eta, sh._XI_SHARPNESS)

    eta_lo = log_es - math.log(sh.V_MAX) / (2.0 * p)
    s = 1.0 + (eta_lo - sh.XI_LO) / knee(eta_lo)
    log_a_hi = sh.XI_HI - log_es
    a = np.clip(a, 0.0, float(np.finfo(np.float64).max) ** 0.25)
    log_a = np.log(np.maximum(a, _TINY))
    log_a_top = np.minimum(log_a, log_a_hi)
    eta = log_a_top + log_es
    xi = np.clip(eta - (s - 1.0) * knee(eta), sh.XI_LO, sh.XI_HI)
    t_val = _lookup_1d(_slice(sh.TABLE_NAME, math.log(p)), xi)
    v0 = np.exp(np.minimum(-2.0 * p * log_a_top, math.log(sh._V0_ZERO)))
    essential = v0 - np.log1p(v0 * (1.0 + 0.5 * v0))
    return np.exp(log_a + log_es - math.log(math.pi) + t_val - essential)


def _van_ginneken(phi):
    return 4.41 * phi / (4.41 * phi + 1.0)


def _ndf(cos_h, beta, p):
    c = np.clip(cos_h, 0.0, 1.0)
    above = c > math.sqrt(_TINY)
    cs = np.where(above, c, 1.0)
    log_c = np.log(cs)
    sin2 = (1.0 - cs) * (1.0 + cs)
    log_x = np.log(np.maximum(sin2, _TINY)) - 2.0 * log_c - 2.0 * math.log(beta)
    log_d0 = math.log(p) - math.log(math.pi) - 2.0 * math.log(beta) - gammaln(1.0 / p)
    expo = np.exp(np.minimum(p * log_x, math.log(1e4)))
    return np.where(above, np.exp(log_d0 - expo - 4.0 * log_c), 0.0)


def _conductor_fresnel(cos, eta, k):
    cos = np.clip(cos, 0.0, 1.0)
    cos2, sin2 = cos * cos, (1.0 - cos) * (1.0 + cos)
    eta2, k2 = eta * eta, k * k
    c1 = eta2 - k2 - sin2
    ek2 = eta2 * k2
    c0 = np.sqrt(c1 * c1 + 4.0 * ek2)
    big = 0.5 * (c0 + np.abs(c1))
    small = ek2 / big
    a2 = np.where(c1 >= 0.0, big, small)
    b2 = np.where(c1 >= 0.0, small, big)
    a = np.sqrt(a2)
    s = a2 + b2
    rs = (s - 2.0 * a * cos + cos2) / (s + 2.0 * a * cos + cos2)
    sin4 = sin2 * sin2
    num = s * cos2 - 2.0 * a * sin2 * cos + sin4
    den = s * cos2 + 2.0 * a * sin2 * cos + sin4
    rp = rs * num / den
    return np.clip(0.5 * (rs + rp), 0.0, 1.0)


def _scaled_normal(big_b, c):
    """ρ(0; B, c) = ℓ(B²) φ(−a log(1+B²)) (scalars; series near 0 as in psd.py)."""
    x = big_b * big_b
    ell = 1.0 - x * (0.5 - x * (1.0 / 3.0 - x / 4.0)) if x < 1e-3 else math.log1p(x) / x
    z = -0.5 * (c - 1.0) * math.log1p(x)
    phi = 1.0 + z * (0.5 + z * (1.0 / 6.0 + z / 24.0)) if abs(z) < 1e-3 else math.expm1(z) / z
    return ell * phi


def _renorm_scaled(sin_d, big_b, c):
    """ρ(s; B, c) = R/((c−1)B²/2) from the renormalisation table sliced at (B, c) [psd.py]."""
    ax = load_table("renormalisation").axes
    b_lo, b_hi = 10.0 ** ax[0].lo, 10.0 ** ax[0].hi
    c_lo, c_hi = 1.0 + 10.0 ** ax[1].lo, 1.0 + 10.0 ** ax[1].hi
    b_x = b_lo if big_b < b_lo else big_b
    b_t = min(b_x, b_hi)
    c_t = min(max(c, c_lo), c_hi)
    qscale = big_b * big_b / (1.0 + big_b * big_b)
    sl = _slice("renormalisation", math.log10(b_t), math.log10(c_t - 1.0))
    s = np.clip(sin_d, 0.0, 1.0)
    q = _lookup_1d(sl, np.arcsinh(b_x * (1.0 - s)) / math.asinh(b_x))
    return _scaled_normal(big_b, c) * np.exp(q * qscale)


def _chebyshev(t, coeffs):
    x = 2.0 * t - 1.0
    t_prev, t_cur = np.ones_like(x), x
    d_prev, d_cur = np.zeros_like(x), np.ones_like(x)
    val = coeffs[..., 0] + coeffs[..., 1] * x
    der = coeffs[..., 1] + 0.0 * x
    for j in range(2, coeffs.shape[-1]):
        t_next = 2.0 * x * t_cur - t_prev
        d_next = 2.0 * t_cur + 2.0 * x * d_cur - d_prev
        val = val + coeffs[..., j] * t_next
        der = der + coeffs[..., j] * d_next
        t_prev, t_cur, d_prev, d_cur = t_cur, t_next, d_cur, d_next
    return val, 2.0 * der


def _compact_table() -> bool:
    """Is the packaged convolution table the compact Chebyshev form (version 1) ported here?"""
    t = load_table("convolution")
    return t.meta.get("version") == 1 and t.values.ndim == 5 and t.values.shape[-1] == 12


def _lobe(cos_h, beta, p, c, u):
    """(S*D)(θ_h) from the convolution table sliced at (β, p, c) [convolution.py].

    The compact Chebyshev table (version 1) is evaluated in NumPy. Any other table format (the
    library is moving to a 5-D table of lobe values) is not ported: the lobe term is then taken
    from the library's table path (JAX, sliced once at (β, p, c)), so the model stays in agreement.
    """
    if not _compact_table():
        import jax.numpy as jnp

        from twoscale import convolution

        sl = convolution.lobe_spline(beta, p, c, jnp.float64)
        out = convolution.lobe_from_components(sl, jnp.asarray(cos_h), jnp.asarray(u))
        return np.asarray(out, dtype=np.float64)
    sl = _slice("convolution", math.log(beta), math.log(p), math.log(c - 1.0))
    comps = _lookup_1d(sl, np.arcsinh(u))
    ct = np.clip(cos_h, 0.0, 1.0)
    c2, s2 = ct * ct, (1.0 - ct) * (1.0 + ct)
    log_k, log_xi_end, coeffs = comps[..., 0], comps[..., 1], comps[..., 2:]
    w2 = 1.0 / (1.0 + 4.0 * u * u) + beta * beta
    t = 0.5 * np.log1p(s2 / w2) * np.exp(-log_xi_end)
    val_in, _ = _chebyshev(np.minimum(t, 1.0), coeffs)
    val_1, der_1 = _chebyshev(np.ones_like(t), coeffs)
    poly = np.where(t <= 1.0, val_in, val_1 + np.minimum(der_1, 0.0) * (t - 1.0))
    return np.exp(np.log(c2 + np.exp(log_k) * s2) + poly)


# ------------------------------------------------------------------------------ the model
def brdf(params: dict, wi, wo, wavelengths=RGB_WAVELENGTHS):
    """ρ(i, o) of the default two-scale conductor, ``(N, 3)`` (1/sr, without cos θ_o).

    Args:
        params: ``{beta, p, sigma_s, b, c, eta (3,), k (3,)}`` in physical units (floats).
        wi, wo: ``(N, 3)`` unit directions (float64).
    """
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    beta, p = float(params["beta"]), float(params["p"])
    sigma_s, b, c = float(params["sigma_s"]), float(params["b"]), float(params["c"])
    eta = np.asarray(params["eta"], dtype=np.float64)
    k = np.asarray(params["k"], dtype=np.float64)
    wl = np.asarray(wavelengths, dtype=np.float64)

    ci, co, ch, cd, sd, phi = _frame(wi, wo)
    above = (ci > 0.0) & (co > 0.0)
    ci, co = np.where(above, ci, 1.0), np.where(above, co, 1.0)
    ch, cd = np.where(above, ch, 1.0), np.where(above, cd, 1.0)
    sd, phi = np.where(above, sd, 0.0), np.where(above, phi, 0.0)

    lam_i = _smith_lambda(beta * _tan(ci), p)
    lam_o = _smith_lambda(beta * _tan(co), p)
    g = 1.0 / (1.0 + np.maximum(lam_i, lam_o) + _van_ginneken(phi) * np.minimum(lam_i, lam_o))
    cdc = cd[:, None]
    f = _conductor_fresnel(cdc, eta, k)  # (N, 3)

    out = np.empty((wi.shape[0], wl.size))
    d = _ndf(ch, beta, p)
    spec = d * g / np.maximum(4.0 * ci * co, _TINY)
    for j, lam in enumerate(wl):
        big_b = b / lam
        rho = _renorm_scaled(sd, big_b, c)
        r, ratio = 0.5 * (c - 1.0) * big_b * big_b * rho, 2.0 / rho
        x = (4.0 * math.pi * sigma_s / lam * cd) ** 2 * r
        lobe = _lobe(ch, beta, p, c, big_b * cd)
        diffraction = g * (-np.expm1(-x)) * 2.0 * f[:, j] * lobe * ratio / (2.0 * math.pi)
        out[:, j] = np.exp(-x) * f[:, j] * spec + diffraction
    return np.where(above[:, None], out, 0.0)


# ------------------------------------------------------------------------------ flat vectors
def pack(params: dict) -> np.ndarray:
    """Physical parameters → flat 11-vector (order :data:`PARAM_NAMES`, η and k per channel)."""
    return np.concatenate([np.ravel(np.asarray(params[n], dtype=np.float64)) for n in PARAM_NAMES])


def unpack(x) -> dict:
    x = np.asarray(x, dtype=np.float64)
    return {
        "beta": x[0],
        "p": x[1],
        "sigma_s": x[2],
        "b": x[3],
        "c": x[4],
        "eta": x[5:8],
        "k": x[8:11],
    }

"""K-correlation PSD and renormalisation R(s; B, c): values, limits, independent quadratures,
table accuracy, gradients, dtype and transformation invariants [HP17 Eq. 16, 19; docs/model.md §3.4-3.5]."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads
from scipy import integrate

from tablegen.check_renorm import accuracy_rows, edge_points, random_points, reference_quad
from twoscale import psd
from twoscale.psd import (
    diffraction_ratio,
    k_correlation,
    renormalisation,
    renormalisation_slice,
)
from twoscale.tables import load_table

#: Compiled with most XLA optimisations off (tests/conftest.py): this module's time is compilation
#: (measured alone on the 2-core machine, 2026-12-06: 14.6 → 10.3 s).
COMPILE_QUICKLY = True

PATHS = ("exact", "tables")

# docs/model.md §3.5 check values (s, B, c) → R, given to 6 decimals.
CHECK_VALUES = [
    ((0.0, 1.0, 2.0), 0.292893),
    ((0.5, 1.0, 2.0), 0.260553),
    ((0.9, 1.0, 2.0), 0.196871),
    ((0.5, 10.0, 1.5), 0.655315),
    ((0.9, 10.0, 1.5), 0.488067),
    ((0.99, 100.0, 2.5), 0.807208),
    ((0.5, 0.1, 2.0), 0.004945),
]


# Jitted once per path: eager JAX compiles every primitive per new shape, which dominates the
# run time of a test file like this one. jit = eager is tested separately.
R = {p: jax.jit(lambda s, B, c, p=p: renormalisation(s, B, c, path=p)) for p in PATHS}
D = {p: jax.jit(lambda s, B, c, p=p: diffraction_ratio(s, B, c, path=p)) for p in PATHS}
R_EXACT, R_TABLES = R["exact"], R["tables"]


def _exact(p):
    return float(R_EXACT(*p))


def _r0(B, c):
    return -np.expm1(-0.5 * (c - 1.0) * np.log1p(B * B))


# --- PSD --------------------------------------------------------------------------------------


@pytest.mark.parametrize("sigma_s,b,c", [(0.02, 0.5, 1.5), (0.1, 2.0, 2.0), (1.0, 0.1, 4.0)])
def test_k_correlation_integrates_to_sigma_squared(sigma_s, b, c):
    """∫_{R²} S_HS d²f = 2π ∫_0^∞ f S_HS(f) df = σ_s² (scipy quad in polar coordinates)."""

    def radial(f):
        return 2.0 * math.pi * f * float(k_correlation(f, sigma_s, b, c))

    head, _ = integrate.quad(radial, 0.0, 1.0 / b, epsabs=0.0, epsrel=1e-12)
    tail, _ = integrate.quad(radial, 1.0 / b, np.inf, epsabs=0.0, epsrel=1e-12, limit=500)
    assert head + tail == pytest.approx(sigma_s**2, rel=1e-8)


def test_k_correlation_formula_and_dtype():
    f, s, b, c = 3.0, 0.05, 0.4, 2.5
    want = (c - 1) / (2 * math.pi) * s**2 * b**2 * (1 + (b * f) ** 2) ** (-(c + 1) / 2)
    assert float(k_correlation(f, s, b, c)) == pytest.approx(want, rel=1e-13)
    out = k_correlation(jnp.float32(f), s, b, c)
    assert out.dtype == jnp.float32


# --- values -----------------------------------------------------------------------------------


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("point,want", CHECK_VALUES)
def test_check_values(path, point, want):
    got = float(R[path](*point))
    tol = 5e-7 + (1e-4 * want if path == "tables" else 0.0)  # 6-decimal rounding (+ table error)
    assert abs(got - want) <= tol


@pytest.mark.parametrize("path", PATHS)
def test_normal_incidence_closed_form(path):
    """R(0; B, c) = 1 − (1+B²)^{−(c−1)/2} on and off the table (B below, inside, above)."""
    B, c = np.meshgrid(10.0 ** np.linspace(-3, 5, 17), [1.01, 1.3, 2.0, 5.0, 10.0])
    got = np.asarray(R[path](0.0, B, c))
    np.testing.assert_allclose(got, _r0(B, c), rtol=1e-12)


def test_exact_path_matches_scipy_quadrature():
    """Exact path vs scipy quad of docs/model.md §3.5 as written: ≤ 1e-8 relative (measured ~1e-12)."""
    pts = np.concatenate([random_points(40, 7), edge_points()[::4]])
    ref = np.array([reference_quad(*p) for p in pts])
    got = np.asarray(R_EXACT(pts[:, 0], pts[:, 1], pts[:, 2]))
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=0)


@pytest.mark.parametrize(
    "s,B,c", [(0.5, 1.0, 2.0), (0.9, 3.0, 1.5), (0.3, 0.5, 4.0)], ids=["p1", "p2", "p3"]
)
def test_independent_disk_quadrature(s, B, c):
    """σ_rel²/σ_s² straight from the definition: ∫ S_HS((o_xy + i_xy)/λ) d²o_xy/(λ² σ_s²) over the
    unit disk of o_xy, in polar coordinates about the disk centre (no use of the radial form)."""
    lam, sigma_s = 0.526, 0.03
    b = B * lam

    def s_hs(f):  # [HP17 Eq. 16] in plain floats (dblquad calls it ~1e5 times)
        return (c - 1) / (2 * math.pi) * (sigma_s * b) ** 2 * (1 + (b * f) ** 2) ** (-(c + 1) / 2)

    assert float(k_correlation(2.0, sigma_s, b, c)) == pytest.approx(s_hs(2.0), rel=1e-13)

    def integrand(phi, rho):
        fx = (rho * math.cos(phi) + s) / lam
        fy = rho * math.sin(phi) / lam
        return rho * s_hs(math.hypot(fx, fy)) / lam**2

    val, _ = integrate.dblquad(integrand, 0.0, 1.0, 0.0, 2.0 * math.pi, epsabs=0, epsrel=1e-10)
    assert val / sigma_s**2 == pytest.approx(_exact((s, B, c)), rel=1e-8)


# --- limits -----------------------------------------------------------------------------------


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("s", [0.0, 0.4, 1.0])
@pytest.mark.parametrize("c", [1.01, 2.0, 10.0])
def test_small_B_limit(path, s, c):
    """R = (c−1)B²/2 · [1 − (c+1)(1+2s²)B²/4 + O(B⁴)] (derived series), down to B = 0."""
    for B in (1e-6, 1e-4, 1e-3, 1e-2):
        series = 0.5 * (c - 1) * B**2 * (1 - (c + 1) * (1 + 2 * s * s) * B**2 / 4)
        got = float(R[path](s, B, c))
        rtol = 5 * (c + 1) ** 2 * B**4 + (1e-12 if path == "exact" else 1e-7)
        assert got == pytest.approx(series, rel=rtol)
    assert float(R[path](s, 0.0, c)) == 0.0
    assert float(D[path](s, 0.0, c)) == pytest.approx(2.0, rel=1e-14)


@pytest.mark.parametrize("path", PATHS)
def test_large_B_limit(path):
    """R → 1 as B → ∞ for s < 1 (and → 1/2 at s = 1); R increases with B (docs/model.md §3.5)."""
    for s in (0.0, 0.5, 0.9):
        assert float(R[path](s, 1e8, 5.0)) == pytest.approx(1.0, abs=1e-9)
    assert float(R[path](1.0, 1e8, 5.0)) == pytest.approx(0.5, abs=1e-4)
    Bs = 10.0 ** np.arange(1, 11)
    for c in (1.01, 1.5, 3.0):
        for s in (0.0, 0.7, 0.999, 1.0):
            r = np.asarray(R[path](s, Bs, c))
            assert np.all(np.diff(r) > -1e-15) and np.all(r < 1.0 + 1e-14)  # up to rounding at 1


# --- table accuracy ---------------------------------------------------------------------------


def test_tables_vs_exact_random_points():
    """The spline reaches ≤ 1e-4 relative error in R (and in (c−1)B²/R) over the whole domain."""
    pts = np.concatenate([random_points(3000, 11), edge_points()])
    a = (pts[:, 0], pts[:, 1], pts[:, 2])
    ex, tb = np.asarray(R_EXACT(*a)), np.asarray(R_TABLES(*a))
    np.testing.assert_allclose(tb, ex, rtol=1e-4, atol=0)
    dex, dtb = np.asarray(D["exact"](*a)), np.asarray(D["tables"](*a))
    np.testing.assert_allclose(dtb, dex, rtol=1e-4, atol=0)


def test_accuracy_rows_report():
    rows = {r["check"]: r for r in accuracy_rows(n_random=500, n_scipy=10, n_outside=100)}
    assert rows["R exact vs scipy quad"]["max_rel_err"] < 1e-10
    assert rows["R tables vs exact (domain)"]["max_rel_err"] < 1e-4
    assert rows["(c-1)B²/R tables vs exact (domain)"]["max_rel_err"] < 1e-4


def test_table_file():
    t = load_table(psd.TABLE_NAME)
    assert t.meta["name"] == "renormalisation" and t.meta["version"] >= 1
    lb, lc, x = t.axes
    assert lb.lo < -2.0 and lb.hi > 4.0 and lc.lo < -2.0 and lc.hi > math.log10(9.0)
    assert x.lo < 0.0 and x.hi > 1.0
    from twoscale.tables import DATA_DIR

    assert (DATA_DIR / "renormalisation.npz").stat().st_size < 5e6


@jax.jit
def SLICE(s, B, c):
    sl = renormalisation_slice(B, c)
    return sl(s), sl.diffraction_ratio(s)


SLICE_VMAP = jax.jit(jax.vmap(lambda B, c: renormalisation_slice(B, c)(0.3)))


@pytest.mark.parametrize("B,c", [(0.7, 2.0), (3e3, 1.01), (1e-2, 9.5)])
def test_slice_equals_full_lookup(B, c):
    s = np.linspace(0.0, 1.0, 101)
    r, d = SLICE(s, B, c)
    np.testing.assert_allclose(np.asarray(r), np.asarray(R_TABLES(s, B, c)), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(d), np.asarray(D["tables"](s, B, c)), rtol=1e-12)
    Bs, cs = np.array([0.5, 1.0, 2.0]), np.array([1.5, 2.0, 3.0])
    many = SLICE_VMAP(Bs, cs)
    np.testing.assert_allclose(np.asarray(many), np.asarray(R_TABLES(0.3, Bs, cs)), rtol=1e-12)
    with pytest.raises(ValueError):
        renormalisation_slice(np.ones(2), 2.0)


# --- diffraction ratio ------------------------------------------------------------------------


D_GRAD = {
    path: jax.jit(
        jax.grad(lambda s, B, c, path=path: diffraction_ratio(s, B, c, path=path), (0, 1, 2))
    )
    for path in PATHS
}


@pytest.mark.parametrize("path", PATHS)
def test_diffraction_ratio_edges(path):
    """(c−1)B²/R finite, with finite gradients, and correct at c = 1.01, B = 1e-2 and beyond."""
    s = np.array([0.0, 0.5, 1.0 - 1e-6, 1.0])
    for B, c in [(1e-2, 1.01), (1e-2, 10.0), (1e-5, 1.01), (1e4, 1.01), (1.0, 1.0), (0.0, 1.0)]:
        got = np.asarray(D[path](s, B, c))
        assert np.all(np.isfinite(got))
        if c > 1.0 and B > 0.0:
            want = (c - 1) * B**2 / np.asarray(R_EXACT(s, B, c))
            np.testing.assert_allclose(got, want, rtol=1e-12 if path == "exact" else 1e-4)
        if B <= 1e-2:  # small-B limit 2[1 + (c+1)(1+2s²)B²/4]
            lim = 2.0 * (1.0 + (c + 1) * (1 + 2 * s * s) * B**2 / 4)
            np.testing.assert_allclose(got, lim, rtol=1e-6)
        for si in s:
            assert all(np.isfinite(float(v)) for v in D_GRAD[path](si, B, c))


# --- gradients --------------------------------------------------------------------------------


def _fd(f, p, i, h, side):
    """4th-order finite difference of f along argument i; one-sided (side = ±1) near s ∈ {0, 1}."""

    def e(k):
        q = list(p)
        q[i] = q[i] + k * h
        return f(*q)

    if side == 0:
        return (e(-2) - 8 * e(-1) + 8 * e(1) - e(2)) / (12 * h)
    d = -25 * e(0) + 48 * e(side) - 36 * e(2 * side) + 16 * e(3 * side) - 3 * e(4 * side)
    return side * d / (12 * h)


GRAD_POINTS = [
    (s, B, c) for s in (0.0, 0.45, 1.0 - 1e-6, 1.0) for B in (1e-2, 1.3, 1e3) for c in (1.01, 5.0)
]


def _log_r(path):
    """log R as a function of (s, log B, log(c−1)): the coordinates the optimiser sees."""

    def f(s, lb, lc1):
        return jnp.log(renormalisation(s, jnp.exp(lb), 1.0 + jnp.exp(lc1), path=path))

    return f


LOG_R = {path: jax.jit(_log_r(path)) for path in PATHS}
LOG_GRAD = {path: jax.jit(jax.grad(_log_r(path), (0, 1, 2))) for path in PATHS}


def _log_coords(p):
    s, B, c = p
    return (s, math.log(B), math.log(c - 1.0))


@pytest.mark.parametrize("p", GRAD_POINTS, ids=str)
def test_gradients_exact_vs_finite_differences(p):
    """Exact-path autodiff vs float64 finite differences of the exact path (itself checked vs
    scipy), at interior points and the extremes s = 0, s = 1 − 1e-6, s = 1, c = 1.01, B = 1e-2."""
    q = _log_coords(p)
    got = np.array([float(v) for v in LOG_GRAD["exact"](*q)])

    def f(*x):
        return float(LOG_R["exact"](*x))

    s, B = p[0], p[1]
    side = 1 if s < 0.1 else (-1 if s > 0.9 else 0)  # stencils stay inside s ∈ [0, 1]
    hs = 1e-3 if B < 10 else 0.2 / B**1.5  # resolve the 1/B-wide edge at s → 1
    want = np.array([_fd(f, q, 0, hs, side), _fd(f, q, 1, 1e-3, 0), _fd(f, q, 2, 1e-3, 0)])
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("p", GRAD_POINTS, ids=str)
def test_gradients_tables_vs_exact(p):
    """Table-path log-derivatives agree with the exact path (C² spline, no kinks at the edges)."""
    q = _log_coords(p)
    got = np.array([float(v) for v in LOG_GRAD["tables"](*q)])
    want = np.array([float(v) for v in LOG_GRAD["exact"](*q)])
    assert np.all(np.isfinite(got))
    # ∂ log R/∂s reaches ~B near s = 1: relative there, absolute elsewhere.
    tol = 5e-4 * np.array([max(1.0, abs(want[0])), 1.0, 1.0])  # measured ≤ 9e-5
    assert np.all(np.abs(got - want) <= tol), (got, want)


@pytest.mark.parametrize("path", PATHS)
def test_check_grads_interior(path):
    check_grads(R[path], (0.37, 1.7, 2.3), order=1, modes=("fwd", "rev"), eps=1e-4)


def test_table_derivative_continuous_across_grid_nodes():
    """The cubic B-spline is C²: derivatives match on both sides of a node of each axis."""
    t = load_table(psd.TABLE_NAME)
    ax_b, ax_c, ax_x = t.axes
    B, c = 10.0 ** ax_b.nodes()[30], 1.0 + 10.0 ** ax_c.nodes()[15]  # on nodes of both axes
    x_node = ax_x.nodes()[20]
    eps = 1e-7

    def s_of_x(x):
        return 1.0 - math.sinh(x * math.asinh(B)) / B

    ds = jax.jit(jax.grad(R_TABLES, 0))
    left, right = float(ds(s_of_x(x_node - eps), B, c)), float(ds(s_of_x(x_node + eps), B, c))
    assert abs(left - right) <= 1e-5 * abs(left)
    lb = math.log10(B)
    dB = jax.jit(jax.grad(lambda lb_: R_TABLES(0.6, 10.0**lb_, c)))
    left, right = float(dB(lb - eps)), float(dB(lb + eps))
    assert abs(left - right) <= 1e-5 * abs(left)
    # A multilinear table would jump here by O(1) relative; the spline's second derivative, too,
    # is continuous, so the jump is O(eps).


# --- transformations and dtypes ---------------------------------------------------------------


@pytest.mark.parametrize("path", PATHS)
def test_jit_equals_eager(path):
    pts = random_points(64, 3)
    a = (pts[:, 0], pts[:, 1], pts[:, 2])
    eager = np.asarray(renormalisation(*a, path=path))
    jitted = np.asarray(jax.jit(lambda *x: renormalisation(*x, path=path))(*a))
    np.testing.assert_allclose(jitted, eager, rtol=1e-13)
    d_eager = np.asarray(diffraction_ratio(*a, path=path))
    d_jit = np.asarray(jax.jit(lambda *x: diffraction_ratio(*x, path=path))(*a))
    np.testing.assert_allclose(d_jit, d_eager, rtol=1e-13)


@pytest.mark.parametrize("path", PATHS)
def test_float32_in_float32_out(path):
    pts = np.concatenate([random_points(200, 5), edge_points()]).astype(np.float32)
    a = tuple(jnp.asarray(pts[:, i]) for i in range(3))
    r, d = R[path](*a), D[path](*a)
    assert r.dtype == jnp.float32 and d.dtype == jnp.float32
    shape = jax.eval_shape(lambda: renormalisation(jnp.float32(0.5), 2.0, 3.0, path=path))
    assert shape.dtype == jnp.float32
    want = np.asarray(R_EXACT(*(p.astype(np.float64) for p in pts.T)))
    np.testing.assert_allclose(np.asarray(r, np.float64), want, rtol=1e-4 + 2e-5)
    grad = jax.jit(jax.grad(lambda x: R[path](x, a[1], a[2]).sum()))
    assert np.all(np.isfinite(np.asarray(grad(a[0]))))
    sl = renormalisation_slice(jnp.float32(2.0), jnp.float32(3.0))
    assert sl(jnp.float32(0.2)).dtype == jnp.float32


def test_python_scalars_give_default_float():
    for path in PATHS:
        shape = jax.eval_shape(lambda p=path: renormalisation(0.5, 1.0, 2.0, path=p))
        assert shape.dtype == jnp.float64
    assert jax.eval_shape(lambda: k_correlation(1.0, 0.1, 1.0, 2.0)).dtype == jnp.float64


def test_invalid_path():
    with pytest.raises(ValueError, match="path"):
        renormalisation(0.5, 1.0, 2.0, path="bogus")


# --- properties -------------------------------------------------------------------------------

unit = st.floats(0.0, 1.0)
log_b = st.floats(-2.0, 4.0)
log_c1 = st.floats(-2.0, math.log10(9.0))


@settings(max_examples=60, deadline=None)
@given(s1=unit, s2=unit, lb=log_b, lc=log_c1)
def test_properties(s1, s2, lb, lc):
    """0 < R ≤ min(1, (c−1)B²/2), i.e. (c−1)B²/R ≥ 2; R non-increasing in s (Anderson's
    inequality: a radially decreasing density over a shifted disk); tables within 1e-4 of exact."""
    B, c = 10.0**lb, 1.0 + 10.0**lc
    lo, hi = sorted((s1, s2))
    r_lo, r_hi = _exact((lo, B, c)), _exact((hi, B, c))
    cap = min(1.0, 0.5 * (c - 1.0) * B * B)
    # Each inequality to 1e-12 relative (the chained form compared r_lo·(1+1e-12) with the cap:
    # R(0; B=1e3, c=6.6) = 1 + 2e-16 after rounding failed it).
    assert 0.0 < r_hi <= r_lo * (1 + 1e-12)
    assert r_lo <= cap * (1 + 1e-12)
    assert float(R_TABLES(hi, B, c)) == pytest.approx(r_hi, rel=1e-4)
    assert float(D["exact"](hi, B, c)) >= 2.0 * (1 - 1e-12)

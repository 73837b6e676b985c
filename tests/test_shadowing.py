"""Smith shadowing-masking of the EPD: check values, closed form, independent quadratures, table
accuracy, joint G forms, gradients at the extremes, dtype and transformation invariants
[HP17 Eq. 36-38; docs/model.md §3.3]."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads
from scipy import integrate, special

from tablegen.check_smith import accuracy_rows, beckmann_lambda, random_points, reference_quad
from tests.helpers import assert_finite_tree, fd_grad
from twoscale import shadowing
from twoscale.geometry import tan_theta
from twoscale.shadowing import (
    joint_g,
    joint_g_from_lambdas,
    smith_g1,
    smith_lambda,
    smith_lambda_a,
    smith_lambda_spline,
    van_ginneken,
)
from twoscale.tables import load_table

#: Compiled with most XLA optimisations off (tests/conftest.py): this module's time is compilation.
COMPILE_QUICKLY = True

PATHS = ("exact", "tables")

# Jitted once per path (eager JAX compiles every primitive per new shape); jit = eager is tested.
LAM = {k: jax.jit(lambda a, p, k=k: smith_lambda_a(a, p, path=k)) for k in PATHS}


def g1_a(a, p, path):
    return 1.0 / (1.0 + LAM[path](a, p))


# --- values ------------------------------------------------------------------------------------


# docs/model.md §3.3: (a, p) → G1, to the digits given there.
CHECK_VALUES = [
    ((0.5, 1.0), 0.99976, 5e-6),
    ((1.0, 1.0), 0.97549, 5e-6),
    ((2.0, 1.0), 0.83358, 5e-6),
    ((1.0, 0.5), 0.7821, 5e-5),
    ((1.0, 2.0), 0.99718, 5e-6),
]


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("args,want,tol", CHECK_VALUES)
def test_check_values(path, args, want, tol):
    assert abs(float(g1_a(*args, path)) - want) <= tol


@pytest.mark.parametrize("path,rtol", [("exact", 1e-12), ("tables", 1e-4)])
def test_beckmann_closed_form(path, rtol):
    """p = 1: ``Λ = (erf μ − 1)/2 + e^{−μ²}/(2μ√π)``, μ = 1/a, from normal-ish to grazing."""
    a = np.geomspace(0.05, 1e7, 300)
    want = beckmann_lambda(a)
    got = np.asarray(LAM[path](a, np.ones_like(a)))
    keep = want > 1e-12
    np.testing.assert_allclose(got[keep], want[keep], rtol=rtol, atol=0)
    # Where Λ is tiny, G1 = 1 to float64 either way.
    np.testing.assert_allclose(1 / (1 + got), 1 / (1 + want), rtol=rtol, atol=0)


def test_limits():
    """Λ(0) = 0 exactly; Λ → 0 as a → 0; Λ ≈ a E[R]/π − 1/2 as a → ∞ (both paths)."""
    for path in PATHS:
        for p in (0.1, 1.0, 10.0):
            assert float(LAM[path](0.0, p)) == 0.0
            assert float(LAM[path](1e-30, p)) < 1e-100
            a = 1e9
            m = float(shadowing.mean_slope(p)) / math.pi
            assert abs(float(LAM[path](a, p)) / (a * m - 0.5) - 1.0) < 1e-6


def _lambda_dblquad(a, p):
    """Λ by ``scipy.integrate.dblquad`` of the definition as written (docs/model.md §3.3)::

    Λ = ∫_{1/a}^{∞} (r a − 1) P2(r) dr,   P2(r) = p/(πΓ(1/p)) ∫_{−∞}^{∞} exp[−(r² + q²)^p] dq.
    """
    cp = p / (math.pi * special.gamma(1.0 / p))
    mu = 1.0 / a
    # The slope density is negligible (< e^{−60}) beyond radius 60^{1/(2p)}; q is symmetric.
    r_max = max(mu, 60.0 ** (0.5 / p)) + 1.0
    val, _ = integrate.dblquad(
        lambda q, r: (r * a - 1.0) * math.exp(-((r * r + q * q) ** p)),
        mu,
        r_max,
        0.0,
        r_max,
        epsabs=0.0,
        epsrel=1e-11,
    )
    return 2.0 * cp * val


@pytest.mark.parametrize(
    "a,p", [(0.5, 1.0), (1.0, 0.5), (2.0, 2.0), (1.5, 0.7), (3.0, 5.0), (0.8, 1.7), (10.0, 3.0)]
)
def test_exact_vs_scipy_dblquad(a, p):
    """Exact path vs SciPy dblquad of the original double integral (independent of every
    derivation in the module)."""
    want = _lambda_dblquad(a, p)
    assert float(LAM["exact"](a, p)) == pytest.approx(want, rel=1e-8)


def test_exact_vs_scipy_polar_random():
    """Exact path vs SciPy quad of the polar single integral at random points, heavy-tailed and
    flat-topped p included."""
    rng = np.random.default_rng(7)
    a = 10.0 ** rng.uniform(-3.0, 7.0, 25)
    p = np.exp(rng.uniform(math.log(0.1), math.log(10.0), 25))
    want = np.array([reference_quad(x, y) for x, y in zip(a, p, strict=True)])
    keep = want > 1e-12
    got = np.asarray(LAM["exact"](a[keep], p[keep]))
    np.testing.assert_allclose(got, want[keep], rtol=1e-9, atol=0)


def test_tables_vs_exact_random():
    """Table path vs exact path at random points over the whole domain: ≤ 1e-4 relative in Λ
    (where Λ > 1e-12) and in G1 (everywhere), including a ∈ [1e-3, 1e7]."""
    a, p = random_points(4000, seed=11)
    a = np.concatenate([a, 10.0 ** np.random.default_rng(3).uniform(-3.0, 7.0, 2000)])
    p = np.concatenate(
        [p, np.exp(np.random.default_rng(4).uniform(math.log(0.1), math.log(10), 2000))]
    )
    ex = np.asarray(LAM["exact"](a, p))
    tb = np.asarray(LAM["tables"](a, p))
    keep = ex > 1e-12
    assert np.max(np.abs(tb[keep] / ex[keep] - 1.0)) < 1e-4
    assert np.max(np.abs((1.0 + ex) / (1.0 + tb) - 1.0)) < 1e-4
    assert np.all(tb >= 0.0)


def test_tables_beyond_edges():
    """Beyond the table (a^{−2p} > 200, a E[R] > 1e7, p outside [0.1, 10]) values stay sensible."""
    # Large a, every p: the neglected −1/2 is ≤ 1.6e-7 of Λ.
    for p in (0.1, 0.5, 3.0, 10.0):
        a = np.array([1e8, 1e10, 1e13])
        np.testing.assert_allclose(LAM["tables"](a, p), LAM["exact"](a, p), rtol=2e-7)
    # Small a: Λ keeps decaying and stays tiny.
    for p in (0.1, 1.0, 10.0):
        a = np.geomspace(1e-16, 0.5 * float(np.exp(-math.log(200.0) / (2 * p))), 20)
        assert np.all(np.asarray(LAM["tables"](a, p)) < 1e-60)
    # p clamped to the table's range.
    assert float(LAM["tables"](1.0, 20.0)) == float(LAM["tables"](1.0, 10.0))


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("p", [0.1, 0.3, 1.0, 3.0, 10.0])
def test_g1_monotone_in_a(path, p):
    a = np.geomspace(1e-16, 1e12, 3000)
    g = np.asarray(g1_a(a, p * np.ones_like(a), path))
    assert np.all(np.diff(g) <= 0.0)
    assert g[0] == 1.0 and 0.0 < g[-1] < 1e-6


def test_smith_lambda_and_g1_compose():
    """``smith_lambda(tan, β, p) = Λ(β tan)``, ``G1 = 1/(1+Λ)``, 1 at normal incidence."""
    for path in PATHS:
        lam = smith_lambda(2.0, 0.3, 1.5, path=path)
        assert float(lam) == pytest.approx(float(LAM[path](0.6, 1.5)), rel=1e-12)
        assert float(smith_g1(2.0, 0.3, 1.5, path=path)) == pytest.approx(1 / (1 + float(lam)))
        assert float(smith_g1(0.0, 0.3, 1.5, path=path)) == 1.0


def test_slice_matches_table_path():
    """The 1-D sliced lookup equals the 2-D table path (same spline, contracted in p)."""
    a = np.geomspace(1e-14, 1e12, 500)
    for p in (0.1, 0.37, 1.0, 4.2, 10.0):
        s = smith_lambda_spline(p)
        got, want = np.asarray(s(a)), np.asarray(LAM["tables"](a, p))
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=0)
        np.testing.assert_allclose(s.g1(a), 1 / (1 + want), rtol=1e-12)
    # Differentiable through the slice in p, and usable under jit.
    g = jax.grad(lambda p: jax.jit(lambda p: smith_lambda_spline(p)(2.0))(p))(1.3)
    assert float(g) == pytest.approx(fd_grad(lambda p: LAM["tables"](2.0, p), 1.3), rel=1e-5)


def test_lookup_equals_the_table_definitions():
    """The lookup's four-transcendental form (the knee as one log1p, ``exp(−h)`` as a polynomial
    times ``e^{−v0}``) equals the coordinate :func:`table_xi` and the reconstruction with
    :func:`essential` that the table was built with, to rounding, over the whole range of a."""
    a = np.geomspace(1e-30, 1e30, 4001)
    for p in (0.1, 0.23, 1.0, 3.7, 10.0):
        s = smith_lambda_spline(p)
        frame = shadowing.table_frame(jnp.asarray(p))
        log_a = np.log(a)
        log_top = np.minimum(log_a, float(frame["log_a_hi"]))
        xi = np.clip(
            np.asarray(shadowing.table_xi(log_top, frame)), shadowing.XI_LO, shadowing.XI_HI
        )
        v0 = np.exp(np.minimum(-2.0 * p * log_top, math.log(shadowing._V0_ZERO)))
        log_m = float(frame["log_es"]) - math.log(math.pi)
        want = np.exp(
            log_a + log_m + np.asarray(s.spline(xi)) - np.asarray(shadowing.essential(v0))
        )
        got = np.asarray(s(a))
        big = want > 1e-250
        assert np.all(got[~big] < 1e-240)
        np.testing.assert_allclose(got[big], want[big], rtol=1e-11, atol=0)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_of_cos_equals_lambda_of_tan(dtype):
    """``SmithLambdaSpline.of_cos`` (the model's per-direction call) equals the slice at
    ``β tan θ`` in value and in its gradients along β and p, from normal incidence to the
    horizon (cos θ = 0 and cosines below machine epsilon included: finite, no NaN)."""
    c = np.concatenate(
        [[0.0, 1e-20, 1e-9], np.linspace(0.0, 1.0, 2001), np.geomspace(1e-8, 1, 300)]
    )
    c = jnp.asarray(c, dtype)
    rtol = 1e-10 if dtype == jnp.float64 else 3e-4

    def new(b, pp, c):
        return smith_lambda_spline(pp).of_cos(c, b)

    def old(b, pp, c):
        return smith_lambda_spline(pp)(b * tan_theta(c))

    # ∂G1/∂β and ∂G1/∂p at every cosine, compiled once for all (β, p).
    grads = {
        (f, arg): jax.jit(
            jax.vmap(jax.grad(lambda *x, f=f: 1.0 / (1.0 + f(*x)), argnums=arg), (None, None, 0))
        )
        for f in (new, old)
        for arg in (0, 1)
    }
    for beta, p in ((0.001, 0.2), (0.05, 0.7), (0.3, 1.0), (1.0, 4.0), (0.2, 10.0)):
        b, pp = jnp.asarray(beta, dtype), jnp.asarray(p, dtype)
        got, want = np.asarray(new(b, pp, c)), np.asarray(old(b, pp, c))
        assert got.dtype == dtype and np.all(np.isfinite(got))
        g1 = 1.0 / (1.0 + want)
        np.testing.assert_allclose(1.0 / (1.0 + got), g1, rtol=rtol, atol=0)
        sig = want > 1e-30
        np.testing.assert_allclose(got[sig], want[sig], rtol=rtol, atol=0)
        for arg in (0, 1):
            x = np.asarray(grads[new, arg](b, pp, c))
            y = np.asarray(grads[old, arg](b, pp, c))
            assert np.all(np.isfinite(x))
            np.testing.assert_allclose(x, y, rtol=rtol, atol=rtol * np.max(np.abs(y)))


@pytest.mark.parametrize("beta", [0.001, 0.05, 1.0])
def test_lambda_partials_equal_forward_mode(beta):
    """The hand-written partials of Λ along β and p equal forward-mode differentiation of the
    same lookup, from normal incidence to the horizon, for p across the table (and beyond it,
    where the slice clamps p and ∂/∂p is 0)."""
    c = np.concatenate(
        [[0.0, 1e-20, 1e-9, 1.0], np.linspace(0, 1, 1001), np.geomspace(1e-8, 1, 200)]
    )
    c = jnp.asarray(c)
    for p in (0.05, 0.1, 0.2, 0.5, 1.7, 10.0, 12.0):

        def lam(b, q):
            return smith_lambda_spline(q).of_cos(c, b)

        value, d_beta, d_p = shadowing.lambda_partials(c, beta, p)
        x = (jnp.float64(beta), jnp.float64(p))
        want, want_beta = jax.jvp(lam, x, (1.0, 0.0))
        _, want_p = jax.jvp(lam, x, (0.0, 1.0))
        np.testing.assert_allclose(value, want, rtol=1e-13, atol=0)
        for got, ref in ((d_beta, want_beta), (d_p, want_p)):
            got, ref = np.asarray(got), np.asarray(ref)
            assert np.all(np.isfinite(got))
            np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-200)


# --- joint G -----------------------------------------------------------------------------------


def test_van_ginneken_wrapping():
    phi = np.linspace(0.0, np.pi, 13)
    lam = np.asarray(van_ginneken(phi))
    np.testing.assert_allclose(lam, 4.41 * phi / (4.41 * phi + 1.0), rtol=1e-15)
    for other in (2 * np.pi - phi, phi + 2 * np.pi, -phi, phi - 4 * np.pi):
        np.testing.assert_allclose(van_ginneken(other), lam, rtol=1e-12, atol=1e-14)
    assert float(van_ginneken(np.pi)) == pytest.approx(0.933, abs=5e-4)  # docs/model.md §3.3


@pytest.mark.parametrize("path", PATHS)
def test_joint_g_forms(path):
    ti, to, beta, p = np.array([0.3, 1.5, 4.0]), np.array([2.0, 0.1, 4.0]), 0.4, 1.2
    g1i = np.asarray(smith_g1(ti, beta, p, path=path))
    g1o = np.asarray(smith_g1(to, beta, p, path=path))
    li = np.asarray(smith_lambda(ti, beta, p, path=path))
    lo = np.asarray(smith_lambda(to, beta, p, path=path))
    unc = np.asarray(joint_g(ti, to, 0.7, beta, p, correlated=False, path=path))
    np.testing.assert_allclose(unc, g1i * g1o, rtol=1e-12)
    # φ = 0: fully correlated, G = min(G1_i, G1_o); φ = π: 1/(1 + max + λ(π) min).
    g0 = np.asarray(joint_g(ti, to, 0.0, beta, p, path=path))
    np.testing.assert_allclose(g0, np.minimum(g1i, g1o), rtol=1e-12)
    gpi = np.asarray(joint_g(ti, to, np.pi, beta, p, path=path))
    lam_pi = 4.41 * np.pi / (4.41 * np.pi + 1.0)
    want = 1.0 / (1.0 + np.maximum(li, lo) + lam_pi * np.minimum(li, lo))
    np.testing.assert_allclose(gpi, want, rtol=1e-12)
    assert np.all(g0 >= gpi) and np.all(gpi >= unc * (1 - 1e-12))
    # From precomputed Λ, and symmetric in (i, o).
    np.testing.assert_allclose(joint_g_from_lambdas(li, lo, 1.0), joint_g_from_lambdas(lo, li, 1.0))
    np.testing.assert_allclose(
        joint_g_from_lambdas(li, lo, 1.0), joint_g(ti, to, 1.0, beta, p, path=path), rtol=1e-12
    )


# --- gradients ---------------------------------------------------------------------------------


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("a,p", [(0.6, 1.0), (1.0, 0.5), (3.0, 2.5), (0.9, 8.0), (40.0, 0.15)])
def test_check_grads_interior(path, a, p):
    # LAM[path]: one jitted function for every point (its derivatives compile once per path).
    check_grads(LAM[path], (a, p), order=1, modes=("rev",), eps=1e-5, atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("beta", [1e-3, 1.0])
@pytest.mark.parametrize("p", [0.2, 5.0])
@pytest.mark.parametrize("tan", [0.0, 0.7, 1e6])
def test_gradients_at_extremes(path, beta, p, tan):
    """Normal incidence (tan 0), grazing (cos θ = 1e-6 → tan ≈ 1e6), β ∈ {1e-3, 1}, p ∈ {0.2, 5}:
    finite gradients that match float64 finite differences."""

    def g1(t, b, q):
        return smith_g1(t, b, q, path=path)

    grads = jax.grad(g1, argnums=(0, 1, 2))(tan, beta, p)
    assert_finite_tree(grads, "G1 gradient")
    for k, x in enumerate((tan, beta, p)):
        args = [tan, beta, p]

        def partial(v, k=k, args=args):
            a = list(args)
            a[k] = v
            return g1(*a)

        h = 1e-6 * max(abs(x), 1e-3)
        want = fd_grad(partial, x, h)
        assert float(grads[k]) == pytest.approx(want, rel=1e-4, abs=1e-9)
    # Joint G, both forms, in every argument (φ away from its folds).
    for corr in (True, False):
        jg = jax.grad(
            lambda ti, to, ph, b, q, corr=corr: joint_g(
                ti, to, ph, b, q, correlated=corr, path=path
            ),
            argnums=(0, 1, 2, 3, 4),
        )(tan, 0.5 * tan + 0.2, 1.0, beta, p)
        assert_finite_tree(jg, "joint G gradient")


def test_gradients_at_ties_and_folds():
    """max/min at Λ_i = Λ_o, φ at 0 and π (folds of the wrap), a = 0 and a = ∞: finite."""
    for path in PATHS:
        for phi in (0.0, np.pi, 2 * np.pi, -1.0):
            g = jax.grad(
                lambda t, ph, path=path: joint_g(t, t, ph, 0.5, 1.0, path=path), argnums=(0, 1)
            )(1.3, phi)
            assert_finite_tree(g)
        for a in (0.0, np.inf, 1e300):
            g = jax.grad(
                lambda a, p, path=path: 1 / (1 + smith_lambda_a(a, p, path=path)), argnums=(0, 1)
            )(a, 1.0)
            assert_finite_tree(g)
            jg = jax.grad(lambda t, path=path: joint_g(t, t, 0.0, 1.0, 1.0, path=path))(a)
            assert np.isfinite(float(jg))


def test_table_derivative_continuous_across_nodes():
    """The C² spline: dΛ/da and dΛ/dp agree on both sides of a grid node (in ξ and in log p)."""
    tab = load_table(shadowing.TABLE_NAME)
    xi_axis, p_axis = tab.axes[1], tab.axes[0]
    p = 1.3
    frame = {k: float(v) for k, v in shadowing.table_frame(p).items()}
    xi_node = xi_axis.nodes()[xi_axis.n // 2]
    # Invert ξ(log a) for this p by bisection.
    lo, hi = -50.0, 50.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if float(shadowing.table_xi(mid, frame)) < xi_node else (lo, mid)
    a_node = math.exp(0.5 * (lo + hi))
    da = jax.grad(lambda a: smith_lambda_a(a, p))
    left, right = float(da(a_node * (1 - 1e-9))), float(da(a_node * (1 + 1e-9)))
    assert left == pytest.approx(right, rel=1e-6)
    p_node = float(np.exp(p_axis.nodes()[p_axis.n // 2]))
    dp = jax.grad(lambda p: smith_lambda_a(2.0, p), argnums=0)
    left, right = float(dp(p_node * (1 - 1e-9))), float(dp(p_node * (1 + 1e-9)))
    assert left == pytest.approx(right, rel=1e-6)


# --- dtype, jit, properties --------------------------------------------------------------------


@pytest.mark.parametrize("path", PATHS)
def test_jit_equals_eager(path):
    a = np.geomspace(1e-4, 1e8, 37)
    p = np.linspace(0.1, 10.0, 37)
    eager = smith_lambda_a(a, p, path=path)
    np.testing.assert_allclose(LAM[path](a, p), eager, rtol=1e-13, atol=0)
    f = lambda ti, to: joint_g(ti, to, 2.0, 0.3, 1.7, path=path)  # noqa: E731
    np.testing.assert_allclose(jax.jit(f)(a, a[::-1]), f(a, a[::-1]), rtol=1e-13)


@pytest.mark.parametrize("path", PATHS)
def test_float32_in_float32_out(path):
    t = jnp.asarray(np.geomspace(1e-3, 1e6, 20), jnp.float32)
    b, p = jnp.float32(0.3), jnp.float32(1.5)
    outs = {
        "lambda_a": smith_lambda_a(t, p, path=path),
        "lambda": smith_lambda(t, b, p, path=path),
        "g1": smith_g1(t, b, p, path=path),
        "joint": joint_g(t, t[::-1], jnp.float32(1.0), b, p, path=path),
        "joint_unc": joint_g(t, t[::-1], jnp.float32(1.0), b, p, correlated=False, path=path),
        "vg": van_ginneken(jnp.float32(1.0)),
        "slice": smith_lambda_spline(p)(t),
    }
    for name, v in outs.items():
        assert v.dtype == jnp.float32, name
        assert np.all(np.isfinite(np.asarray(v))), name
    # float32 agrees with float64 to float32 accuracy.
    ref = np.asarray(smith_g1(np.asarray(t, np.float64), 0.3, 1.5, path=path))
    np.testing.assert_allclose(np.asarray(outs["g1"], np.float64), ref, rtol=2e-5)
    g = jax.grad(lambda t: jnp.sum(smith_g1(t, b, p, path=path)))(t)
    assert g.dtype == jnp.float32 and np.all(np.isfinite(np.asarray(g)))


def test_bad_path():
    with pytest.raises(ValueError, match="path"):
        smith_lambda_a(1.0, 1.0, path="table")


_a = st.one_of(
    st.sampled_from([0.0, 1e-300, 1e-6, 1.0, 1e6, 1e15, 1e300, math.inf]),
    st.floats(0.0, 1e12, allow_nan=False),
)


@settings(max_examples=60, deadline=None)
@given(
    ti=_a,
    to=_a,
    phi=st.floats(-20.0, 20.0, allow_nan=False),
    beta=st.floats(1e-3, 1.0),
    p=st.floats(0.1, 10.0),
    path=st.sampled_from(PATHS),
    correlated=st.booleans(),
)
def test_property_finite_values_and_grads(ti, to, phi, beta, p, path, correlated):
    args = tuple(jnp.float64(x) for x in (ti, to, phi, beta, p))
    val, grads = _G_AND_GRAD(*args, correlated=correlated, path=path)
    assert 0.0 <= float(val) <= 1.0
    assert_finite_tree(grads, "gradient")
    lam = _LAMBDA(args[0], args[3], args[4], path=path)
    assert np.isfinite(float(lam)) and float(lam) >= 0.0


# Compiled once per (correlated, path), not once per example: each example only runs them.
_G_AND_GRAD = jax.jit(
    jax.value_and_grad(joint_g, argnums=(0, 1, 2, 3, 4)), static_argnames=("correlated", "path")
)
_LAMBDA = jax.jit(smith_lambda, static_argnames=("path",))


# --- generator and report ----------------------------------------------------------------------


def test_shipped_table_matches_generator():
    """The packaged table has the generator's axes and version, and a small rebuild is
    deterministic."""
    from tablegen import build_smith

    tab = load_table(shadowing.TABLE_NAME)
    assert tab.axes == build_smith.axes()
    assert tab.meta["version"] == build_smith.VERSION
    # The shipped axes' ranges with fewer nodes (a coarse grid would pad them past the range
    # where Λ is representable): two rebuilds are bit-identical.
    ax = tuple(dataclasses.replace(a, n=n) for a, n in zip(tab.axes, (5, 9), strict=True))
    np.testing.assert_array_equal(build_smith.t_grid(ax), build_smith.t_grid(ax))
    # The grid values are T at the nodes: the shipped table reproduces the exact path there.
    lp = tab.axes[0].nodes()[10]
    xi = tab.axes[1].nodes()[1:-1][::25]  # interior nodes: the padding nodes lie outside ξ's range
    log_a = build_smith.log_a_of_xi(xi, np.full_like(xi, np.exp(lp)))
    want = np.asarray(LAM["exact"](np.exp(log_a), np.full_like(xi, np.exp(lp))))
    np.testing.assert_allclose(LAM["tables"](np.exp(log_a), np.exp(lp)), want, rtol=1e-9)


def test_accuracy_rows_report():
    rows = accuracy_rows(n_points=3000, seed=1, n_scipy=12)
    by = {(r["quantity"], r["domain"]): r for r in rows}
    assert all(r["n_points"] > 0 for r in rows)
    for r in rows:
        bound = 1e-4 if "tables" in r["quantity"] else 1e-9
        assert r["max_rel_err"] < bound, r
    assert any("G1" in k[0] for k in by)

"""EPD normal distribution: normalisation, Beckmann and gennorm references, gradients, dtypes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads
from scipy import integrate, special, stats

from tests.helpers import assert_finite_tree, grads_all
from twoscale import distribution


@pytest.mark.parametrize("p", [0.3, 1.0, 3.0])
@pytest.mark.parametrize("beta", [0.01, 0.1, 0.5])
def test_projected_area_normalisation(p, beta):
    """∫ D(m) cos θ_m dω_m = 1 (SciPy adaptive quadrature, split at the lobe's scale)."""

    def f(t):
        return 2 * np.pi * float(distribution.ndf(np.cos(t), beta, p)) * np.cos(t) * np.sin(t)

    pts = [np.arctan(beta * x) for x in (0.1, 1.0, 3.0, 10.0)]
    val = integrate.quad(f, 0, np.pi / 2, points=pts, limit=500, epsabs=1e-13)[0]
    assert val == pytest.approx(1.0, abs=1e-7)


def test_p1_is_beckmann():
    beta = 0.23
    cos = np.linspace(0.05, 1.0, 50)
    tan2 = (1 - cos**2) / cos**2
    beck = np.exp(-tan2 / beta**2) / (np.pi * beta**2 * cos**4)
    np.testing.assert_allclose(distribution.ndf(cos, beta, 1.0), beck, rtol=1e-12)


def test_slope_density_is_bivariate_gennorm():
    """P22 is radially a generalised normal: its marginal in one slope matches scipy's gennorm-based
    density integrated over the other slope (independent reference via SciPy)."""
    beta, p = 0.3, 2.5
    d0 = float(distribution.d0(beta, p))
    assert d0 == pytest.approx(p / (np.pi * beta**2 * special.gamma(1 / p)), rel=1e-12)
    # ∫∫ P22 dx dy = 1 over the slope plane (P22(x, y) = d0 exp(-((x²+y²)/β²)^p)).
    val = integrate.quad(
        lambda r: 2 * np.pi * r * d0 * np.exp(-((r**2 / beta**2) ** p)), 0, np.inf, limit=200
    )[0]
    assert val == pytest.approx(1.0, rel=1e-9)
    # 1-D radial profile equals scipy.stats.gennorm with shape 2p evaluated at r/β (up to a constant).
    r = np.linspace(0, 3 * beta, 7)
    prof = np.exp(-((r**2 / beta**2) ** p))
    ref = stats.gennorm.pdf(r / beta, 2 * p) / stats.gennorm.pdf(0.0, 2 * p)
    np.testing.assert_allclose(prof, ref, rtol=1e-12)


def test_below_horizon_zero():
    assert float(distribution.ndf(0.0, 0.3, 1.0)) == 0.0
    assert float(distribution.ndf(-0.5, 0.3, 1.0)) == 0.0


def test_small_p_does_not_overflow():
    # Γ(1/p) overflows for p < ~0.006 in float64; lgamma keeps d0 finite.
    assert np.isfinite(float(distribution.d0(0.3, 0.005)))
    assert np.isfinite(float(distribution.ndf(0.99, 0.3, 0.005)))


@pytest.mark.parametrize("cos", [1.0, 0.999999, 0.7, 1e-3, 1e-7, 0.0])
@pytest.mark.parametrize("beta", [1e-3, 0.2, 1.0])
@pytest.mark.parametrize("p", [0.2, 1.0, 5.0])
def test_gradients_finite_at_extremes(cos, beta, p):
    assert_finite_tree(grads_all(distribution.ndf, cos, beta, p), "ndf gradient")
    assert_finite_tree(grads_all(distribution.log_ndf, cos, beta, p), "log_ndf gradient")


def test_gradient_in_p_at_normal_incidence_is_finite():
    # Trap 1: (tan²θ/β²)^p at θ = 0 has d/dp = 0·log 0. The exact derivative of D(0) = d0 is
    # d d0/dp, which we compare with a central difference.
    beta = 0.2
    g = float(jax.grad(distribution.ndf, argnums=2)(1.0, beta, 0.5))
    h = 1e-6
    fd = (float(distribution.d0(beta, 0.5 + h)) - float(distribution.d0(beta, 0.5 - h))) / (2 * h)
    assert g == pytest.approx(fd, rel=1e-6)


@pytest.mark.parametrize("cos,beta,p", [(0.9, 0.3, 0.7), (0.95, 0.1, 2.0), (0.5, 0.8, 1.3)])
def test_check_grads_interior(cos, beta, p):
    # eps = 1e-6: D has large second derivatives near the peak when p < 1.
    check_grads(distribution.ndf, (cos, beta, p), order=2, modes=["fwd", "rev"], eps=1e-6)


def test_dtype_and_jit():
    c = jnp.linspace(0, 1, 9, dtype=jnp.float32)
    assert distribution.ndf(c, jnp.float32(0.2), jnp.float32(1.5)).dtype == jnp.float32
    c64 = np.linspace(0, 1, 9)
    np.testing.assert_allclose(
        jax.jit(distribution.ndf)(c64, 0.2, 1.5), distribution.ndf(c64, 0.2, 1.5), rtol=1e-13
    )
    batched = jax.vmap(distribution.ndf, in_axes=(None, 0, 0))(
        c64, jnp.array([0.1, 0.2]), jnp.array([1.0, 2.0])
    )
    np.testing.assert_allclose(batched[1], distribution.ndf(c64, 0.2, 2.0), rtol=1e-13)


@settings(max_examples=60, deadline=None)
@given(cos=st.floats(0.0, 1.0), beta=st.floats(1e-3, 1.0), p=st.floats(0.1, 10.0))
def test_property_finite(cos, beta, p):
    v = distribution.ndf(cos, beta, p)
    assert np.isfinite(v) and float(v) >= 0.0
    assert_finite_tree(grads_all(distribution.ndf, cos, beta, p), "grad")

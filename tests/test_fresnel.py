"""Fresnel: closed forms, agreement between the two formulas, limits, gradients, dtypes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

from tests.helpers import assert_finite_tree, grads_all
from twoscale import fresnel


def _conductor_complex(cos, eta, k):
    """Independent reference: Fresnel equations with complex arithmetic (NumPy)."""
    n = eta + 1j * k
    sin2 = 1 - cos**2
    ct = np.sqrt(n**2 - sin2 + 0j) / n  # cos of the (complex) refraction angle
    rs = (cos - n * ct) / (cos + n * ct)
    rp = (n * cos - ct) / (n * cos + ct)
    return 0.5 * (abs(rs) ** 2 + abs(rp) ** 2)


@pytest.mark.parametrize("eta,k", [(1.5, 0.0), (0.2, 3.0), (1.1, 6.6), (2.8, 0.4), (0.05, 2.0)])
def test_normal_incidence_closed_form(eta, k):
    expected = ((eta - 1) ** 2 + k**2) / ((eta + 1) ** 2 + k**2)
    assert float(fresnel.conductor(1.0, eta, k)) == pytest.approx(expected, rel=1e-12)
    if k == 0.0:
        assert float(fresnel.dielectric(1.0, eta)) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("eta,k", [(1.5, 0.0), (0.2, 3.0), (1.1, 6.6), (2.8, 0.4), (0.05, 2.0)])
def test_conductor_matches_complex_reference(eta, k):
    cos = np.linspace(0.0, 1.0, 101)
    ref = _conductor_complex(cos, eta, k)
    got = np.asarray(fresnel.conductor(cos, eta, k))
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("eta", [1.0001, 1.33, 1.5, 2.4, 4.0])
def test_conductor_k0_equals_dielectric(eta):
    cos = np.linspace(0.0, 1.0, 201)
    np.testing.assert_allclose(
        fresnel.conductor(cos, eta, 0.0), fresnel.dielectric(cos, eta), rtol=1e-12, atol=1e-15
    )


def test_grazing_gives_one():
    for f in (lambda c: fresnel.dielectric(c, 1.5), lambda c: fresnel.conductor(c, 0.3, 2.5)):
        assert float(f(0.0)) == pytest.approx(1.0, abs=1e-15)
        assert float(f(1e-7)) == pytest.approx(1.0, abs=1e-5)


def test_total_internal_reflection():
    # eta < 1: critical angle at sin θ = eta; beyond it F = 1.
    cos_crit = np.sqrt(1 - 0.7**2)
    assert float(fresnel.dielectric(cos_crit * 0.99, 0.7)) == 1.0
    assert float(fresnel.dielectric(1.0, 0.7)) < 0.1


def test_diffuse_fresnel_continuity_and_values():
    # The two published branches of the fit do not meet exactly at η = 1: 0.00170 vs 0.00021.
    lo = float(fresnel.diffuse_fresnel(1.0 - 1e-12))
    hi = float(fresnel.diffuse_fresnel(1.0))
    assert lo == pytest.approx(0.0017, abs=1e-6) and hi == pytest.approx(0.000207, abs=1e-6)
    # Known values of the fit: Fdr(1.5) ≈ 0.092 (varnish), Fdr(1/1.5) ≈ 0.596 (internal).
    assert float(fresnel.diffuse_fresnel(1.5)) == pytest.approx(0.0918, abs=2e-3)
    assert float(fresnel.diffuse_fresnel(1 / 1.5)) == pytest.approx(0.596, abs=5e-3)


def test_diffuse_fresnel_against_quadrature():
    # Fdr(η) = ∫ F(θ) 2 cosθ sinθ dθ, the cosine-weighted hemispherical average (independent reference).
    from scipy import integrate

    for eta in (1.3, 1.5, 2.0):
        ref = integrate.quad(lambda c, e=eta: 2 * c * float(fresnel.dielectric(c, e)), 0, 1)[0]
        assert float(fresnel.diffuse_fresnel(eta)) == pytest.approx(ref, abs=5e-3)


@pytest.mark.parametrize("cos", [1.0, 0.7, 0.2, 1e-6, 1e-7])
@pytest.mark.parametrize("eta,k", [(1.5, 0.0), (0.2, 3.0), (2.0, 0.0), (1.0, 1.0)])
def test_gradients_finite_everywhere(cos, eta, k):
    g = grads_all(fresnel.conductor, cos, eta, k)
    assert_finite_tree(g, "conductor gradient")
    if k == 0.0:
        assert_finite_tree(grads_all(fresnel.dielectric, cos, eta), "dielectric gradient")


@pytest.mark.parametrize("cos", [0.9, 0.5, 0.1])
def test_check_grads_interior(cos):
    check_grads(
        lambda c, e, k: fresnel.conductor(c, e, k), (cos, 0.4, 2.7), order=2, modes=["fwd", "rev"]
    )
    check_grads(lambda c, e, k: fresnel.conductor(c, e, k), (cos, 1.6, 0.3), order=2, modes=["rev"])
    check_grads(lambda c, e: fresnel.dielectric(c, e), (cos, 1.5), order=2, modes=["fwd", "rev"])
    check_grads(fresnel.diffuse_fresnel, (1.0 / (1.0 + cos),), order=1, modes=["rev"])
    check_grads(fresnel.diffuse_fresnel, (1.0 + cos,), order=1, modes=["rev"])


def test_k_zero_gradient_in_k():
    # At k = 0 the derivative in k of a dielectric-like conductor is 0 by symmetry (F even in k).
    g = jax.grad(fresnel.conductor, argnums=2)(0.6, 1.5, 0.0)
    assert np.isfinite(g) and abs(float(g)) < 1e-12


def test_dtype_preserved_and_jit():
    c32 = jnp.linspace(0, 1, 17, dtype=jnp.float32)
    assert fresnel.conductor(c32, jnp.float32(0.2), jnp.float32(3.0)).dtype == jnp.float32
    assert fresnel.dielectric(c32, jnp.float32(1.5)).dtype == jnp.float32
    assert fresnel.diffuse_fresnel(jnp.float32(1.5)).dtype == jnp.float32
    c = np.linspace(0, 1, 17)
    # jit may fuse operations differently: equal to a few ulp.
    np.testing.assert_allclose(
        jax.jit(fresnel.conductor)(c, 0.2, 3.0), fresnel.conductor(c, 0.2, 3.0), rtol=1e-14
    )


@settings(max_examples=60, deadline=None)
@given(
    cos=st.floats(0.0, 1.0),
    eta=st.floats(0.05, 5.0),
    k=st.floats(0.0, 10.0),
)
def test_property_finite(cos, eta, k):
    v = fresnel.conductor(cos, eta, k)
    assert np.isfinite(v) and 0.0 <= float(v) <= 1.0
    assert_finite_tree(grads_all(fresnel.conductor, cos, eta, k), "grad")
    d = fresnel.dielectric(cos, eta)
    assert np.isfinite(d) and 0.0 <= float(d) <= 1.0
    assert_finite_tree(grads_all(fresnel.dielectric, cos, eta), "grad")


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_gradients_finite_deep_grazing_grid(dtype):
    """Regression: cos θ down to denormals (cos θ = 4.5e-160, η = 1 once gave a NaN gradient).

    The discarded branch of a Fresnel ratio had ``den² = 0``; every combination of tiny cosines,
    index-matched and total-internal-reflection indices and k = 0 / tiny / large is checked.
    """
    cs = jnp.array(
        [0, 5e-324, 1e-310, 1e-300, 1e-200, 4.5e-160, 1e-155, 1e-150, 1e-100, 1e-20, 1e-8, 0.5, 1.0]
    )
    es = jnp.array([0.05, 0.5, 0.999, 1.0, 1.0 + 1e-12, 1.001, 1.5, 5.0])
    ks = jnp.array([0.0, 1e-300, 1e-8, 1.0, 10.0])
    c, e, k = (x.astype(dtype).ravel() for x in jnp.meshgrid(cs, es, ks, indexing="ij"))
    for f, args in ((fresnel.conductor, (c, e, k)), (fresnel.dielectric, (c, e))):
        vals = jax.vmap(f)(*args)
        assert vals.dtype == dtype
        assert np.all(np.isfinite(vals)) and np.all((vals >= 0) & (vals <= 1))
        grads = jax.vmap(jax.grad(f, argnums=tuple(range(len(args)))))(*args)
        assert_finite_tree(grads, f"{f.__name__} gradient")

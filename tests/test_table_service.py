"""The table service (``twoscale.tables.spline``): one registry keyed by table, dtype and extra."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twoscale import convolution, psd, shadowing, tables

NAMES = (shadowing.TABLE_NAME, psd.TABLE_NAME, convolution.TABLE_NAME)


def test_same_key_same_object():
    for name in NAMES:
        assert tables.spline(name, jnp.float64) is tables.spline(name, "float64")
    a = tables.spline(convolution.TABLE_NAME, jnp.float64, "map", n_axes=4)
    assert a is tables.spline(convolution.TABLE_NAME, np.float64, "map", n_axes=4)
    assert a.ndim == 4 and a.coeffs.shape[-1] == 3  # (β, p, c, u) axes, 3 components
    key = (convolution.TABLE_NAME, "float64", "map", 4, 3, 1)
    assert key in tables.cached_splines()


def test_dtypes_get_their_own_splines():
    s64 = tables.spline(shadowing.TABLE_NAME, jnp.float64)
    s32 = tables.spline(shadowing.TABLE_NAME, jnp.float32)
    assert s64 is not s32
    assert s64.coeffs.dtype == jnp.float64 and s32.coeffs.dtype == jnp.float32
    np.testing.assert_array_equal(s32.coeffs, np.asarray(s64.coeffs).astype(np.float32))


def test_clear_caches_and_reload_identical():
    before = {name: np.asarray(tables.spline(name, jnp.float64).coeffs) for name in NAMES}
    old = tables.spline(psd.TABLE_NAME, jnp.float64)
    tables.clear_caches()
    assert tables.cached_splines() == ()
    assert tables.load_table.cache_info().currsize == 0
    new = tables.spline(psd.TABLE_NAME, jnp.float64)
    assert new is not old and (new.lo, new.step, new.n) == (old.lo, old.step, old.n)
    for name in NAMES:
        after = np.asarray(tables.spline(name, jnp.float64).coeffs)
        assert after.tobytes() == before[name].tobytes()


def test_float32_in_float32_tables():
    f32 = jnp.float32
    assert shadowing.smith_lambda_spline(f32(1.5)).spline.coeffs.dtype == f32
    assert psd.renormalisation_slice(f32(3.0), f32(2.2)).spline.coeffs.dtype == f32
    lobe = convolution.lobe_spline(0.1, 1.5, 2.2, f32)
    assert all(s.coeffs.dtype == f32 for s in (lobe.g, lobe.log_map))
    assert lobe.log_k.dtype == f32
    out = lobe(jnp.linspace(0, 1, 5, dtype=f32), f32(0.5))
    assert out.dtype == f32
    assert {k[1] for k in tables.cached_splines() if k[0] in NAMES} >= {"float32"}


def test_key_is_the_canonical_dtype():
    """Without x64 a float64 request gets (and is cached as) float32; with x64 back on, float64."""
    with jax.enable_x64(False):
        s = tables.spline(shadowing.TABLE_NAME, jnp.float64)
        assert s.coeffs.dtype == jnp.float32
        assert s is tables.spline(shadowing.TABLE_NAME, jnp.float32)
        assert shadowing.smith_lambda_spline(1.5).spline.coeffs.dtype == jnp.float32
    assert tables.spline(shadowing.TABLE_NAME, jnp.float64).coeffs.dtype == jnp.float64
    assert shadowing.smith_lambda_spline(1.5).spline.coeffs.dtype == jnp.float64


def test_extra_needs_n_axes():
    with pytest.raises(ValueError, match="n_axes"):
        tables.spline(convolution.TABLE_NAME, jnp.float64, "map")
    with pytest.raises(ValueError, match="n_axes"):
        tables.spline(convolution.TABLE_NAME, jnp.float64, n_axes=2)
    with pytest.raises(KeyError, match="no extra"):
        tables.spline(convolution.TABLE_NAME, jnp.float64, "nope", n_axes=2)


def test_interpolation_hook():
    default = tables.spline(shadowing.TABLE_NAME, jnp.float64)
    extra = tables.spline(convolution.TABLE_NAME, jnp.float64, "log_k", n_axes=2)
    with tables.interpolation(order=1, stride=2):
        s = tables.spline(shadowing.TABLE_NAME, jnp.float64)
        assert s.order == 1 and s.n == tuple((n - 1) // 2 + 1 for n in default.n)
        assert tables.spline(convolution.TABLE_NAME, jnp.float64, "log_k", n_axes=2) is extra
        with tables.interpolation(order=3, stride=2):  # nests
            assert tables.spline(shadowing.TABLE_NAME, jnp.float64).order == 3
        assert tables.spline(shadowing.TABLE_NAME, jnp.float64) is s
    assert tables.spline(shadowing.TABLE_NAME, jnp.float64) is default
    with pytest.raises(ValueError, match="order"), tables.interpolation(order=2):
        pass


def test_large_table_stored_float32_computes_float64():
    """The convolution table keeps float32 coefficients (they are constants of every compiled
    function that slices it) but slices and evaluates in float64: its values agree with the
    float64 coefficients' to the float32 rounding, and the result and its gradient are float64."""
    name = convolution.TABLE_NAME
    assert name in tables.STORED_FLOAT32
    stored = tables.spline(name, jnp.float64)
    assert stored.coeffs.dtype == jnp.float32 and stored.dtype == jnp.float64
    wide = tables.load_table(name).spline(jnp.float64)
    assert wide.coeffs.dtype == jnp.float64 and wide.compute is None
    at = (jnp.log(0.01), jnp.log(0.7), jnp.log(0.5))
    a, b = stored.slice(*at), wide.slice(*at)
    assert a.coeffs.dtype == jnp.float64
    x = (jnp.linspace(0.0, 7.0, 9), jnp.linspace(0.0, 1.0, 9))
    np.testing.assert_allclose(np.asarray(a(*x)), np.asarray(b(*x)), rtol=0, atol=2e-6)
    # A 5-D query straight on the stored spline gives the same as slicing first.
    full = stored(*(jnp.full(9, v) for v in at), *x)
    assert full.dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(full), np.asarray(a(*x)), rtol=1e-12, atol=1e-12)
    g = jax.grad(lambda lb: stored.slice(lb, *at[1:])(*x).sum())(at[0])
    gw = jax.grad(lambda lb: wide.slice(lb, *at[1:])(*x).sum())(at[0])
    assert g.dtype == jnp.float64 and abs(float(g) - float(gw)) <= 1e-5 * (1 + abs(float(gw)))

"""The per-pair path of ``brdf`` (channels vmapped, channel first) against the channel-last
composition the grid path uses, and the kernels the per-pair path added: values to float64
round-off, gradients equal."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import twoscale
from twoscale import geometry, model, psd, shadowing, spectral
from twoscale._numerics import asinh_nonneg
from twoscale.tables import Axis, Table

#: Compiled with most XLA optimisations off (tests/conftest.py): this module's time is compilation.
COMPILE_QUICKLY = True

CONDUCTOR = twoscale.TwoScaleParams.conductor(
    beta=0.1, p=1.5, eta=(0.2, 0.5, 1.4), k=(3.5, 2.5, 1.9), sigma_s=0.01, b=1.5, c=2.2
)
PLASTIC = twoscale.TwoScaleParams.plastic(
    0.08, 0.8, 1.5, (0.2, 0.3, 0.4), sigma_s=0.02, b=0.8, c=1.8, e=0.4
)
_WL = tuple(spectral.spectral_wavelengths(5))
_ETA, _K = spectral.preset("gold", _WL)
SPECTRAL = twoscale.TwoScaleParams.conductor(
    beta=0.2, p=0.9, eta=_ETA, k=_K, sigma_s=0.02, b=1.0, c=2.8
)
CASES = [
    (CONDUCTOR, twoscale.ModelConfig(q_mode="full")),
    (PLASTIC, twoscale.ModelConfig(material="plastic", apparatus=True, fresnel="schlick")),
    (SPECTRAL, twoscale.ModelConfig(wavelengths=_WL, shadowing="uncorrelated")),
]


def _dirs(n, seed):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(2, n, 3))
    v[..., 2] = np.abs(v[..., 2])
    v[0, :5, 2] *= -1.0  # a few below the horizon
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    return jnp.asarray(v[0]), jnp.asarray(v[1])


def _channel_last(params, wi, wo, cfg):
    """The channel-last composition (``_half_diff_terms`` + ``_cells_total``, as the grid path)."""
    ch = model._channels(params, cfg, wi, wo)
    fr = geometry.frame(wi, wo)
    above = (fr.cos_i > 0.0) & (fr.cos_o > 0.0)
    hd = model._half_diff_terms(
        ch,
        jnp.where(above, fr.cos_h, 1.0),
        jnp.where(above, fr.cos_d, 1.0),
        jnp.where(above, fr.sin_d, 0.0),
        cfg,
    )
    return model._cells_total(ch, hd, fr.cos_i, fr.cos_o, fr.phi, cfg)


@pytest.mark.parametrize(
    "case",
    # Each case compiles values and gradients of both compositions (30-45 s on 2 cores): the slow
    # set. By default brdf's per-pair path is checked against finite differences
    # (tests/test_model.py::test_check_grads_every_parameter), against the grid path
    # (tests/test_grid.py::test_brdf_merl_equals_brdf) and in float32 (below).
    [pytest.param(c, marks=pytest.mark.slow) for c in (0, 1, 2)],
)
def test_per_pair_path_equals_channel_last_composition(case):
    params, cfg = CASES[case]
    wi, wo = _dirs(300, case)
    fast = jax.jit(lambda p, a, b: twoscale.brdf(p, a, b, cfg))
    ref = jax.jit(lambda p, a, b: _channel_last(p, a, b, cfg))
    v, r = np.asarray(fast(params, wi, wo)), np.asarray(ref(params, wi, wo))
    assert v.shape == r.shape
    np.testing.assert_allclose(v, r, rtol=1e-12, atol=0.0)
    assert np.all(v[:5] == 0.0)

    # Gradients in every parameter and in the directions.
    def loss(f):
        return lambda p, a, b: jnp.sum(jnp.log1p(f(p, a, b)))

    g_fast = jax.jit(jax.grad(loss(fast), argnums=(0, 1, 2)))(params, wi, wo)
    g_ref = jax.jit(jax.grad(loss(ref), argnums=(0, 1, 2)))(params, wi, wo)
    for a, b in zip(
        jax.tree_util.tree_leaves(g_fast), jax.tree_util.tree_leaves(g_ref), strict=True
    ):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-12)


def test_per_pair_path_float32_and_shapes():
    cfg = twoscale.ModelConfig()
    wi, wo = _dirs(60, 7)
    p32 = CONDUCTOR.astype(jnp.float32)
    v32 = twoscale.brdf(
        p32, wi.astype(jnp.float32).reshape(3, 20, 3), wo[0].astype(jnp.float32), cfg
    )
    assert v32.dtype == jnp.float32 and v32.shape == (3, 20, 3)
    v64 = twoscale.brdf(CONDUCTOR, wi.reshape(3, 20, 3), wo[0], cfg)
    np.testing.assert_allclose(np.asarray(v32), np.asarray(v64), rtol=2e-4, atol=1e-6)
    lobes = twoscale.lobes(CONDUCTOR, wi, wo, cfg)
    np.testing.assert_allclose(
        sum(np.asarray(x) for x in lobes.values()),
        np.asarray(twoscale.brdf(CONDUCTOR, wi, wo, cfg)),
        rtol=1e-14,
    )


def test_asinh_nonneg():
    x = np.concatenate([[0.0], np.logspace(-300, 300, 4001), -np.logspace(-8, 8, 33)])
    v = np.asarray(asinh_nonneg(jnp.asarray(x)))
    np.testing.assert_allclose(v, np.arcsinh(x), rtol=4e-16, atol=0.0)
    x32 = np.logspace(-30, 30, 1001).astype(np.float32)
    v32 = asinh_nonneg(jnp.asarray(x32))
    assert v32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(v32), np.arcsinh(x32.astype(np.float64)), rtol=3e-7)
    d = jax.vmap(jax.grad(asinh_nonneg))(jnp.asarray([0.0, 1.0, 1e200, -2.0]))
    np.testing.assert_allclose(np.asarray(d), [1.0, 0.5**0.5, 1e-200, 5.0**-0.5], rtol=1e-15)


def test_scaled_channels_equals_slices():
    s = jnp.linspace(0.0, 1.0, 101)
    B = jnp.asarray([0.005, 2.3, 40.0, 2e4])
    c = jnp.float64(2.2)
    v = np.asarray(psd.scaled_channels(s, B, c))
    for j in range(B.size):
        ref = np.asarray(psd.renormalisation_slice(B[j], c).scaled(s))
        np.testing.assert_allclose(v[:, j], ref, rtol=1e-15, atol=0.0)


def test_frame_from_components_and_wrapped_g():
    wi, wo = _dirs(200, 3)
    a = geometry.frame(wi, wo)
    unit = geometry.unit_components
    b = geometry.frame_from_components(unit(tuple(wi.T)), unit(tuple(wo.T)))
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    # frame scales its directions to unit length, and leaves unit ones as they are.
    raw = geometry.frame_from_components(tuple(wi.T), tuple(wo.T))
    for x, y in zip(a, raw, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    scaled = geometry.frame(wi * 3.0, wo * 0.25)
    for x, y in zip(scaled, raw, strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-14, atol=1e-15)
    phi = jnp.concatenate([jnp.zeros(1), jnp.logspace(-12, 0, 50) * jnp.pi])
    li, lo = jnp.full_like(phi, 0.7), jnp.full_like(phi, 0.3)
    g = shadowing.joint_g_from_lambdas(li, lo, phi, wrapped=True)
    ref = shadowing.joint_g_from_lambdas(li, lo, phi)
    np.testing.assert_allclose(np.asarray(g), np.asarray(ref), rtol=1e-15)


def test_spline_components_and_orders():
    rng = np.random.default_rng(0)
    axes = (Axis("a", 0.0, 1.0, 6), Axis("b", -1.0, 2.0, 7))
    table = Table(axes, rng.normal(size=(6, 7, 2)), {}, {})
    xa, xb = jnp.asarray(rng.uniform(-0.1, 1.1, 50)), jnp.asarray(rng.uniform(-1.2, 2.2, 50))
    for order in (3, 1):
        sp = table.spline(jnp.float64, order)
        v = np.asarray(sp(xa, xb))
        assert v.shape == (50, 2)
        for j in range(2):
            one = Table(axes, table.values[..., j], {}, {}).spline(jnp.float64, order)
            np.testing.assert_allclose(v[:, j], np.asarray(one(xa, xb)), rtol=1e-15, atol=1e-15)

"""Tests of twoscale.geometry: frame, half/difference angles, guards, gradients, dtypes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from twoscale import geometry as g


def random_dirs(rng, n, min_cos=0.0):
    """n unit directions, uniform on the upper hemisphere with cos θ > min_cos."""
    cos = rng.uniform(min_cos, 1.0, n)
    phi = rng.uniform(-np.pi, np.pi, n)
    sin = np.sqrt(1.0 - cos**2)
    return np.stack([sin * np.cos(phi), sin * np.sin(phi), cos], -1)


def frame_numpy(wi, wo):
    """Independent NumPy reference: normalised h, dot products, azimuths from arctan2."""
    h = wi + wo
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    cos_d = np.sum(wi * h, -1)
    dphi = np.mod(np.arctan2(wi[:, 1], wi[:, 0]) - np.arctan2(wo[:, 1], wo[:, 0]), 2 * np.pi)
    return dict(
        cos_i=wi[:, 2],
        cos_o=wo[:, 2],
        cos_h=h[:, 2],
        sin_h=np.hypot(h[:, 0], h[:, 1]),
        cos_d=cos_d,
        sin_d=np.linalg.norm(np.cross(wi, h), axis=-1),
        phi=np.minimum(dphi, 2 * np.pi - dphi),
    )


def rot_z(v, a):
    c, s = np.cos(a), np.sin(a)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1], v[..., 2]], -1)


def test_frame_matches_numpy():
    rng = np.random.default_rng(1)
    wi, wo = random_dirs(rng, 2000, 0.01), random_dirs(rng, 2000, 0.01)
    f = g.frame(wi, wo)
    ref = frame_numpy(wi, wo)
    for name, val in ref.items():
        np.testing.assert_allclose(getattr(f, name), val, rtol=0, atol=1e-12, err_msg=name)
    np.testing.assert_allclose(f.cos_d**2 + f.sin_d**2, 1.0, atol=1e-15)
    np.testing.assert_allclose(f.cos_h**2 + f.sin_h**2, 1.0, atol=1e-15)
    assert np.all((f.cos_d >= 0) & (f.cos_d <= 1) & (f.sin_d >= 0) & (f.sin_d <= 1))
    assert np.all((f.phi >= 0) & (f.phi <= np.pi))


def test_frame_reciprocity_and_rotation_invariance():
    rng = np.random.default_rng(2)
    wi, wo = random_dirs(rng, 1000), random_dirs(rng, 1000)
    f = g.frame(wi, wo)
    fs = g.frame(wo, wi)
    for name in ("cos_h", "sin_h", "cos_d", "sin_d", "phi"):
        np.testing.assert_allclose(getattr(fs, name), getattr(f, name), atol=1e-14, err_msg=name)
    np.testing.assert_array_equal(fs.cos_i, f.cos_o)
    a = rng.uniform(-np.pi, np.pi, (1000, 1))[:, 0]
    fr = g.frame(rot_z(wi, a), rot_z(wo, a))
    for name in g.Frame._fields:
        np.testing.assert_allclose(getattr(fr, name), getattr(f, name), atol=1e-13, err_msg=name)


def test_frame_broadcasts_and_jit_equals_eager():
    rng = np.random.default_rng(3)
    wi = random_dirs(rng, 5).reshape(5, 1, 3)
    wo = random_dirs(rng, 7)
    f = g.frame(wi, wo)
    assert all(x.shape == (5, 7) for x in f)
    fj = jax.jit(g.frame)(wi, wo)
    for a, b in zip(f, fj, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-15)


# Degenerate configurations: the guards must give finite values and finite gradients.
Z = np.array([0.0, 0.0, 1.0])
_S = np.sqrt(1.0 - 1e-14)
GRAZ = np.array([_S, 0.0, 1e-7])  # cos θ = 1e-7
GENERIC = np.array([0.3, -0.4, np.sqrt(0.75)])
DEGENERATE = {
    "normal_i": (Z, GENERIC),
    "normal_o": (GENERIC, Z),
    "both_normal": (Z, Z),
    "i_eq_o": (GENERIC, GENERIC),
    "i_eq_o_grazing": (GRAZ, GRAZ),
    "grazing_i": (GRAZ, GENERIC),
    "grazing_both_opposite_azimuth": (GRAZ, GRAZ * np.array([-1.0, 1.0, 1.0])),
    "specular": (GENERIC, GENERIC * np.array([-1.0, -1.0, 1.0])),
    "i_eq_minus_o": (GENERIC, -GENERIC),
    "i_eq_minus_o_grazing": (GRAZ, -GRAZ),
}


def _sum_frame(wi, wo):
    return sum(jnp.sum(x) for x in g.frame(wi, wo))


def _sum_half_diff(wi, wo):
    return sum(jnp.sum(x) for x in g.half_diff_from_dirs(wi, wo))


_GRADS = {
    fun.__name__: jax.jit(jax.grad(fun, argnums=(0, 1))) for fun in (_sum_frame, _sum_half_diff)
}


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_degenerate_values_and_grads_finite(dtype):
    # All cases in one batch: the functions are elementwise, so the gradient of the sum holds the
    # gradient of each case in its own row.
    wi = jnp.asarray(np.stack([v[0] for v in DEGENERATE.values()]), dtype)
    wo = jnp.asarray(np.stack([v[1] for v in DEGENERATE.values()]), dtype)
    cases = np.array(list(DEGENERATE))
    for name, x in zip(g.Frame._fields, g.frame(wi, wo), strict=True):
        assert x.dtype == dtype, name
        assert np.all(np.isfinite(x)), (name, cases[~np.isfinite(x)])
    for x in g.half_diff_from_dirs(wi, wo):
        assert x.dtype == dtype
        assert np.all(np.isfinite(x)), cases[~np.isfinite(x)]
    for fun_name, grad in _GRADS.items():
        gi, go = grad(wi, wo)
        assert gi.dtype == dtype and go.dtype == dtype
        bad = ~(np.isfinite(gi).all(-1) & np.isfinite(go).all(-1))
        assert not bad.any(), (fun_name, cases[bad])


def test_degenerate_values():
    f = g.frame(Z, GENERIC)
    assert f.phi == 0.0 and f.cos_i == 1.0
    f = g.frame(GENERIC, GENERIC)
    assert f.cos_d == 1.0 and f.sin_d == 0.0 and f.phi == 0.0
    np.testing.assert_allclose(f.cos_h, GENERIC[2], rtol=1e-15)
    f = g.frame(GRAZ, GRAZ * np.array([-1.0, 1.0, 1.0]))  # opposite azimuths at grazing
    np.testing.assert_allclose(f.phi, np.pi, rtol=1e-15)
    np.testing.assert_allclose(f.cos_h, 1.0, rtol=1e-15)
    f = g.frame(GENERIC, -GENERIC)  # h undefined: documented h = z
    assert (f.cos_h, f.sin_h, f.cos_d, f.sin_d) == (1.0, 0.0, 0.0, 1.0)


def test_check_grads_interior():
    rng = np.random.default_rng(4)
    wi, wo = random_dirs(rng, 8, 0.1), random_dirs(rng, 8, 0.1)
    # Fields stacked: one check covers all of them (eager, first order: kept cheap).
    check_grads(lambda a, b: jnp.stack(g.frame(a, b)), (wi, wo), order=1, modes=["fwd", "rev"])
    half_diff = lambda a, b: jnp.stack(g.half_diff_from_dirs(a, b))  # noqa: E731
    check_grads(half_diff, (wi, wo), order=1, modes=["rev"])
    th = rng.uniform(0.05, 1.4, 8), rng.uniform(0.05, 1.4, 8), rng.uniform(0.1, 3.0, 8)
    check_grads(lambda *a: jnp.stack(g.dirs_from_half_diff(*a)), th, order=1, modes=["rev"])


def test_float32_preserved():
    rng = np.random.default_rng(5)
    wi, wo = (random_dirs(rng, 10).astype(np.float32) for _ in range(2))
    assert all(x.dtype == jnp.float32 for x in g.frame(wi, wo))
    assert all(x.dtype == jnp.float32 for x in g.half_diff_from_dirs(wi, wo))
    t = np.linspace(0.1, 1.0, 10, dtype=np.float32)
    assert all(x.dtype == jnp.float32 for x in g.dirs_from_half_diff(t, t, t))
    assert g.spherical(t, t).dtype == jnp.float32
    assert g.tan_theta(t).dtype == jnp.float32
    assert g.frame(wi, wo.astype(np.float64)).cos_h.dtype == jnp.float64


def test_tan_theta():
    c = np.array([1.0, 0.9, 0.5, 0.1, 1e-7, 1e-300, 0.0])
    t = g.tan_theta(c)
    np.testing.assert_allclose(t[:5], np.sqrt(1 - c[:5] ** 2) / c[:5], rtol=1e-15)
    eps = np.finfo(np.float64).eps
    np.testing.assert_allclose(t[5:], 1.0 / eps, rtol=1e-12)
    gr = jax.vmap(jax.grad(g.tan_theta))(jnp.asarray(c))
    assert np.all(np.isfinite(gr))
    np.testing.assert_allclose(gr[1:5], -1.0 / (c[1:5] ** 2 * np.sqrt(1 - c[1:5] ** 2)), rtol=1e-9)
    assert np.all(np.isfinite(g.tan_theta(np.float32(0.0))))


def test_spherical():
    rng = np.random.default_rng(6)
    th, ph = rng.uniform(0, np.pi, 50), rng.uniform(-np.pi, np.pi, 50)
    v = np.asarray(g.spherical(th, ph))
    np.testing.assert_allclose(np.linalg.norm(v, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(np.arccos(v[:, 2]), th, atol=1e-7)
    np.testing.assert_allclose(np.arctan2(v[:, 1], v[:, 0]), ph, atol=1e-12)


def test_half_diff_round_trip():
    rng = np.random.default_rng(7)
    th = rng.uniform(0.0, np.pi / 2, 5000)
    td = rng.uniform(0.0, np.pi / 2, 5000)
    pd = rng.uniform(-np.pi, np.pi, 5000)
    wi, wo = g.dirs_from_half_diff(th, td, pd)
    np.testing.assert_allclose(np.linalg.norm(wi, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(wo, axis=-1), 1.0, atol=1e-15)
    # h = (sin θh, 0, cos θh) and o is the mirror of i about h.
    h = np.array(wi + wo)
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    np.testing.assert_allclose(h[:, 1], 0.0, atol=1e-14)
    np.testing.assert_allclose(h[:, 0], np.sin(th), atol=1e-13)
    # cos θ_i, cos θ_o formulas of docs/model.md §7.3.
    a, b = np.cos(th) * np.cos(td), np.sin(th) * np.sin(td) * np.cos(pd)
    np.testing.assert_allclose(wi[:, 2], a - b, atol=1e-15)
    np.testing.assert_allclose(wo[:, 2], a + b, atol=1e-15)
    th2, td2, pd2 = g.half_diff_from_dirs(wi, wo)
    np.testing.assert_allclose(th2, th, atol=1e-13)
    # Directions of any length: the angles of their unit vectors.
    scale = rng.uniform(0.05, 20.0, (2, 5000, 1))
    for a, b in zip(
        g.half_diff_from_dirs(wi * scale[0], wo * scale[1]), (th2, td2, pd2), strict=True
    ):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-12)
    np.testing.assert_allclose(td2, td, atol=1e-13)
    dp = np.angle(np.exp(1j * (np.asarray(pd2) - pd)))
    np.testing.assert_allclose(dp, 0.0, atol=1e-11)
    # Frame agrees with the half/difference angles.
    f = g.frame(wi, wo)
    np.testing.assert_allclose(f.cos_h, np.cos(th), atol=1e-14)
    np.testing.assert_allclose(f.cos_d, np.cos(td), atol=1e-14)
    np.testing.assert_allclose(f.sin_d, np.sin(td), atol=1e-14)


def test_half_diff_rotation_invariant():
    rng = np.random.default_rng(8)
    wi, wo = random_dirs(rng, 500), random_dirs(rng, 500)
    a = rng.uniform(-np.pi, np.pi, 500)
    r0 = g.half_diff_from_dirs(wi, wo)
    r1 = g.half_diff_from_dirs(rot_z(wi, a), rot_z(wo, a))
    for x, y in zip(r0[:2], r1[:2], strict=True):
        np.testing.assert_allclose(x, y, atol=1e-13)
    np.testing.assert_allclose(np.angle(np.exp(1j * (r0[2] - r1[2]))), 0.0, atol=1e-10)

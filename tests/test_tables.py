"""Table core: exact at nodes, 4th-order accuracy, slicing, C² continuity, clamping, file round trip."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twoscale.tables import Axis, Table, read_table, save_table


def _table(n0=21, n1=17):
    axes = (Axis("x", 0.0, 2.0, n0, "x"), Axis("y", -1.0, 1.0, n1, "y"))
    X, Y = np.meshgrid(axes[0].nodes(), axes[1].nodes(), indexing="ij")
    return Table(axes, np.sin(2 * X) * np.exp(Y), {}, {})


def _f(x, y):
    return np.sin(2 * x) * np.exp(y)


def test_exact_at_nodes():
    t = _table()
    X, Y = np.meshgrid(t.axes[0].nodes(), t.axes[1].nodes(), indexing="ij")
    np.testing.assert_allclose(t(X, Y), _f(X, Y), atol=1e-13)


def test_fourth_order_convergence():
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0, 2, 2000), rng.uniform(-1, 1, 2000)
    errs = [float(np.max(np.abs(_table(n, n)(x, y) - _f(x, y)))) for n in (11, 21, 41)]
    rates = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(rates > 3.5), (errs, rates)


def test_slice_equals_full_evaluation():
    t = _table()
    y = np.linspace(-1, 1, 13)
    s = t.spline().slice(0.731)
    np.testing.assert_allclose(s(y), t(np.full_like(y, 0.731), y), atol=1e-14)


def test_gradient_matches_function_and_is_continuous_across_node():
    t = _table(41, 41)
    gx = jax.grad(lambda x: t(x, 0.2))
    np.testing.assert_allclose(float(gx(0.3)), 2 * np.cos(0.6) * np.exp(0.2), rtol=1e-4)
    node = t.axes[0].nodes()[10]
    left, right = float(gx(node - 1e-9)), float(gx(node + 1e-9))
    assert left == pytest.approx(right, rel=1e-6)
    # second derivative is continuous too (C² spline)
    gxx = jax.grad(gx)
    assert float(gxx(node - 1e-9)) == pytest.approx(float(gxx(node + 1e-9)), rel=1e-5)


def test_clamping_outside_domain():
    t = _table()
    assert float(t(5.0, 0.0)) == pytest.approx(float(t(2.0, 0.0)), abs=1e-14)
    g = jax.grad(lambda x: t(x, 0.0))(5.0)
    assert float(g) == 0.0


def test_components_and_dtype():
    axes = (Axis("x", 0.0, 1.0, 8),)
    vals = np.stack([np.linspace(0, 1, 8), np.linspace(1, 2, 8) ** 2], axis=-1)
    t = Table(axes, vals, {}, {})
    out = t(jnp.array([0.0, 0.5], dtype=jnp.float32))
    assert out.shape == (2, 2) and out.dtype == jnp.float32
    np.testing.assert_allclose(out[:, 0], [0.0, 0.5], atol=1e-6)


def test_save_read_round_trip(tmp_path):
    t = _table()
    path = tmp_path / "t.npz"
    save_table(path, t.values, t.axes, name="demo", version=1, generator={"f": "sin(2x)exp(y)"})
    r = read_table(path)
    assert r.meta["name"] == "demo" and r.meta["generator"]["f"] == "sin(2x)exp(y)"
    assert r.axes == t.axes
    np.testing.assert_array_equal(r.values, t.values)


def test_save_rejects_bad_values(tmp_path):
    t = _table()
    with pytest.raises(ValueError, match="non-finite"):
        save_table(tmp_path / "x.npz", t.values * np.nan, t.axes, name="x", version=1)
    with pytest.raises(ValueError, match="shape"):
        save_table(tmp_path / "x.npz", t.values[:-1], t.axes, name="x", version=1)


def test_too_few_nodes():
    with pytest.raises(ValueError, match="at least 4"):
        _ = Table((Axis("x", 0, 1, 3),), np.zeros(3), {}, {}).coeffs

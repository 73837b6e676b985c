"""Parameters and configuration: validation, unconstrained bijection, JSON, config properties."""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twoscale.config import ModelConfig
from twoscale.params import TwoScaleParams, bounds_for
from twoscale.spectral import spectral_wavelengths


def _conductor():
    return TwoScaleParams.conductor(
        0.1, 1.3, [0.2, 0.4, 1.4], [3.5, 2.4, 1.8], sigma_s=0.02, b=1.5, c=2.2
    )


def _plastic(material="plastic"):
    ctor = getattr(TwoScaleParams, material)
    return ctor(0.2, 0.8, [1.5, 1.52, 1.55], [0.5, 0.3, 0.1], sigma_s=0.01, b=3.0, c=1.6, e=0.7)


# ------------------------------------------------------------------------------------ config
def test_config_is_hashable_and_static():
    a, b = ModelConfig(), ModelConfig(wavelengths=[0.645, 0.526, 0.444])
    assert a == b and hash(a) == hash(b)
    f = jax.jit(lambda x, cfg: x * cfg.n_channels, static_argnums=1)
    assert float(f(2.0, a)) == 6.0


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"material": "metal"}, "material"),
        ({"q_mode": "4F"}, "q_mode"),
        ({"shadowing": "none"}, "shadowing"),
        ({"path": "fast"}, "path"),
        ({"spectral_output": "xyz"}, "spectral_output"),
        ({"specular": 1}, "specular"),
        ({"wavelengths": (0.5, 3.0)}, "wavelengths"),
        ({"wavelengths": (0.3, 0.5)}, r"\[0.35, 2\]"),
        ({"wavelengths": (0.6, 0.5, 0.4, 0.36)}, "increasing"),
        ({"wavelengths": 0.5}, "wavelengths"),
        ({"specular": False, "diffraction": False}, "switched off"),
        ({"material": "plastic", "specular": False, "diffraction": False, "diffuse": False}, "off"),
    ],
)
def test_config_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ModelConfig(**kwargs)


def test_config_param_names_and_channels():
    assert ModelConfig().param_names == ("beta", "p", "sigma_s", "b", "c", "eta", "k")
    assert ModelConfig(diffraction=False).param_names == ("beta", "p", "eta", "k")
    cfg = ModelConfig(material="plastic", apparatus=True)
    assert cfg.param_names == ("beta", "p", "sigma_s", "b", "c", "eta", "rho_d", "e")
    knee = ModelConfig(material="plastic", apparatus=True, apparatus_knee=True)
    assert knee.param_names == ("beta", "p", "sigma_s", "b", "c", "eta", "rho_d", "e", "m")
    assert "m" not in ModelConfig(apparatus_knee=True).param_names  # no apparatus: no factor
    with pytest.raises(ValueError, match="apparatus_knee"):
        ModelConfig(apparatus=True, apparatus_knee=1)
    assert ModelConfig(material="subsurface", diffuse=False).param_names[-1] == "eta"
    assert ModelConfig(material="conductor", diffuse=True).has_diffuse is False
    diffuse_only = ModelConfig(material="plastic", specular=False, diffraction=False)
    assert diffuse_only.param_names == ("eta", "rho_d")
    wl = tuple(spectral_wavelengths(8))
    assert ModelConfig(wavelengths=wl).n_channels == 3
    assert ModelConfig(wavelengths=wl, spectral_output="spectrum").n_channels == 8
    assert ModelConfig().n_channels == 3 and not ModelConfig().is_spectral


# ------------------------------------------------------------------------------------ params
def test_constructors_and_pytree():
    p = _conductor()
    assert p.material == "conductor" and p.rho_d is None and p.e is None
    assert len(jax.tree_util.tree_leaves(p)) == 7
    q = _plastic("subsurface")
    assert q.material == "subsurface" and q.k is None
    assert q.replace(e=None).e is None
    with pytest.raises(ValueError, match="no field"):
        q.replace(gamma=1.0)
    assert p.astype(jnp.float32).beta.dtype == jnp.float32


def test_validate_accepts_good_params():
    _conductor().validate(ModelConfig())
    _plastic().validate(ModelConfig(material="plastic", apparatus=True))
    _plastic("subsurface").validate(ModelConfig(material="subsurface"))


@pytest.mark.parametrize(
    "field,value,text",
    [
        ("beta", 0.0, r"beta = 0.0 is outside the valid range \[0.001, 1\]"),
        ("beta", 2.0, "beta"),
        ("p", 0.1, r"p = 0.1 .*\[0.2, 5\]"),
        ("sigma_s", -0.01, "sigma_s"),
        ("sigma_s", 1.5, r"\[0, 1\]"),
        ("b", 1e3, r"b = 1000.0 .*\[0.01, 350\]"),
        ("c", 1.0, r"c = 1.0 .*\[1.01, 5\]"),
        ("eta", [0.2, 0.4, 7.0], r"eta = \[0.2, 0.4, 7.0\] .*\[0.01, 6\].*conductor"),
        ("k", [3.5, -1.0, 1.8], "k"),
        ("beta", float("nan"), "beta = nan"),
    ],
)
def test_validate_errors_name_field_value_range(field, value, text):
    p = _conductor().replace(**{field: value})
    with pytest.raises(ValueError, match=text):
        p.validate()


def test_validate_dielectric_ranges_and_structure():
    with pytest.raises(ValueError, match=r"eta = \[0.9.*\[1, 4\].*plastic"):
        _plastic().replace(eta=[0.9, 1.5, 1.5]).validate()
    with pytest.raises(ValueError, match="rho_d"):
        _plastic().replace(rho_d=[0.5, 1.2, 0.1]).validate()
    with pytest.raises(ValueError, match="needs parameter"):
        _plastic().replace(sigma_s=None).validate(ModelConfig(material="plastic"))
    with pytest.raises(ValueError, match="material"):
        _plastic().validate(ModelConfig(material="conductor"))
    with pytest.raises(ValueError, match="scalar"):
        _conductor().replace(beta=[0.1, 0.2]).validate()
    with pytest.raises(ValueError, match="shape"):
        _conductor().replace(eta=[0.2, 0.4]).validate(ModelConfig())
    # Without the nano-scale parameters, a configuration without diffraction is fine.
    no_nano = TwoScaleParams.conductor(0.1, 1.0, 0.5, 2.0)
    no_nano.validate(ModelConfig(diffraction=False))


def test_for_config_drops_unused_and_upsamples():
    p = _plastic()
    q = p.for_config(ModelConfig(material="plastic", diffraction=False))
    assert q.sigma_s is None and q.b is None and q.c is None and q.e is None
    assert q.rho_d is not None
    wl = tuple(spectral_wavelengths(10))
    s = p.for_config(ModelConfig(material="plastic", wavelengths=wl))
    assert s.eta.shape == (10,) and s.rho_d.shape == (10,)
    # Exact at the RGB wavelengths: a spectral config containing them reproduces the RGB values.
    # (With exactly 3 spectral wavelengths, 3 values are taken as one per wavelength.)
    t = p.for_config(ModelConfig(material="plastic", wavelengths=(0.444, 0.5, 0.526, 0.645)))
    np.testing.assert_allclose(np.asarray(t.eta)[[0, 2, 3]], np.asarray(p.eta)[::-1], rtol=1e-12)
    with pytest.raises(ValueError, match="needs parameter"):
        TwoScaleParams.conductor(0.1, 1.0, 0.5, 2.0).for_config(ModelConfig())


# ------------------------------------------------------------------------------------ bijection
@pytest.mark.parametrize("make", [_conductor, _plastic])
def test_unconstrained_round_trip(make):
    p = make()
    u = p.to_unconstrained()
    assert u.material == p.material
    back = TwoScaleParams.from_unconstrained(u)
    for name, value in p.fields().items():
        np.testing.assert_allclose(getattr(back, name), value, rtol=1e-10, err_msg=name)


def test_bounds_map_to_finite_unconstrained_values():
    p = TwoScaleParams.conductor(1e-3, 5.0, [0.01, 6.0, 1.0], [0.0, 10.0, 1.0], 0.0, 350.0, 1.01)
    u = p.to_unconstrained()
    for name, value in u.fields().items():
        assert np.all(np.isfinite(value)) and np.all(np.abs(value) <= 40.0), name
    back = TwoScaleParams.from_unconstrained(u)
    back.validate()
    assert float(back.sigma_s) < 1e-17  # σ_s = 0 is a limit; its image gives A_s = 1 exactly


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("material", ["conductor", "plastic", "subsurface"])
def test_random_unconstrained_vectors_map_into_domain(dtype, material):
    rng = np.random.default_rng(0)
    template = _conductor() if material == "conductor" else _plastic(material)
    template = template.replace(e=1.0)
    for scale in (1.0, 10.0, 1e3):
        leaves, treedef = jax.tree_util.tree_flatten(template)
        rand = [jnp.asarray(scale * rng.standard_normal(np.shape(x)), dtype) for x in leaves]
        u = jax.tree_util.tree_unflatten(treedef, rand)
        p = TwoScaleParams.from_unconstrained(u)
        p.validate()
        assert all(x.dtype == dtype for x in jax.tree_util.tree_leaves(p))


def test_from_unconstrained_is_differentiable_with_partition():
    p = _conductor()
    u = p.to_unconstrained()
    fixed = jax.tree_util.tree_map(lambda _: False, u)
    spec = eqx.tree_at(lambda t: (t.beta, t.eta), fixed, (True, True))
    free, static = eqx.partition(u, spec)

    def f(free):
        q = TwoScaleParams.from_unconstrained(eqx.combine(free, static))
        return q.beta + jnp.sum(q.eta)

    g = jax.grad(f)(free)
    assert np.isfinite(float(g.beta)) and float(g.beta) > 0
    assert g.k is None and np.all(np.asarray(g.eta) > 0)


def test_bound_maps_are_monotone():
    for name in ("beta", "p", "sigma_s", "b", "c", "k", "rho_d", "e"):
        bnd = bounds_for(name, "conductor")
        x = np.asarray(bnd.forward(jnp.linspace(-30.0, 30.0, 201)))
        assert np.all(np.diff(x) >= 0) and x[0] >= bnd.lo and x[-1] <= bnd.hi, name


# ------------------------------------------------------------------------------------ JSON
@pytest.mark.parametrize("make", [_conductor, _plastic])
def test_dict_round_trip_through_json(make):
    p = make()
    d = json.loads(json.dumps(p.to_dict()))
    q = TwoScaleParams.from_dict(d)
    assert q.material == p.material
    assert q.fields().keys() == p.fields().keys()
    for name, value in p.fields().items():
        np.testing.assert_array_equal(np.asarray(getattr(q, name)), np.asarray(value))
    with pytest.raises(ValueError, match="unknown key"):
        TwoScaleParams.from_dict({**d, "gamma": 1.0})


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_bound_maps_same_on_host_and_traced(dtype):
    """Concrete values are mapped in NumPy (one host computation, not a dispatch per JAX
    operation), traced ones in JAX: the same values, the input's dtype, bounds to ±40."""
    for name in ("beta", "p", "sigma_s", "b", "c", "k", "rho_d", "e"):
        bound = bounds_for(name, "conductor" if name == "k" else "plastic")
        x = np.array([bound.lo, bound.lo + 1e-3 * (bound.hi - bound.lo), bound.hi, bound.hi * 2])
        x = x.astype(dtype)
        u_host, u_traced = bound.inverse(x), jax.jit(bound.inverse)(jnp.asarray(x))
        assert u_host.dtype == u_traced.dtype == dtype
        # float32 on a bound: NumPy's and XLA's log may round t to 1 or just below it (u = 40
        # or ≈ 16.6, both σ(u) = 1 in float32): compared inside the range only.
        inside = slice(None) if dtype == np.float64 else slice(1, 2)
        tol = 1e-6 if dtype == np.float32 else 1e-14
        np.testing.assert_allclose(u_host[inside], u_traced[inside], rtol=tol)
        assert float(u_host[0]) == -40.0 and float(u_host[-1]) == 40.0
        assert np.all(np.abs(np.asarray(u_traced)[[0, 2, 3]]) > 16.0)
        v_host, v_traced = bound.forward(u_host), jax.jit(bound.forward)(u_traced)
        assert v_host.dtype == v_traced.dtype == dtype
        np.testing.assert_allclose(v_host, v_traced, rtol=tol, atol=tol * bound.hi)
    assert bounds_for("beta", "conductor").inverse(0.1).dtype == jnp.asarray(0.1).dtype

"""The plastic's Lambertian body (``ModelConfig(diffuse_fresnel=False)``, docs/model.md §3.9)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import twoscale
from twoscale import ModelConfig, TwoScaleParams

#: Compiled with most XLA optimisations off (tests/conftest.py): this module's time is compilation.
COMPILE_QUICKLY = True

LAMBERT = ModelConfig(material="plastic", diffuse_fresnel=False)
FRESNEL = ModelConfig(material="plastic")
PARAMS = TwoScaleParams.plastic(
    0.12, 1.3, (1.5, 1.45, 1.4), (0.25, 0.4, 0.6), sigma_s=0.02, b=1.2, c=2.0
)
WI = jnp.array([[0.3, 0.0, 0.954], [0.0, 0.8, 0.6], [0.99, 0.0, 0.141]])
WO = jnp.array([[-0.3, 0.0, 0.954], [0.5, -0.2, 0.843], [-0.7, 0.1, 0.707]])


def test_lambertian_body_is_rho_over_pi_and_leaves_the_other_lobes_alone():
    lam = twoscale.lobes(PARAMS, WI, WO, LAMBERT)
    ref = twoscale.lobes(PARAMS, WI, WO, FRESNEL)
    rho = np.asarray(PARAMS.rho_d)
    np.testing.assert_allclose(np.asarray(lam["diffuse"]), np.broadcast_to(rho / np.pi, (3, 3)))
    for name in ("specular", "diffraction"):  # the same code in two compiled programs
        np.testing.assert_allclose(np.asarray(lam[name]), np.asarray(ref[name]), rtol=1e-11)
    # The reference layer darkens towards grazing; the Lambertian body does not.
    assert np.all(np.asarray(ref["diffuse"])[2] < np.asarray(lam["diffuse"])[2])


def test_lambertian_body_gradients_and_grid_path():
    def diffuse_sum(p):
        return twoscale.lobes(p, WI, WO, LAMBERT)["diffuse"].sum()

    g = jax.grad(diffuse_sum)(PARAMS)
    np.testing.assert_allclose(np.asarray(g.rho_d), np.full(3, 3 / np.pi))
    np.testing.assert_array_equal(np.asarray(g.eta), 0.0)  # η no longer reaches the body
    grid = np.asarray(twoscale.brdf_merl(PARAMS, LAMBERT))
    wi, wo = twoscale.merl.grid_directions()
    idx = (np.array([3, 40, 85]), np.array([10, 60, 80]), np.array([0, 50, 170]))
    np.testing.assert_allclose(
        grid[idx], np.asarray(twoscale.brdf(PARAMS, wi[idx], wo[idx], LAMBERT)), rtol=1e-9
    )


def test_lambertian_body_float32_stays_float32():
    p32 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), PARAMS)
    out = twoscale.brdf(p32, WI.astype(jnp.float32), WO.astype(jnp.float32), LAMBERT)
    assert out.dtype == jnp.float32 and bool(jnp.all(jnp.isfinite(out)))


def test_diffuse_fresnel_config():
    with pytest.raises(ValueError, match="diffuse_fresnel"):
        ModelConfig(material="plastic", diffuse_fresnel="no")
    with pytest.raises(ValueError, match="diffuse_eta2"):
        ModelConfig(material="plastic", diffuse_fresnel=False, diffuse_eta2=True)
    # Ignored for the other materials (like `diffuse` for conductors): a conductor is unchanged.
    metal = TwoScaleParams.conductor(0.1, 1.0, (0.3, 0.5, 1.2), (3.5, 2.6, 2.0), 0.02, 1.0, 2.0)
    np.testing.assert_array_equal(
        np.asarray(twoscale.brdf(metal, WI, WO, ModelConfig(diffuse_fresnel=False))),
        np.asarray(twoscale.brdf(metal, WI, WO, ModelConfig())),
    )
    # The fit record keeps the switch.
    from twoscale.fit.adapters import config_from_dict, config_to_dict

    assert config_from_dict(config_to_dict(LAMBERT)) == LAMBERT


def test_conductor_floor_adds_rho_over_pi():
    """``ModelConfig(conductor_floor=True)``: the conductor's lobes plus a Lambertian floor
    ``ρ_d/π`` on every path (per direction and on the MERL grid), gradient ``1/π`` per
    direction and channel; the flag means nothing for a dielectric (normalised to False)."""
    bare_cfg = ModelConfig(material="conductor")
    floor_cfg = ModelConfig(material="conductor", conductor_floor=True)
    assert floor_cfg.has_diffuse and "rho_d" in floor_cfg.param_names
    assert "rho_d" not in bare_cfg.param_names
    assert ModelConfig(material="plastic", conductor_floor=True).conductor_floor is False
    bare = TwoScaleParams.conductor(0.12, 1.3, (0.3, 0.5, 1.2), (3.0, 2.4, 1.9), 0.02, 1.2, 2.0)
    rho = np.array([0.004, 0.006, 0.01])
    floor = bare.replace(rho_d=rho)
    with_floor = np.asarray(twoscale.brdf(floor, WI, WO, floor_cfg))
    without = np.asarray(twoscale.brdf(bare, WI, WO, bare_cfg))
    np.testing.assert_allclose(
        with_floor - without, np.broadcast_to(rho / np.pi, (3, 3)), atol=1e-15
    )
    grid = np.asarray(twoscale.brdf_merl(floor, floor_cfg)) - np.asarray(
        twoscale.brdf_merl(bare, bare_cfg)
    )
    above = np.asarray(twoscale.brdf_merl(bare, bare_cfg))[..., 0] > 0
    np.testing.assert_allclose(
        grid[above], np.broadcast_to(rho / np.pi, grid[above].shape), atol=1e-12
    )
    g = jax.grad(lambda p: twoscale.brdf(p, WI, WO, floor_cfg).sum())(floor)
    np.testing.assert_allclose(np.asarray(g.rho_d), np.full(3, 3 / np.pi))

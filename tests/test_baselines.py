"""Cook-Torrance + Lambert baselines: normalisation, Smith Λ, reciprocity, reparametrisation."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate, special

from twoscale.baselines import (
    ALPHA_RANGE,
    CookTorranceConfig,
    CookTorranceParams,
    _lambda_beckmann,
    _lambda_ggx,
    cook_torrance,
)


def _dir(theta, phi):
    return np.array(
        [math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)]
    )


@pytest.mark.parametrize("dist", ["ggx", "beckmann"])
@pytest.mark.parametrize("alpha", [0.05, 0.3, 0.8])
def test_ndf_normalised(dist, alpha):
    """∫ D(m) cos θ_m dω_m = 1, D recovered from the BRDF at the mirror configuration."""

    # D(θ) of each distribution, written out independently of the module.
    def d(theta):
        t2 = math.tan(theta) ** 2
        c4 = math.cos(theta) ** 4
        if dist == "ggx":
            return alpha**2 / (math.pi * c4 * (alpha**2 + t2) ** 2)
        return math.exp(-t2 / alpha**2) / (math.pi * alpha**2 * c4)

    val, _ = integrate.quad(
        lambda t: d(t) * math.cos(t) * math.sin(t) * 2 * math.pi, 0, math.pi / 2, limit=200
    )
    assert val == pytest.approx(1.0, rel=1e-6)
    # The module's lobe at normal incidence/exit equals F0 D(0)/4 (G = 1, Schlick F = F0).
    p = CookTorranceParams(alpha, [0.5, 0.5, 0.5], [0.0, 0.0, 0.0])
    n = jnp.array([0.0, 0.0, 1.0])
    rho = cook_torrance(p, n, n, CookTorranceConfig(dist))
    np.testing.assert_allclose(rho, 0.5 * d(0.0) / 4, rtol=1e-12)


@pytest.mark.parametrize("alpha", [0.1, 0.5])
@pytest.mark.parametrize("theta", [0.2, 0.8, 1.3])
def test_smith_lambda_matches_integral(alpha, theta):
    """Λ(θ) = ∫ (tan-slope projection) against the slope distributions, by quadrature."""
    tan2 = math.tan(theta) ** 2
    mu = 1.0 / (alpha * math.tan(theta))
    beck = 0.5 * (special.erf(mu) - 1) + math.exp(-mu * mu) / (2 * mu * math.sqrt(math.pi))
    assert float(_lambda_beckmann(jnp.float64(tan2), alpha)) == pytest.approx(beck, rel=1e-10)
    ggx = 0.5 * (-1 + math.sqrt(1 + alpha**2 * tan2))
    assert float(_lambda_ggx(jnp.float64(tan2), alpha)) == pytest.approx(ggx, rel=1e-12)
    # Independent check of the Beckmann Λ: Λ = ∫_{cot θ}^{∞} (q tanθ − 1) P(q) dq, P the 1-D
    # marginal slope density N(0, α²/2).
    s = alpha / math.sqrt(2)

    def integrand(q):
        return (
            (q * math.tan(theta) - 1)
            * math.exp(-q * q / (2 * s * s))
            / (s * math.sqrt(2 * math.pi))
        )

    val, _ = integrate.quad(integrand, 1 / math.tan(theta), np.inf)
    assert val == pytest.approx(beck, rel=1e-7, abs=1e-14)


@pytest.mark.parametrize("dist", ["ggx", "beckmann"])
def test_reciprocal_and_zero_below_horizon(dist):
    p = CookTorranceParams(0.3, [0.9, 0.6, 0.3], [0.1, 0.2, 0.3])
    cfg = CookTorranceConfig(dist)
    rng = np.random.default_rng(0)
    th = rng.uniform(0, 1.5, (2, 50))
    ph = rng.uniform(0, 2 * np.pi, (2, 50))
    wi = np.stack([_dir(a, b) for a, b in zip(th[0], ph[0], strict=True)])
    wo = np.stack([_dir(a, b) for a, b in zip(th[1], ph[1], strict=True)])
    np.testing.assert_allclose(
        cook_torrance(p, wi, wo, cfg), cook_torrance(p, wo, wi, cfg), rtol=1e-12
    )
    below = wo * np.array([1, 1, -1])
    assert np.all(np.asarray(cook_torrance(p, wi, below, cfg)) == 0.0)
    # Directions of any length give their unit vectors' values; a zero vector gives 0.
    scale = rng.uniform(0.05, 20.0, (2, 50, 1))
    np.testing.assert_allclose(
        cook_torrance(p, wi * scale[0], wo * scale[1], cfg),
        cook_torrance(p, wi, wo, cfg),
        rtol=1e-12,
    )
    assert np.all(np.asarray(cook_torrance(p, 0.0 * wi, wo, cfg)) == 0.0)


def test_unconstrained_roundtrip_and_range():
    p = CookTorranceParams(0.2, [0.9, 0.5, 0.05], [0.3, 0.01, 0.7])
    u = p.to_unconstrained()
    q = CookTorranceParams.from_unconstrained(u)
    for a, b in zip(jax.tree_util.tree_leaves(p), jax.tree_util.tree_leaves(q), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12)
    big = jax.tree_util.tree_map(lambda x: jnp.full_like(x, 50.0), u)
    small = jax.tree_util.tree_map(lambda x: jnp.full_like(x, -50.0), u)
    for extreme in (big, small):
        e = CookTorranceParams.from_unconstrained(extreme)
        assert ALPHA_RANGE[0] <= float(e.alpha) <= ALPHA_RANGE[1]
        assert np.all((np.asarray(e.f0) >= 0) & (np.asarray(e.f0) <= 1))


def test_apparatus_knee_parameter():
    """``apparatus_knee`` adds the knee exponent m (range [1, 20], log-scaled) next to e; m = 2
    gives the paper's factor, which the plain ``apparatus`` switch uses; m round-trips through
    the unconstrained map and the record."""
    from twoscale.baselines import M_BOUND

    plain, knee = (
        CookTorranceConfig(apparatus=True),
        CookTorranceConfig(apparatus=True, apparatus_knee=True),
    )
    assert plain.param_names == ("alpha", "f0", "rho_d", "e")
    assert knee.param_names == ("alpha", "f0", "rho_d", "e", "m")
    assert CookTorranceConfig(apparatus_knee=True).param_names == ("alpha", "f0", "rho_d")
    assert CookTorranceConfig.from_dict(knee.to_dict()) == knee
    assert CookTorranceConfig.from_dict({"distribution": "ggx", "apparatus": True}) == plain
    wi = jnp.asarray([np.sin(1.4), 0.0, np.cos(1.4)])
    wo = jnp.asarray([-np.sin(1.38), 0.05, np.cos(1.38)])
    p2 = CookTorranceParams(0.2, 0.5, 0.1, e=0.9, m=2.0)
    np.testing.assert_allclose(
        cook_torrance(p2, wi, wo, knee),
        cook_torrance(CookTorranceParams(0.2, 0.5, 0.1, e=0.9), wi, wo, plain),
        rtol=1e-12,
    )
    p8 = CookTorranceParams(0.2, 0.5, 0.1, e=0.9, m=8.0)
    assert np.all(
        np.asarray(cook_torrance(p8, wi, wo, knee)) > np.asarray(cook_torrance(p2, wi, wo, knee))
    )
    with pytest.raises(ValueError, match="needs the parameter m"):
        cook_torrance(CookTorranceParams(0.2, 0.5, 0.1, e=0.9), wi, wo, knee)
    q = CookTorranceParams.from_unconstrained(p8.to_unconstrained())
    np.testing.assert_allclose(q.m, 8.0, rtol=1e-12)
    assert CookTorranceParams.from_dict(p8.to_dict()).to_dict() == p8.to_dict()
    for u in (-60.0, 60.0):
        far = CookTorranceParams(p8.alpha, p8.f0, p8.rho_d, p8.e, jnp.asarray(u))
        m = float(CookTorranceParams.from_unconstrained(far).m)
        assert M_BOUND.lo <= m <= M_BOUND.hi


def test_gradients_finite_at_normal_incidence():
    cfg = CookTorranceConfig("beckmann")
    n = jnp.array([0.0, 0.0, 1.0])

    def f(u):
        return jnp.sum(cook_torrance(CookTorranceParams.from_unconstrained(u), n, n, cfg))

    u = CookTorranceParams(0.2, 0.5, 0.5).to_unconstrained()
    g = jax.grad(f)(u)
    assert all(np.all(np.isfinite(x)) for x in jax.tree_util.tree_leaves(g))


def test_dict_roundtrip_and_config_validation():
    p = CookTorranceParams(0.2, [0.9, 0.5, 0.05], [0.3, 0.01, 0.7])
    q = CookTorranceParams.from_dict(p.to_dict())
    assert q.to_dict() == p.to_dict()
    with pytest.raises(ValueError, match="distribution"):
        CookTorranceConfig("phong")


def test_apparatus_angles_theta_d():
    """``apparatus_angles="theta_d"``: the specular term carries ``L(θ_d)²`` (θ_d from the half
    vector) instead of ``L(θ_i) L(θ_o)``; the body is unchanged; the switch round-trips and a
    record without it reads as the paper's form."""
    from twoscale.model import apparatus_factor

    p = CookTorranceParams(0.3, [0.9, 0.5, 0.05], [0.2, 0.1, 0.05], e=0.9, m=3.0)
    wi, wo = _dir(1.2, 0.0), _dir(1.45, 0.3)  # rough lobe, forward and grazing
    bare = CookTorranceParams(0.3, [0.9, 0.5, 0.05], [0.2, 0.1, 0.05])
    body = np.asarray(p.rho_d) / math.pi
    spec = np.asarray(cook_torrance(bare, wi, wo)) - body
    h = (np.asarray(wi) + np.asarray(wo)) / np.linalg.norm(np.asarray(wi) + np.asarray(wo))
    cd = float(np.dot(np.asarray(wi), h))
    for angles, fall in (
        (
            "theta_io",
            apparatus_factor(math.cos(1.2), 0.9, 3.0) * apparatus_factor(math.cos(1.45), 0.9, 3.0),
        ),
        ("theta_d", apparatus_factor(cd, 0.9, 3.0) ** 2),
    ):
        cfg = CookTorranceConfig(apparatus=True, apparatus_knee=True, apparatus_angles=angles)
        got = np.asarray(cook_torrance(p, wi, wo, cfg))
        np.testing.assert_allclose(got, body + spec * float(fall), rtol=1e-10)
        assert CookTorranceConfig.from_dict(cfg.to_dict()) == cfg
    assert CookTorranceConfig.from_dict({"distribution": "ggx"}).apparatus_angles == "theta_io"
    with pytest.raises(ValueError, match="apparatus_angles"):
        CookTorranceConfig(apparatus_angles="theta_h")


@pytest.mark.parametrize("dist", ["ggx", "beckmann"])
def test_uncorrelated_shadowing(dist):
    """``shadowing="uncorrelated"``: the specular term carries ``G1(i) G1(o)`` instead of the
    height-correlated ``1/(1 + Λ_i + Λ_o)``; the body is unchanged; the switch round-trips."""
    p = CookTorranceParams(0.3, [0.9, 0.5, 0.05], [0.0, 0.0, 0.0])
    wi, wo = _dir(1.45, 0.0), _dir(1.5, math.pi)  # both near grazing: G far from 1
    cor = np.asarray(cook_torrance(p, wi, wo, CookTorranceConfig(dist)))
    unc_cfg = CookTorranceConfig(dist, shadowing="uncorrelated")
    unc = np.asarray(cook_torrance(p, wi, wo, unc_cfg))
    lam = _lambda_ggx if dist == "ggx" else _lambda_beckmann
    li, lo = (float(lam(math.tan(t) ** 2, 0.3)) for t in (1.45, 1.5))
    assert li > 0.3 and lo > 0.3
    np.testing.assert_allclose(unc / cor, (1 + li + lo) / ((1 + li) * (1 + lo)), rtol=1e-12)
    assert CookTorranceConfig.from_dict(unc_cfg.to_dict()) == unc_cfg
    assert unc_cfg.to_dict()["shadowing"] == "uncorrelated"
    assert CookTorranceConfig.from_dict({"distribution": dist}).shadowing == "correlated"
    with pytest.raises(ValueError, match="shadowing"):
        CookTorranceConfig(dist, shadowing="joint")

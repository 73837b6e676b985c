"""Importance sampling (twoscale.sample / twoscale.pdf) and the albedo table.

Deterministic (fixed PRNG keys). The χ² tests bin ``sample``'s directions on a (cos θ_o, φ_o)
grid and compare the counts with the integral of ``pdf`` over each bin (adaptive Gauss-Legendre
cubature), with one more bin for the samples that carry nothing (``pdf = 0``, below the horizon),
whose expected count is ``n (1 − ∫pdf)``; bins with fewer than 5 expected samples are pooled.
Compilations are shared: every test uses the same two configurations and array shapes.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import chi2

import twoscale
from twoscale._numerics import gauss_legendre
from twoscale.config import ModelConfig
from twoscale.params import TwoScaleParams

CONDUCTOR = ModelConfig()
PLASTIC = ModelConfig(material="plastic")
LUM = np.array([0.2126, 0.7152, 0.0722])
N_SAMPLES = 40_000
N_COS, N_PHI = 32, 32
CHUNK = 1 << 15  # directions per pdf call on the cubature nodes (one compiled shape)


def _conductor(**kw):
    base = dict(eta=(0.2, 0.5, 1.4), k=(3.5, 2.5, 1.9), sigma_s=0.01, b=1.5, c=2.2)
    base.update(kw)
    return TwoScaleParams.conductor(**base)


def _plastic(**kw):
    base = dict(beta=0.2, p=1.0, eta=(1.5, 1.5, 1.5), rho_d=(0.6, 0.4, 0.2), sigma_s=0.01)
    base.update(dict(b=1.5, c=2.2), **kw)
    return TwoScaleParams.plastic(**base)


MATERIALS = {
    "rough": (_conductor(beta=0.5, p=1.0, sigma_s=0.003, b=1.0), CONDUCTOR),
    "smooth": (_conductor(beta=0.03, p=2.0), CONDUCTOR),
    "p0.2": (_conductor(beta=0.02, p=0.2), CONDUCTOR),
    "p5": (_conductor(beta=0.2, p=5.0), CONDUCTOR),
    "strong-diffraction": (_conductor(beta=0.05, p=1.0, sigma_s=0.1, b=3.0, c=1.5), CONDUCTOR),
    "weak-diffraction": (_conductor(beta=0.1, p=1.5, sigma_s=0.002, b=8.0, c=3.0), CONDUCTOR),
    "plastic": (_plastic(), PLASTIC),
}


def _wi(theta_deg):
    t = math.radians(theta_deg)
    return jnp.asarray([math.sin(t), 0.0, math.cos(t)])


def _uniforms(seed, n=N_SAMPLES):
    return jax.random.uniform(jax.random.PRNGKey(seed), (n, 3), dtype=jnp.float64)


def _draw(name, theta_deg, seed=0):
    params, cfg = MATERIALS[name]
    wi = _wi(theta_deg)
    wo, pdf = twoscale.sample(params, wi, _uniforms(seed), cfg)
    return params, cfg, wi, np.asarray(wo), np.asarray(pdf)


# ------------------------------------------------------------------------------ cubature of pdf
def _pdf_at(params, cfg, wi, cos_o, phi_o):
    s = np.sqrt(np.clip(1.0 - cos_o * cos_o, 0.0, None))
    wo = np.stack([s * np.cos(phi_o), s * np.sin(phi_o), cos_o], -1)
    out = np.empty(len(cos_o))
    for k in range(0, len(cos_o), CHUNK):
        blk = wo[k : k + CHUNK]
        pad = CHUNK - len(blk)
        blk = np.concatenate([blk, np.tile([[0.0, 0.0, 1.0]], (pad, 1))])
        out[k : k + CHUNK] = np.asarray(twoscale.pdf(params, wi, jnp.asarray(blk), cfg))[
            : CHUNK - pad
        ]
    return out


def _cell_integrals(params, cfg, wi, cells, g=4):
    """Gauss-Legendre g×g on each (cos, φ) cell and on its 2×2 sub-cells: (coarse, fine)."""
    x, w = gauss_legendre(g)
    c0, c1, p0, p1 = cells.T
    cm, pm = 0.5 * (c0 + c1), 0.5 * (p0 + p1)
    boxes = [
        (c0, c1, p0, p1),
        (c0, cm, p0, pm),
        (cm, c1, p0, pm),
        (c0, cm, pm, p1),
        (cm, c1, pm, p1),
    ]
    nodes_c, nodes_p, weights = [], [], []
    for a0, a1, b0, b1 in boxes:
        cc = a0[:, None, None] + (a1 - a0)[:, None, None] * x[None, :, None]
        pp = b0[:, None, None] + (b1 - b0)[:, None, None] * x[None, None, :]
        cc, pp = np.broadcast_arrays(cc, pp)
        nodes_c.append(cc.ravel())
        nodes_p.append(pp.ravel())
        weights.append(((a1 - a0) * (b1 - b0))[:, None, None] * np.outer(w, w)[None])
    d = _pdf_at(params, cfg, wi, np.concatenate(nodes_c), np.concatenate(nodes_p))
    m = len(c0) * g * g
    vals = [
        np.sum(d[k * m : (k + 1) * m].reshape(-1, g, g) * weights[k], axis=(1, 2)) for k in range(5)
    ]
    return vals[0], vals[1] + vals[2] + vals[3] + vals[4]


def _bin_probabilities(params, cfg, wi, n_samples, max_level=10, mirror_width=1e-3):
    """∫ pdf over each (cos θ_o, φ_o) bin, refined until the error is ≪ √(expected count).

    A cell is split in four while its 4×4 rule and the rule on its 2×2 sub-cells differ by more
    than 0.05 √max(1, expected). The cells on the mirror plane (φ = ±π: the specular lobe's
    azimuth for ``wi`` at φ = 0) are first split in φ down to ``mirror_width``: at grazing
    incidence the lobe is compressed in φ to a few 1e-3 rad, and a coarse cell's nodes could
    all miss it (both rules would then agree on a wrong value).
    """
    ce, pe = np.linspace(0.0, 1.0, N_COS + 1), np.linspace(-np.pi, np.pi, N_PHI + 1)
    ic, ip = np.meshgrid(np.arange(N_COS), np.arange(N_PHI), indexing="ij")
    idx = (ic * N_PHI + ip).ravel()
    cells = np.stack([ce[ic].ravel(), ce[ic + 1].ravel(), pe[ip].ravel(), pe[ip + 1].ravel()], -1)
    prob = np.zeros(N_COS * N_PHI)
    for level in range(max_level + 1):
        coarse, fine = _cell_integrals(params, cfg, wi, cells)
        ok = np.abs(fine - coarse) * n_samples <= 0.05 * np.sqrt(np.maximum(fine * n_samples, 1.0))
        on_mirror = np.isclose(np.abs(cells[:, 2]), np.pi) | np.isclose(np.abs(cells[:, 3]), np.pi)
        wide = on_mirror & (cells[:, 3] - cells[:, 2] > mirror_width)
        ok = (ok & ~wide) | (level == max_level)
        np.add.at(prob, idx[ok], fine[ok])
        if ok.all():
            break
        c0, c1, p0, p1 = cells[~ok].T
        cm, pm = 0.5 * (c0 + c1), 0.5 * (p0 + p1)
        halve = wide[~ok]
        quarters = [(c0, cm, p0, pm), (cm, c1, p0, pm), (c0, cm, pm, p1), (cm, c1, pm, p1)]
        quarters = np.stack([np.stack(q, -1) for q in quarters], 1)
        halves = np.stack([np.stack(q, -1) for q in [(c0, c1, p0, pm), (c0, c1, pm, p1)]], 1)
        cells = np.concatenate([quarters[~halve].reshape(-1, 4), halves[halve].reshape(-1, 4)])
        parent = idx[~ok]
        idx = np.concatenate([np.repeat(parent[~halve], 4), np.repeat(parent[halve], 2)])
    return prob


def _chi2(params, cfg, wi, wo, pdf):
    """χ² test of samples ``(wo, pdf)`` against the cubature of ``pdf``: ``(p-value, bins, ∫pdf,
    fraction of samples below the horizon)``."""
    n = len(pdf)
    valid = pdf > 0.0
    ic = np.clip((wo[valid, 2] * N_COS).astype(int), 0, N_COS - 1)
    phi = np.arctan2(wo[valid, 1], wo[valid, 0])
    ip = np.clip(((phi + np.pi) / (2 * np.pi) * N_PHI).astype(int), 0, N_PHI - 1)
    observed = np.zeros(N_COS * N_PHI)
    np.add.at(observed, ic * N_PHI + ip, 1.0)
    prob = _bin_probabilities(params, cfg, wi, n)
    total = prob.sum()
    observed = np.append(observed, (~valid).sum())
    expected = np.append(n * prob, n * max(1.0 - total, 0.0))
    big = expected >= 5.0
    obs = np.append(observed[big], observed[~big].sum())
    exp = np.append(expected[big], expected[~big].sum())
    if exp[-1] < 5.0:  # the pooled rest is itself too small: merge it into the last bin
        obs, exp = np.append(obs[:-2], obs[-2:].sum()), np.append(exp[:-2], exp[-2:].sum())
    stat = float(np.sum((obs - exp) ** 2 / exp))
    return chi2.sf(stat, len(exp) - 1), len(exp), total, 1.0 - valid.mean()


CHI2_CASES = [
    ("rough", 0),
    ("rough", 45),
    ("rough", 87),
    ("smooth", 0),
    ("smooth", 45),
    ("smooth", 87),
    ("p0.2", 0),
    ("p0.2", 60),
    ("p5", 30),
    ("p5", 87),
    ("strong-diffraction", 0),
    ("strong-diffraction", 45),
    ("strong-diffraction", 87),
    ("weak-diffraction", 20),
    ("weak-diffraction", 87),
    ("plastic", 0),
    ("plastic", 45),
    ("plastic", 87),
]


@pytest.mark.parametrize("name,theta_deg", CHI2_CASES)
def test_sample_matches_pdf_chi2(name, theta_deg):
    """χ² goodness of fit of ``sample`` against ``pdf``; ``pdf`` integrates to 1 minus the
    fraction of samples that fall below the horizon (and to at most 1)."""
    params, cfg, wi, wo, pdf = _draw(name, theta_deg)
    p_value, n_bins, total, below = _chi2(params, cfg, wi, wo, pdf)
    # ∫pdf ≤ 1, and = 1 − P(below the horizon) (binomial error of the sampled fraction).
    assert total <= 1.0 + 1e-3
    sd = math.sqrt(max(below * (1 - below), 1e-6) / len(pdf))
    assert abs(total + below - 1.0) <= 4.0 * sd + 2e-3
    assert n_bins >= 8, "too few bins for a meaningful test"
    assert p_value > 1e-3, f"p = {p_value:.2e} with {n_bins} bins"


# ------------------------------------------------------------------------------ weights
# Measured maxima of luminance(ρ) cos θ_o / pdf over the 40 000 samples at θ_i ∈ {0, 45, 80,
# 87}°: ≤ 8 for every material here, except p = 0.2 (heavy-tailed EPD) at grazing incidence,
# where the NDF is sampled without regard to visibility (≈ 21 at 87°). The averages of these
# weights are checked against the albedo in test_albedo_table_convention_and_agreement.
WEIGHT_BOUND = {"p0.2": 40.0}


@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_weights_bounded(name):
    """``ρ cos θ_o / pdf`` (luminance) stays below a stated bound where the lobes are sampled."""
    params, cfg = MATERIALS[name]
    for theta_deg in (0, 45, 80, 87):
        _, _, wi, wo, pdf = _draw(name, theta_deg, seed=1)
        rho = np.asarray(twoscale.brdf(params, wi, jnp.asarray(wo), cfg)) @ LUM
        valid = pdf > 0
        w = np.where(valid, rho * np.clip(wo[:, 2], 0, None) / np.where(valid, pdf, 1.0), 0.0)
        assert np.all(np.isfinite(w)) and np.all(w >= 0)
        assert w.max() <= WEIGHT_BOUND.get(name, 12.0), (theta_deg, w.max())


# ------------------------------------------------------------------------------ domain
def test_pdf_zero_below_horizon():
    """0 when ``wo`` or ``wi`` is at or below the horizon; positive above it."""
    params, cfg = MATERIALS["plastic"]
    rng = np.random.default_rng(3)
    d = rng.normal(size=(2, 512, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    wi, wo = np.abs(d[0]) * [1, 1, 1], d[1]  # wi above, wo on both sides
    wi[:8, 2] = 0.0  # on the horizon
    wi[8:16, 2] *= -1.0  # below
    pdf = np.asarray(twoscale.pdf(params, jnp.asarray(wi), jnp.asarray(wo), cfg))
    below = (wo[:, 2] <= 0) | (wi[:, 2] <= 0)
    assert np.all(pdf[below] == 0.0)
    assert np.all(pdf[~below] > 0.0)  # the diffuse lobe covers the whole hemisphere
    # Samples for an incidence at or below the horizon carry nothing.
    wo_s, pdf_s = twoscale.sample(params, jnp.asarray(wi), _uniforms(4, 512), cfg)
    assert np.all(np.asarray(pdf_s)[wi[:, 2] <= 0] == 0.0)
    assert np.all(np.isfinite(np.asarray(wo_s)))
    # A sample whose wo fell below the horizon has pdf 0, and only those.
    _, _, _, wo_r, pdf_r = _draw("rough", 80)
    np.testing.assert_array_equal(pdf_r == 0.0, wo_r[:, 2] <= 0.0)
    # Directions of any length: the density and the samples of their unit vectors.
    s_i, s_o = rng.uniform(0.05, 20.0, (2, 512, 1))
    np.testing.assert_allclose(
        twoscale.pdf(params, jnp.asarray(wi * s_i), jnp.asarray(wo * s_o), cfg), pdf, rtol=1e-12
    )
    wo_l, pdf_l = twoscale.sample(params, jnp.asarray(wi * s_i), _uniforms(4, 512), cfg)
    np.testing.assert_allclose(wo_l, wo_s, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(pdf_l, pdf_s, rtol=1e-12)


def _extreme_params():
    """Conductors and plastics at the corners of the parameter ranges (twoscale.params)."""
    cond = [
        _conductor(beta=1e-3, p=0.2, sigma_s=1.0, b=350.0, c=1.01, eta=(0.01,) * 3, k=(10.0,) * 3),
        _conductor(beta=1.0, p=5.0, sigma_s=0.0, b=0.01, c=5.0, eta=(6.0,) * 3, k=(0.0,) * 3),
        _conductor(beta=1e-3, p=5.0, sigma_s=1.0, b=0.01, c=5.0, eta=(0.01,) * 3, k=(0.0,) * 3),
        _conductor(beta=1.0, p=0.2, sigma_s=1.0, b=350.0, c=1.01, eta=(6.0,) * 3, k=(10.0,) * 3),
    ]
    plas = [
        _plastic(beta=1e-3, p=0.2, eta=(1.0,) * 3, rho_d=(0.0,) * 3, sigma_s=1.0),
        _plastic(beta=1.0, p=5.0, eta=(4.0,) * 3, rho_d=(1.0,) * 3, sigma_s=0.0),
    ]
    return cond, plas


def _grazing_dirs(n):
    """Incidences from the normal to the horizon (cos θ_i down to 1e-7), random azimuths."""
    cos_i = np.geomspace(1e-7, 1.0, n)
    phi = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    s = np.sqrt(1.0 - cos_i**2)
    return np.stack([s * np.cos(phi), s * np.sin(phi), cos_i], -1)


def test_finite_at_grazing_and_parameter_bounds():
    """No NaN/inf in ``wo`` or ``pdf`` at the parameter bounds, from normal to grazing incidence."""
    cond, plas = _extreme_params()
    wi = jnp.asarray(_grazing_dirs(512))
    u = _uniforms(5, 512)
    for params, cfg in [(p, CONDUCTOR) for p in cond] + [(p, PLASTIC) for p in plas]:
        wo, pdf = twoscale.sample(params, wi, u, cfg)
        wo, pdf = np.asarray(wo), np.asarray(pdf)
        assert np.all(np.isfinite(wo)) and np.all(np.isfinite(pdf)) and np.all(pdf >= 0)
        np.testing.assert_allclose(np.linalg.norm(wo, axis=-1), 1.0, atol=1e-9)
        assert np.mean(pdf > 0) > 0.3  # most samples are usable even at the bounds
        again = np.asarray(twoscale.pdf(params, wi, jnp.asarray(wo), cfg))
        np.testing.assert_allclose(again, pdf, rtol=1e-12)


def test_jit_vmap_float32():
    """``jit(vmap(sample))`` over parameter sets: float32 in, float32 out, finite, and the
    float32 density agrees with the float64 one at the same directions."""
    cond, _ = _extreme_params()
    sets = [MATERIALS["rough"][0], MATERIALS["strong-diffraction"][0], cond[0], cond[3]]
    batch = jax.tree_util.tree_map(lambda *x: jnp.stack(x).astype(jnp.float32), *sets)
    wi = jnp.asarray(_grazing_dirs(512), jnp.float32)
    u = jnp.asarray(_uniforms(5, 512), jnp.float32)
    run = jax.jit(jax.vmap(lambda p, a, b: twoscale.sample(p, a, b, CONDUCTOR), (0, None, None)))
    wo, pdf = run(batch, wi, u)
    assert wo.dtype == jnp.float32 and pdf.dtype == jnp.float32
    assert wo.shape == (4, 512, 3) and pdf.shape == (4, 512)
    assert np.all(np.isfinite(np.asarray(wo))) and np.all(np.isfinite(np.asarray(pdf)))
    for k, params in enumerate(sets[:2]):  # away from the bounds: float32 ≈ float64
        wo64 = jnp.asarray(wo[k], jnp.float64)
        wo64 = wo64 / jnp.linalg.norm(wo64, axis=-1, keepdims=True)
        ref = np.asarray(twoscale.pdf(params, jnp.asarray(wi, jnp.float64), wo64, CONDUCTOR))
        got = np.asarray(pdf[k], np.float64)
        usable = (ref > 1e-6) & (np.asarray(wi[:, 2]) > 1e-3) & (np.asarray(wo64[:, 2]) > 1e-3)
        assert usable.sum() > 100
        np.testing.assert_allclose(got[usable], ref[usable], rtol=2e-3)


# ------------------------------------------------------------------------------ albedo table
def test_albedo_table_convention_and_agreement():
    """Shape ``(n, 3)``; row ``i`` is the albedo at ``cos θ_i = (i+1)/n``: it agrees with the
    Monte Carlo estimate ``mean(ρ cos θ_o / pdf)`` over ``sample``'s directions at that
    incidence (87.3°, 60°, normal), for a conductor and a plastic. This checks the table's
    convention and accuracy and that the sampler is unbiased (its pdf covers the BRDF)."""
    n = 64
    for name in ("strong-diffraction", "plastic"):
        params, cfg = MATERIALS[name]
        table = np.asarray(twoscale.albedo_table(params, n, cfg))
        assert table.shape == (n, 3) and np.all(np.isfinite(table)) and np.all(table >= 0)
        rows = np.array([2, n // 2 - 1, n - 1])  # cos θ_i = 3/64 (87.3°), 1/2, 1
        for row in rows:
            cos_i = (row + 1.0) / n
            wi = jnp.asarray([math.sqrt(1.0 - cos_i**2), 0.0, cos_i])
            wo, pdf = twoscale.sample(params, wi, _uniforms(6), cfg)
            pdf = np.asarray(pdf)
            rho = np.asarray(twoscale.brdf(params, wi, wo, cfg))
            valid = (pdf > 0)[:, None]
            w = np.where(valid, rho * np.asarray(wo[:, 2:]) / np.where(valid, pdf[:, None], 1), 0)
            sigma = w.std(axis=0) / math.sqrt(len(w))
            err = np.abs(w.mean(axis=0) - table[row])
            np.testing.assert_array_less(err, 5 * sigma + 2e-3 * table[row], err_msg=str(row))


def test_albedo_table_energy_conserving_in_unit_interval():
    """Energy-conserving sets (no nano-scale roughness: a Cook-Torrance lobe; and a weak
    diffraction lobe): every row in [0, 1]."""
    sets = [
        _conductor(beta=0.6, p=1.0, sigma_s=0.0),
        _conductor(
            beta=0.05, p=2.0, sigma_s=0.003, b=1.0, c=3.0, eta=(0.15, 0.4, 1.5), k=(4.0,) * 3
        ),
    ]
    for params in sets:
        table = np.asarray(twoscale.albedo_table(params, 64, CONDUCTOR))
        assert np.all(table >= 0.0) and np.all(table <= 1.0), table.max()
    assert table.max() > 0.9  # the smooth, bright set comes close to (not above) 1


# ------------------------------------------------------------------------------ other configs
def _variant_params(cfg):
    base = dict(beta=0.15, p=1.3, sigma_s=0.03, b=2.0, c=2.1, e=0.8)
    if cfg.is_conductor:
        return TwoScaleParams.conductor(eta=(0.2, 0.5, 1.4), k=(3.5, 2.5, 1.9), **base)
    return getattr(TwoScaleParams, cfg.material)(eta=(1.5, 1.5, 1.5), rho_d=(0.6, 0.4, 0.2), **base)


VARIANTS = [
    ModelConfig(diffraction=False),
    ModelConfig(material="plastic", diffraction=False),
    ModelConfig(specular=False),
    ModelConfig(material="plastic", specular=False, diffraction=False),
    ModelConfig(material="subsurface"),
    ModelConfig(material="plastic", diffuse_eta2=True, q_mode="F"),
    ModelConfig(material="plastic", diffuse_fresnel=False, apparatus=True),  # fit's protocol
    ModelConfig(q_mode="full", shadowing="uncorrelated", apparatus=True),
    ModelConfig(wavelengths=(0.4, 0.45, 0.5, 0.55, 0.6, 0.65, 0.7)),
    ModelConfig(wavelengths=(0.45, 0.55, 0.65), spectral_output="spectrum"),
    ModelConfig(path="exact"),
]


@pytest.mark.slow
@pytest.mark.parametrize("cfg", VARIANTS, ids=lambda c: str(VARIANTS.index(c)))
def test_every_config_chi2_and_unbiased(cfg):
    """Every kind of configuration (lobes off, subsurface, full Q, apparatus, Lambertian body,
    spectral, exact path): χ² of ``sample`` against ``pdf``, finite values, and an unbiased albedo estimate.
    The fast tests run the same code on the default conductor and plastic configurations."""
    params = _variant_params(cfg)
    n_out = cfg.n_channels
    for theta_deg in (30, 85):
        wi = _wi(theta_deg)
        wo, pdf = twoscale.sample(params, wi, _uniforms(7), cfg)
        wo, pdf = np.asarray(wo), np.asarray(pdf)
        assert np.all(np.isfinite(wo)) and np.all(np.isfinite(pdf))
        p_value = _chi2(params, cfg, wi, wo, pdf)[0]
        assert p_value > 1e-3, (theta_deg, p_value)
        valid = pdf > 0
        rho = np.asarray(twoscale.brdf(params, wi, jnp.asarray(wo), cfg))
        assert rho.shape == (len(pdf), n_out)
        w = np.where(valid[:, None], rho * wo[:, 2:] / np.where(valid, pdf, 1.0)[:, None], 0.0)
        ref = np.asarray(twoscale.albedo(params, float(wi[2]), cfg))
        sigma = w.std(axis=0) / math.sqrt(len(w))
        np.testing.assert_array_less(np.abs(w.mean(axis=0) - ref), 5 * sigma + 3e-3 * ref + 1e-6)

"""The MERL-grid fast path: brdf_grid / brdf_merl, the per-bin factorisation used by the fit,
the forward-mode rule of the shadowing term, and the fit's duplicate-solution test."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import twoscale
from twoscale import merl, model
from twoscale.fit.adapters import adapter_for
from twoscale.fit.candidates import Candidate, same_solution
from twoscale.fit.cells import pack, pair_cells, select_cells
from twoscale.fit.evaluation import predict_cells
from twoscale.fit.material_type import merl_protocol, resolve_configs
from twoscale.fit.residuals import Layout, Problem, normal_equations
from twoscale.fit.synthetic import synthetic
from twoscale.geometry import _dirs_from_half_diff

#: Compiled with most XLA optimisations off (tests/conftest.py): this module's time is compilation.
COMPILE_QUICKLY = True

CONDUCTOR = twoscale.TwoScaleParams.conductor(
    beta=0.1, p=1.5, eta=(0.2, 0.5, 1.4), k=(3.5, 2.5, 1.9), sigma_s=0.01, b=1.5, c=2.2
)
PLASTIC = twoscale.TwoScaleParams.plastic(
    0.08, 0.8, 1.5, (0.2, 0.3, 0.4), sigma_s=0.02, b=0.8, c=1.8, e=0.4
)
SUBSURFACE = twoscale.TwoScaleParams.subsurface(
    0.3, 2.5, 1.4, (0.5, 0.3, 0.1), sigma_s=0.005, b=3.0, c=3.0
)
CASES = [
    (CONDUCTOR, twoscale.ModelConfig()),
    (PLASTIC, twoscale.ModelConfig(material="plastic", q_mode="full", apparatus=True)),
    (SUBSURFACE, twoscale.ModelConfig(material="subsurface", shadowing="uncorrelated")),
    (CONDUCTOR, twoscale.ModelConfig(diffraction=False)),
    # Without the apparatus factor the grid path unfolds per-cell weights, not the total:
    # a Lambertian body (formed after the unfolding) and the full Q (a weight per channel).
    (
        PLASTIC.replace(e=None),
        twoscale.ModelConfig(material="plastic", diffuse_fresnel=False, q_mode="full"),
    ),
]


def _grid_directions(convention):
    ih, jd, kp = np.meshgrid(np.arange(90), np.arange(90), np.arange(180), indexing="ij")
    return _dirs_from_half_diff(np, *merl.bin_to_angles(ih, jd, kp, convention))


#: The bin-centre convention for the conductor (per-cell weights unfolded) and the plastic with
#: the apparatus factor (the total unfolded): both orders of the grid path. Its other cases run
#: in the slow set (the convention only changes the bins' angles, the same code for every case).
_CENTRE_FAST = (0, 1)


@pytest.mark.parametrize(
    ("case", "convention"),
    [(case, "lower") for case in range(len(CASES))]
    + [
        pytest.param(case, "centre", marks=() if case in _CENTRE_FAST else pytest.mark.slow)
        for case in range(len(CASES))
    ],
)
def test_brdf_merl_equals_brdf(case, convention):
    """The grid path is the same model: equal to brdf at every MERL cell's directions."""
    params, cfg = CASES[case]
    grid = np.asarray(model.brdf_merl(params, cfg, convention))
    assert grid.shape == (90, 90, 180, 3) and grid.dtype == np.float64
    wi, wo = _grid_directions(convention)
    below = (wi[..., 2] <= 0) | (wo[..., 2] <= 0)
    assert np.all(grid[below] == 0) and np.all(np.isfinite(grid))
    # brdf at a random eighth of the cells (every cell costs 1 s per case; the mirror, the
    # horizon and the grazing cells are all well represented in 180 000 cells).
    pick = np.random.default_rng(case).random(grid.shape[:3]) < 0.125
    ref = np.asarray(model.brdf(params, wi[pick], wo[pick], cfg))
    np.testing.assert_array_equal(grid[pick] == 0, ref == 0)
    # Relative agreement to rounding; the largest differences (~1e-10) sit at grazing cells,
    # where cos θ_o ~ 1e-6 is computed from different expressions (the φ_d mirror).
    np.testing.assert_allclose(grid[pick], ref, rtol=1e-9, atol=1e-14 * ref.max())


def test_brdf_merl_is_reciprocal_and_finite():
    vals = np.asarray(model.brdf_merl(CONDUCTOR))
    assert np.all(np.isfinite(vals)) and vals.min() >= 0.0
    # Lower edges: bin k and 180 − k hold the same direction pair with i and o swapped.
    np.testing.assert_array_equal(vals[:, :, 1:90], vals[:, :, 179:90:-1])


def _small_grid(convention="lower"):
    """Every 17th θ_h, 13th θ_d, 11th φ_d bin of the MERL grid (all bins computed: no mirror)."""
    ch, cd, sd, *_ = model._merl_grid_numpy(convention)
    ih, jd, kp = np.arange(0, 90, 17), np.arange(0, 90, 13), np.arange(0, 180, 11)
    wi, wo = _dirs_from_half_diff(np, *merl.bin_to_angles(*np.ix_(ih, jd, kp), convention))
    from twoscale.geometry import _azimuth_difference

    phi = _azimuth_difference(np, wi, wo, np.finfo(float).eps ** 2)
    g = model.HalfDiffGrid(
        *(jnp.asarray(a) for a in (ch[ih], cd[jd], sd[jd], wi[..., 2], wo[..., 2], phi)),
        jnp.arange(kp.size, dtype=jnp.int32),
    )
    return g, wi, wo


def _check_grid_gradients(case):
    """Parameter gradients of the grid path equal those of brdf at the same directions, and its
    forward-mode Jacobian (the fit's) equals its reverse mode (through the custom JVP rule of G).
    Three compiled functions: the reverse gradient of a random weighting of the grid path's
    values, the same of brdf's, and the grid path's forward Jacobian, which contracted with the
    weights must give the same gradient (a random projection of the whole Jacobian: a column
    that differs would differ there too, except on a set of weights of measure zero)."""
    params, cfg = CASES[case]
    grid, wi, wo = _small_grid()
    weights = np.random.default_rng(0).random(wi.shape[:-1] + (3,))

    def loss_ref(p):
        return jnp.sum(jnp.asarray(weights) * model.brdf(p, wi, wo, cfg))

    def loss_grid(p):
        return jnp.sum(jnp.asarray(weights) * model.brdf_grid(p, grid, cfg))

    gr = jax.jit(jax.grad(loss_grid))(params)
    jf = jax.jit(jax.jacfwd(lambda p: model.brdf_grid(p, grid, cfg)))(params)
    ref = jax.jit(jax.grad(loss_ref))(params)
    for a, b in zip(jax.tree_util.tree_leaves(gr), jax.tree_util.tree_leaves(ref), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12 * np.abs(b).max())
    for a, b in zip(jax.tree_util.tree_leaves(jf), jax.tree_util.tree_leaves(gr), strict=True):
        a = np.asarray(a)
        projected = np.tensordot(weights, a, axes=weights.ndim)
        assert np.all(np.isfinite(a)) and np.abs(a).max() > 0.0
        np.testing.assert_allclose(projected, b, rtol=1e-9, atol=1e-12 * np.abs(b).max())


@pytest.mark.slow
def test_brdf_grid_gradients_match_brdf():
    """The plastic with full Q and the apparatus factor (CASES[1]). Slow set (45 s on 2 cores):
    by default the grid path's derivatives are checked in forward mode, the fit's, by
    test_factorised_normal_equations_match_jacfwd (the same per-bin terms and per-cell total),
    its values by test_brdf_merl_equals_brdf, and brdf's gradients against finite differences by
    tests/test_model.py::test_check_grads_every_parameter."""
    _check_grid_gradients(1)


@pytest.mark.slow
def test_brdf_grid_gradients_match_brdf_conductor():
    """The conductor (CASES[0]); see test_brdf_grid_gradients_match_brdf for what the default
    set checks instead."""
    _check_grid_gradients(0)


@pytest.mark.parametrize("correlated", [True, False])
def test_shadowing_rule_equals_forward_mode(correlated):
    """G's hand-written rule along β and p (tables path, the fit's tangents) equals forward-mode
    differentiation of G itself, at cells from the normal to the horizon (equal Λ of both
    directions included, where the correlated form's max and min swap)."""
    rng = np.random.default_rng(7)
    cos_i = jnp.asarray(np.concatenate([rng.random(400), [1.0, 0.5, 1e-9, 0.3]]))
    cos_o = jnp.asarray(np.concatenate([rng.random(400), [1.0, 0.5, 0.7, 0.3]]))
    phi = jnp.asarray(np.concatenate([rng.random(400) * np.pi, [0.0, 1.0, 2.0, 3.0]]))
    static = ("tables", correlated)
    for beta, p in ((0.002, 0.25), (0.1, 1.5), (0.8, 6.0)):
        x = (jnp.float64(beta), jnp.float64(p))
        for tangent in ((1.0, 0.0), (0.0, 1.0), (0.3, -2.0)):

            def rule(b, q):
                return model._shadowing_g(static, b, q, cos_i, cos_o, phi)

            def plain(b, q):
                return model._g_of_cells(static, b, q, cos_i, cos_o, phi)

            got, d_got = jax.jvp(rule, x, tangent)
            _, d_want = jax.jvp(plain, x, tangent)
            # The value is G's own, bit for bit (forward mode of the plain G rounds its value
            # differently in the last bit at a few cells).
            np.testing.assert_array_equal(got, plain(*x))
            np.testing.assert_allclose(d_got, d_want, rtol=1e-9, atol=1e-14)


def test_shadowing_rule_under_multilinear_tables():
    """Inside ``tables.interpolation(order=1)`` (the benchmark's speed/accuracy trade) G's
    derivative along β and p is the plain forward mode of the multilinear tables' G (the
    hand-written partials are for the cubic spline; they raised there, and a fit with
    multilinear tables failed)."""
    from twoscale import tables

    cos_i = jnp.asarray([0.9, 0.5, 0.1, 1e-3])
    cos_o = jnp.asarray([0.8, 0.2, 0.6, 0.05])
    phi = jnp.asarray([0.3, 2.0, 3.1, 0.0])
    static = ("tables", True)
    x = (jnp.float64(0.3), jnp.float64(1.7))
    with tables.interpolation(order=1):
        got, d_got = jax.jvp(
            lambda b, q: model._shadowing_g(static, b, q, cos_i, cos_o, phi), x, (1.0, -0.5)
        )
        _, d_want = jax.jvp(
            lambda b, q: model._g_of_cells(static, b, q, cos_i, cos_o, phi), x, (1.0, -0.5)
        )
        want = model._g_of_cells(static, *x, cos_i, cos_o, phi)
    with tables.interpolation(order=3):
        cubic = model._shadowing_g(static, *x, cos_i, cos_o, phi)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_allclose(d_got, d_want, rtol=1e-12, atol=1e-15)
    assert np.all(np.isfinite(np.asarray(d_got))) and np.any(np.asarray(d_got) != 0.0)
    assert not np.array_equal(np.asarray(got), np.asarray(cubic))  # the other interpolation


def test_shadowing_rule_matches_finite_differences():
    """The custom forward rule of G: d/dβ, d/dp and d/d(directions) against central differences."""
    cos_i = jnp.asarray([0.9, 0.5, 0.1, 1e-3])
    cos_o = jnp.asarray([0.8, 0.2, 0.6, 0.05])
    phi = jnp.asarray([0.3, 2.0, 3.1, 0.0])
    static = ("tables", True)

    def g(beta, p, ci):
        return model._shadowing_g(static, beta, p, ci, cos_o, phi)

    for k, (x0, h) in enumerate([(0.3, 1e-6), (1.7, 1e-6)]):
        args = [0.3, 1.7, cos_i]
        tangent = [0.0, 0.0, jnp.zeros(4)]
        tangent[k] = 1.0
        _, d = jax.jvp(
            g, tuple(jnp.asarray(a) for a in args), tuple(jnp.asarray(t) for t in tangent)
        )
        up, dn = list(args), list(args)
        up[k], dn[k] = x0 + h, x0 - h
        fd = (g(*up) - g(*dn)) / (2 * h)
        np.testing.assert_allclose(d, fd, rtol=1e-6, atol=1e-9)
    _, d = jax.jvp(lambda c: g(0.3, 1.7, c), (cos_i,), (jnp.ones(4),))
    h = 1e-7
    fd = (g(0.3, 1.7, cos_i + h) - g(0.3, 1.7, cos_i - h)) / (2 * h)
    np.testing.assert_allclose(d, fd, rtol=1e-5, atol=1e-9)


@pytest.fixture(scope="module")
def conductor_data():
    return synthetic(CONDUCTOR, twoscale.ModelConfig(), noise=0.01, seed=3)


FIT_CASES = [
    (CONDUCTOR.replace(beta=0.12, p=1.2, c=2.6), twoscale.ModelConfig()),
    (
        PLASTIC.replace(beta=0.1, p=0.7, c=2.4),
        twoscale.ModelConfig(material="plastic", apparatus=True, fresnel="schlick"),
    ),
    (CONDUCTOR.replace(beta=0.12, p=1.2), twoscale.ModelConfig(diffraction=False)),
    # The MERL protocol's conductor: L(θ_d)² with its knee, a factor of θ_d (differentiated
    # per bin, in e and m too), and the Lambertian floor.
    (
        CONDUCTOR.replace(beta=0.12, p=1.2, c=2.6, e=0.7, m=3.0, rho_d=(0.01, 0.02, 0.005)),
        merl_protocol(),
    ),
    # The protocol's plastic: a Lambertian body, so η_c is separable (one seed for η).
    (
        PLASTIC.replace(beta=0.1, p=0.7, c=2.4, e=0.6, m=3.0),
        resolve_configs(None, "plastic")[0],
    ),
]


@pytest.mark.parametrize(
    # The plastic compiles for ≈ 24 s (the conductor covers the same factor code), and the bare
    # conductor's case takes ≈ 15 s (measured 2026-12-07; the protocol's conductor, case 3, has
    # every factor of it and the fall-off and floor besides): the slow set.
    "case",
    [pytest.param(0, marks=pytest.mark.slow), pytest.param(1, marks=pytest.mark.slow), 2, 3, 4],
)
def test_factorised_normal_equations_match_jacfwd(conductor_data, case):
    """The fit's per-bin factorisation (factors of θ_d, θ_h and of both differentiated once per
    pass, multiplied per pair) gives the normal equations of jacfwd through the plain model at
    the cells' directions."""
    sel = select_cells(conductor_data)
    cells = sel.fit.take(np.random.default_rng(1).choice(len(sel.fit), 1500, replace=False))
    p0, cfg = FIT_CASES[case]
    adapter = adapter_for(cfg)
    spec = jax.tree_util.tree_map(lambda _: True, p0)
    free, frozen = eqx.partition(p0.to_unconstrained(), spec)
    layout = Layout.of(free)
    y = layout.ravel(free)
    problem = Problem(adapter, layout, "log")
    assert problem.factorised
    data, n_active = pack(pair_cells(cells), n_chunks=3, chunk=512)

    def full(yy):
        pred = model.brdf(problem.params(yy, frozen), cells.wi, cells.wo, cfg)
        cos = cells.cos_i[:, None]
        return (jnp.log1p(pred * cos) - jnp.log1p(cells.rho * cos)).reshape(-1)

    r = jax.jit(full)(y)  # jitted: eager, every small op compiles on its own
    jac = jax.jit(jax.jacfwd(full))(y)
    jtj, jtr, rr = normal_equations(problem, y, frozen, data, jnp.int32(n_active))
    np.testing.assert_allclose(rr, r @ r, rtol=1e-9)
    np.testing.assert_allclose(jtj, jac.T @ jac, rtol=1e-7, atol=1e-11 * np.abs(jtj).max())
    np.testing.assert_allclose(jtr, jac.T @ r, rtol=1e-7, atol=1e-11 * np.abs(jtr).max())


def test_grid_lobe_rule_forward_reverse_and_frozen():
    """The lobe on the grid's bins carries its own forward-mode rule (its derivative along
    β, p, c, b, applied to every tangent): through the fit's factors, jacfwd and jacrev equal
    the plain model's jacfwd at the cells' directions; with β, p, c and b frozen the rest
    still differentiates; the grid's own angles are not differentiable."""
    from jax.flatten_util import ravel_pytree

    from twoscale.geometry import _azimuth_difference

    cfg = twoscale.ModelConfig(apparatus=True)
    params = CONDUCTOR.replace(beta=0.12, p=1.2, c=2.6, e=0.7)
    rng = np.random.default_rng(4)
    ih, jd, kp = (rng.integers(0, n, 200) for n in (90, 90, 180))
    wi, wo = _dirs_from_half_diff(np, *merl.bin_to_angles(ih, jd, kp, "lower"))
    phi = _azimuth_difference(np, wi, wo, 1e-30)
    above = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    grid = model.merl_grid("lower")
    u0, unravel = ravel_pytree(params.to_unconstrained())

    def factored(u):
        p = twoscale.TwoScaleParams.from_unconstrained(unravel(u))
        fac = model.half_diff_factors(p, grid, cfg)
        return model.brdf_from_factors(p, fac, ih, jd, wi[:, 2], wo[:, 2], phi, cfg)[above]

    def plain(u):
        p = twoscale.TwoScaleParams.from_unconstrained(unravel(u))
        return model.brdf(p, wi, wo, cfg)[above]

    ref = jax.jit(jax.jacfwd(plain))(u0)
    scale = np.abs(ref).max()
    for jac in (jax.jacfwd, jax.jacrev):
        got = jax.jit(jac(factored))(u0)
        np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-12 * scale)

    # Only η and k differentiated (the lobe's four parameters constants: symbolic zeros).
    def eta_k_only(v):
        p = twoscale.TwoScaleParams.from_unconstrained(unravel(u0))
        p = p.replace(eta=jnp.exp(v[:3]), k=jnp.exp(v[3:]))
        fac = model.half_diff_factors(p, grid, cfg)
        return model.brdf_from_factors(p, fac, ih, jd, wi[:, 2], wo[:, 2], phi, cfg)[above]

    def eta_k_plain(v):
        p = twoscale.TwoScaleParams.from_unconstrained(unravel(u0))
        p = p.replace(eta=jnp.exp(v[:3]), k=jnp.exp(v[3:]))
        return model.brdf(p, wi, wo, cfg)[above]

    v0 = jnp.log(jnp.concatenate([jnp.asarray(params.eta), jnp.asarray(params.k)]))
    np.testing.assert_allclose(
        jax.jit(jax.jacfwd(eta_k_only))(v0),
        jax.jit(jax.jacfwd(eta_k_plain))(v0),
        rtol=1e-10,
        atol=1e-12 * scale,
    )
    with pytest.raises(NotImplementedError, match="grid"):
        jax.jvp(
            lambda c: model._grid_lobe(
                ("tables", jnp.float64), jnp.array([0.1, 1.0, 2.0, 1.0]), c, c, jnp.ones(3)
            ),
            (grid.cos_h,),
            (jnp.ones_like(grid.cos_h),),
        )


def test_predict_cells_grid_path(conductor_data):
    sel = select_cells(conductor_data)
    cells = sel.valid.take(np.arange(0, len(sel.valid), 997))
    adapter = adapter_for(twoscale.ModelConfig())
    ref = np.asarray(model.brdf(CONDUCTOR, cells.wi, cells.wo))
    np.testing.assert_allclose(predict_cells(adapter, CONDUCTOR, cells), ref, rtol=1e-9)


def test_same_solution():
    jtj = np.diag([100.0, 1.0])

    def cand(y):
        return Candidate("c", 0, jnp.asarray(y), rr=10.0, jtj=jtj, m=12)

    # σ² = rr/(m − n) = 1: distance² = δᵀ JᵀJ δ.
    a = cand([0.0, 0.0])
    assert same_solution(a, cand([0.04, 0.0]))  # 0.4 SE
    assert not same_solution(a, cand([0.06, 0.0]))  # 0.6 SE
    assert same_solution(a, cand([0.0, 0.4]))
    assert not same_solution(a, cand([0.0, 0.6]))
    assert not same_solution(a, Candidate("d", 1, jnp.zeros(2), rr=10.0, jtj=jtj, m=12))
    assert not same_solution(a, cand([np.nan, 0.0]))

"""The fitting driver: residual machinery, starts, standard errors, records, parameter recovery.

Recovery: synthetic MERL tables made by the model itself (conductor and plastic, several parameter
sets), noise-free or with 1 % multiplicative noise and the realistic invalid mask (≈ 24 % invalid
cells). The fit from the default starts must recover the parameters (2 % noise-free; within a few
reported standard errors with noise) and bring the RMSE down to the noise level. Most cases use the
preview schedule (subsamples of 4 096 and 32 768 cells) to bound the CI cost; one uses the full grid.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twoscale.baselines import CookTorranceConfig, CookTorranceParams
from twoscale.fit import Stage, fit, load_result, synthetic
from twoscale.fit.adapters import adapter_for
from twoscale.fit.cells import Cells, pack, pair_cells, select_cells
from twoscale.fit.material_type import MERL_APPARATUS_ANGLES
from twoscale.fit.residuals import Layout, Problem, compressed_residuals, normal_equations
from twoscale.fit.starts import data_stats

CT = CookTorranceConfig("ggx")
CT_TRUE = CookTorranceParams(0.15, [0.9, 0.7, 0.4], [0.02, 0.05, 0.1])


@pytest.fixture(scope="module")
def ct_clean():
    return synthetic(CT_TRUE, CT, noise=0.0, seed=1)


@pytest.fixture(scope="module")
def ct_noisy():
    return synthetic(CT_TRUE, CT, noise=0.01, seed=2)


def _leaves_close(a, b, rtol):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol)


# ------------------------------------------------------------------------------------ machinery
def test_synthetic_mask_is_realistic(ct_clean):
    assert 0.755 <= ct_clean.valid_fraction <= 0.762  # MERL files: 0.758
    assert np.all(ct_clean.values[~ct_clean.valid] == 0.0)


def test_select_cells_horizon_and_angle_cut(ct_clean):
    sel = select_cells(ct_clean)
    assert len(sel.valid) == len(sel.fit) == int(ct_clean.valid.sum())
    assert np.all(sel.valid.wi[:, 2] > 0) and np.all(sel.valid.wo[:, 2] > 0)
    cut = select_cells(ct_clean, max_theta_deg=60)
    cmin = math.cos(math.radians(60))
    assert len(cut.valid) == len(sel.valid) > len(cut.fit) > 0
    assert np.all(cut.fit.wi[:, 2] >= cmin - 1e-12) and np.all(cut.fit.wo[:, 2] >= cmin - 1e-12)
    with pytest.raises(ValueError, match="max_theta"):
        select_cells(ct_clean, max_theta_deg=0)


def test_select_cells_all_invalid():
    from twoscale import merl

    empty = merl.MerlData(np.zeros((90, 90, 180, 3)), np.zeros((90, 90, 180), bool))
    with pytest.raises(ValueError, match="no valid cell"):
        select_cells(empty)


def test_compressed_problem_matches_full_residuals(ct_noisy):
    """|r̃|² = |r|², J̃ᵀJ̃ = JᵀJ and J̃ᵀr̃ = Jᵀr, against jacfwd of the plain residual vector."""
    sel = select_cells(ct_noisy)
    rng = np.random.default_rng(0)
    cells = sel.fit.take(rng.choice(len(sel.fit), 3000, replace=False))
    adapter = adapter_for(CT)
    p0 = CookTorranceParams(0.1, [0.5, 0.5, 0.5], [0.1, 0.1, 0.1])
    spec = jax.tree_util.tree_map(lambda _: True, p0)
    spec = eqx.tree_at(lambda s: s.rho_d, spec, False)  # one frozen field
    free, frozen = eqx.partition(p0.to_unconstrained(), spec)
    layout = Layout.of(free)
    assert layout.size == 4
    y = layout.ravel(free)
    np.testing.assert_array_equal(layout.ravel(layout.unravel(y)), y)
    scale = cells.log_scale()
    assert scale.shape == (3,) and np.all(scale > 0.0)
    for metric in ("log", "scaled-log", "blend", "linear"):
        problem = Problem(adapter, layout, metric)
        data, n_active = pack(pair_cells(cells), n_chunks=2, chunk=2048, log_scale=scale)

        def full(yy, problem=problem, metric=metric):
            p = problem.params(yy, frozen)
            pred = adapter.evaluate(p, cells.wi, cells.wo)
            cos = cells.cos_i[:, None]
            if metric == "log":
                return (jnp.log1p(pred * cos) - jnp.log1p(cells.rho * cos)).reshape(-1)
            if metric in ("scaled-log", "blend"):
                cs = cos / scale
                r_s = (jnp.log1p(pred * cs) - jnp.log1p(cells.rho * cs)).reshape(-1)
                if metric == "scaled-log":
                    return r_s
                # The blend: every cell's scaled and plain log residuals (the order of the
                # residuals does not matter to the normal equations).
                r_l = (jnp.log1p(pred * cos) - jnp.log1p(cells.rho * cos)).reshape(-1)
                return jnp.concatenate([r_s, r_l])
            return ((pred - cells.rho) * cos).reshape(-1)

        r = full(y)
        jac = jax.jacfwd(full)(y)
        jtj, jtr, rr = normal_equations(problem, y, frozen, data, n_active)
        np.testing.assert_allclose(rr, r @ r, rtol=1e-10)
        np.testing.assert_allclose(jtj, jac.T @ jac, rtol=1e-8, atol=1e-12 * np.abs(jtj).max())
        np.testing.assert_allclose(jtr, jac.T @ r, rtol=1e-8, atol=1e-12 * np.abs(jtr).max())
        r_c, lin = jax.linearize(
            lambda yy, pb=problem, d=data, n=n_active: compressed_residuals(pb, yy, frozen, d, n), y
        )
        j_c = jax.vmap(lin)(jnp.eye(4)).T
        np.testing.assert_allclose(r_c @ r_c, r @ r, rtol=1e-10)
        np.testing.assert_allclose(
            j_c.T @ j_c, jac.T @ jac, rtol=1e-8, atol=1e-12 * np.abs(jtj).max()
        )
        np.testing.assert_allclose(
            j_c.T @ r_c, jac.T @ r, rtol=1e-7, atol=1e-12 * np.abs(jtr).max()
        )


def test_folded_passes_equal_chunk_by_chunk_passes(ct_noisy):
    """A pass takes :data:`~twoscale.fit.residuals.FOLD` chunks of the buffer at a time where
    their number allows, masking the pairs of inactive chunks inside a partly active fold: its
    normal equations and sum of squares are those of the same pairs taken chunk by chunk, for
    every number of active chunks (a stage's prefix). The buffer's measured log terms are those
    of its values, and follow its scale."""
    from twoscale.fit.cells import with_scale
    from twoscale.fit.residuals import FOLD, sum_squares

    sel = select_cells(ct_noisy)
    cells = sel.fit.take(np.random.default_rng(1).choice(len(sel.fit), 1300, replace=False))
    pairs = pair_cells(cells)
    assert 2 * 512 < len(pairs) <= 3 * 512
    adapter = adapter_for(CT)
    free, frozen = eqx.partition(adapter.to_unconstrained(CT_TRUE), True)
    layout = Layout.of(free)
    problem = Problem(adapter, layout, "blend")
    y = layout.ravel(free) + 0.05  # away from the truth: residuals of both signs
    scale = cells.log_scale()
    folded, n_active = pack(pairs, n_chunks=2 * FOLD, chunk=512, log_scale=scale)
    plain, _ = pack(pairs, n_chunks=3, chunk=512, log_scale=scale)  # 3: not foldable
    assert n_active == 3
    rho, cos = np.asarray(plain["rho"]), np.asarray(plain["cos"])[..., None]
    np.testing.assert_allclose(plain["log"], np.log1p(rho * cos), rtol=1e-15)
    np.testing.assert_allclose(plain["log_s"], np.log1p(rho * cos / scale), rtol=1e-15)
    unscaled = with_scale(plain, 1.0)
    np.testing.assert_allclose(unscaled["log_s"], plain["log"], rtol=1e-15)
    rr = []
    for n in (1, 2, 3):
        want = normal_equations(problem, y, frozen, plain, n)
        got = normal_equations(problem, y, frozen, folded, n)
        for a, b in zip(want, got, strict=True):
            np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12 * np.abs(a).max())
        np.testing.assert_allclose(sum_squares(problem, y, frozen, folded, n), want[2], rtol=1e-12)
        rr.append(float(want[2]))
    assert rr[0] < rr[1] < rr[2]  # each active chunk adds its pairs, the others none


def test_scaled_log_metric_is_scale_invariant(ct_noisy):
    """The scaled log metric's scale is each channel's median ρ cos θ_i (floored), so scaling a
    channel's data and model by k leaves its error unchanged, where the plain log metric (nearly
    absolute below 0.1 1/sr) sees k times smaller errors on a darkened channel."""
    from twoscale.fit.cells import LOG_SCALE_FLOOR, Cells
    from twoscale.fit.evaluation import rmse

    cells = select_cells(ct_noisy).fit
    med = np.median(cells.rho * cells.cos_i[:, None], axis=0)
    np.testing.assert_allclose(cells.log_scale(), np.maximum(med, LOG_SCALE_FLOOR))
    pred = cells.rho * 1.2  # 20 % too bright everywhere
    k = np.array([1.0, 0.01, 100.0])
    dark = Cells(cells.wi, cells.wo, cells.rho * k, cells.index)
    a, b = rmse(pred, cells), rmse(pred * k, dark)
    np.testing.assert_allclose(
        b["per_channel"]["rmse_log_scaled"], a["per_channel"]["rmse_log_scaled"], rtol=1e-9
    )
    assert b["per_channel"]["rmse_log"][1] < 0.1 * a["per_channel"]["rmse_log"][1]
    black = Cells(cells.wi, cells.wo, cells.rho * [1.0, 0.0, 1.0], cells.index)
    assert black.log_scale()[1] == LOG_SCALE_FLOOR  # a black channel stays finite
    with pytest.raises(ValueError, match="log_scale"):
        pack(pair_cells(cells.take(np.arange(1000))), n_chunks=1, log_scale=[1.0, 0.0, 1.0])


def test_reciprocal_pairs(ct_clean):
    """Cells φ_d = k and 180 − k share one pair; the pair's directions are the first member's."""
    from twoscale import merl

    sel = select_cells(ct_clean)
    pairs = pair_cells(sel.fit)
    assert pairs.n_cells == len(sel.fit)
    assert len(pairs) < 0.52 * len(sel.fit)  # nearly every cell has its partner
    # Members: cos θ_i of the second member is cos θ_o of the first; values match the table.
    k = np.arange(len(pairs))[:: max(1, len(pairs) // 500)]
    for j in k:
        both = pairs.w[j] == 1
        assert np.all(pairs.cos[j] > 0) and both.any()
    # A pair's model value is the value at either member's own directions (reciprocity).
    th, td, pd = merl.bin_to_angles(np.array([40, 40]), np.array([20, 20]), np.array([30, 150]))
    from twoscale.geometry import dirs_from_half_diff

    wi, wo = (np.asarray(v) for v in dirs_from_half_diff(th, td, pd))
    adapter = adapter_for(CT)
    vals = np.asarray(adapter.evaluate(CT_TRUE, wi, wo))
    np.testing.assert_allclose(vals[0], vals[1], rtol=1e-12)
    np.testing.assert_allclose(wi[0, 2], wo[1, 2], rtol=1e-12)


def test_pack_pads_with_zero_weight():
    cells = Cells(
        np.tile([0.0, 0.0, 1.0], (5, 1)),
        np.tile([0.0, 0.0, 1.0], (5, 1)),
        np.ones((5, 3)),
        np.arange(5) * 180,  # φ_d bin 0: single cells, five pairs
    )
    data, n_active = pack(pair_cells(cells), n_chunks=3, chunk=4)
    assert n_active == 2
    assert data["w"].shape == (3, 4, 2)
    assert float(data["w"].sum()) == 5.0


def test_data_stats_peak_width(ct_clean):
    """The 1/e half-width gives α to ~15 % for GGX (tan θ_{1/e} ≈ 0.80 α, cos⁴ neglected)."""
    stats = data_stats(np.asarray(ct_clean.values), np.asarray(ct_clean.valid))
    alpha_est = stats.beta / math.sqrt(math.sqrt(math.e) - 1.0)
    assert alpha_est == pytest.approx(0.15, rel=0.15)
    # The floor is the diffuse level plus GGX's heavy specular tail.
    assert np.all(stats.floor >= 0.95 * np.asarray(CT_TRUE.rho_d) / np.pi)
    assert np.all(stats.floor < 0.05 * stats.peak)


# ------------------------------------------------------------------------------------ baseline fits
def test_baseline_recovery_noise_free(ct_clean):
    res = fit(ct_clean, config=CT, schedule="preview")
    assert res.converged
    _leaves_close(res.params, CT_TRUE, rtol=1e-6)
    assert res.rmse_log < 1e-9
    assert res.model == "cook-torrance-ggx"


def test_baseline_recovery_noisy_within_standard_errors(ct_noisy):
    res = fit(ct_noisy, config=CT, schedule="preview")
    assert res.converged
    # log residual of 1 % multiplicative noise: ≈ 0.01 ρcos/(1+ρcos), below 0.01.
    assert 1e-3 < res.rmse_log < 0.01
    for name in ("alpha", "f0", "rho_d"):
        est = np.asarray(getattr(res.params, name))
        true = np.asarray(getattr(CT_TRUE, name))
        se = np.asarray(res.std_errors[name])
        assert np.all(se > 0)
        assert np.all(np.abs(est - true) <= 4 * se + 1e-12), (name, est, true, se)


def test_fixed_parameter_is_held(ct_noisy):
    res = fit(ct_noisy, config=CT, schedule="preview", fixed={"alpha": 0.16})
    assert float(res.params.alpha) == pytest.approx(0.16, rel=1e-12)
    assert res.std_errors["alpha"] is None
    assert res.std_errors["f0"] is not None
    with pytest.raises(ValueError, match="cannot fix"):
        fit(ct_noisy, config=CT, schedule="preview", fixed={"beta": 0.1})


@pytest.mark.parametrize(
    "config, fixed, needle",
    [
        (None, {"p": 100.0}, r"cannot fix p = 100: outside its valid range \[0.2, 5\]"),
        (None, {"beta": 0.0}, r"cannot fix beta = 0: outside its valid range"),
        (None, {"p": float("nan")}, "not a finite number"),
        (None, {"eta": [1.5, 1.5]}, r"give 1 or 3 value\(s\), got 2"),
        (None, {"eta": 0.5}, r"outside its valid range \[1, 4\] \(plastic\)"),
        # The names of every stage's model, not only those of the first (diffraction-off) stage.
        (None, {"foo": 1.0}, "parameters of this fit are beta, p, sigma_s, b, c"),
        (None, {"k": 0.5, "rho_d": 0.1}, "no material type has them all"),
        (CT, {"f0": 2.0}, r"cannot fix f0 = 2: outside its valid range \[0, 1\]"),
    ],
)
def test_bad_fixed_values_are_refused_before_any_work(ct_noisy, config, fixed, needle):
    """A held value the fit could not hold as given is an error naming it, not a clamp (p = 100
    was fitted at p = 5, β = 0 at 1e-3, both with exit 0) nor a fit of NaNs."""
    with pytest.raises(ValueError, match=needle):
        fit(ct_noisy, config=config, fixed=fixed)


def test_data_that_is_not_merl_data_is_a_type_error(ct_noisy):
    with pytest.raises(TypeError, match="needs a twoscale.merl.MerlData .* got ndarray"):
        fit(np.asarray(ct_noisy.values), config=CT)


def test_a_held_parameter_of_one_type_fits_that_type_only():
    from twoscale.fit.driver import _types_holding
    from twoscale.fit.material_type import merl_protocol

    configs = [
        dataclasses.replace(merl_protocol(), material=m, conductor_floor=False)
        for m in ("conductor", "plastic")
    ]
    said = []
    kept = _types_holding(configs, {"k": 0.5}, said.append)
    assert [c.material for c in kept] == ["conductor"]
    assert said == [
        "the held k leaves out the plastic type (it has no such parameter): fitting the "
        "conductor only"
    ]
    assert [c.material for c in _types_holding(configs, {"rho_d": 0.1}, said.append)] == ["plastic"]
    assert _types_holding(configs, {"p": 1.0}, said.append) == configs


def test_result_record_roundtrip(ct_noisy, tmp_path):
    res = fit(ct_noisy, config=CT, schedule=[Stage(4096, 1, 40)], metric="linear")
    path = res.save(tmp_path / "params.json")
    raw = json.loads(path.read_text())
    assert raw["format"] == "twoscale-fit/1"
    assert raw["metrics"]["metric"] == "linear"
    assert set(raw["versions"]) >= {"python", "jax", "optimistix", "numpy"}
    assert raw["covariance"]["rank"] == 7
    back = load_result(path)
    _leaves_close(back.params, res.params, rtol=1e-15)
    assert raw["metrics"]["rmse_log_scaled"] > 0 and len(raw["metrics"]["log_scale"]) == 3
    assert back.rmse_log_scaled == res.rmse_log_scaled and back.log_scale == res.log_scale
    assert back.rmse_log == res.rmse_log and back.std_errors == json.loads(
        json.dumps(res.std_errors)
    )
    assert CookTorranceParams.from_dict(raw["params"]).to_dict() == res.params.to_dict()
    assert not list(tmp_path.glob(".*tmp"))  # the atomic write left no temporary file


def test_bad_arguments(ct_clean):
    with pytest.raises(ValueError, match="metric"):
        fit(ct_clean, config=CT, metric="l2")
    with pytest.raises(ValueError, match="schedule"):
        fit(ct_clean, config=CT, schedule="fast")
    with pytest.raises(ValueError, match="material"):
        fit(ct_clean, config=CT, material="plastic")


def test_needs_float64(ct_clean):
    jax.config.update("jax_enable_x64", False)
    try:
        with pytest.raises(RuntimeError, match="float64"):
            fit(ct_clean, config=CT)
    finally:
        jax.config.update("jax_enable_x64", True)


@pytest.mark.slow
def test_nested_start_keeps_full_model_at_least_as_good():
    """The full model contains the diffraction-off model (σ_s → 0): with the nested start its fit
    is never worse than that model's own fit on the same cells and schedule. (Three fits, ≈ 25 s
    on 2 cores: the slow set. The fast set runs the nested start's code in
    test_preview_of_a_bare_metal_fits_one_type, the full conductor started from its special
    case, and test_narrow_start_placed_from_the_special_case.)"""
    from twoscale import ModelConfig, TwoScaleParams

    true = TwoScaleParams.conductor(0.1, 1.3, (0.3, 0.5, 1.2), (3.5, 2.6, 2.0))
    data = synthetic(true, ModelConfig(diffraction=False), noise=0.01, seed=5)
    stages = [Stage(4096, 2, 25), Stage(8192, 1, 15)]
    # The few starts of --preview (the special case from p = 1, the full model from the nested
    # start and one point of the grid around it): the same code as the default start set.
    kw = {"material": "conductor", "schedule": stages, "starts": "few"}
    spec = fit(data, config=ModelConfig(diffraction=False), **kw)
    full = fit(data, config=ModelConfig(), **kw)
    labels = [e["start"] for e in full.stages[0]["starts"]]
    assert sum("nested" in label for label in labels) == 1, labels
    assert len(labels) == 2, labels
    # Every start of the full model comes from the special case's fit (the nested one and the
    # lobe placed from its highlight).
    assert all("nested" in label or "narrow as the special case" in label for label in labels)
    assert full.rmse_log <= spec.rmse_log * (1 + 1e-3), (full.rmse_log, spec.rmse_log)
    # Without the nested start the full model starts from the data (the few of them suffice to
    # show that: starts="few" keeps the p = 1 data starts).
    no_nested = fit(
        data,
        config=ModelConfig(),
        material="conductor",
        schedule=stages[:1],
        nested=False,
        starts="few",
    )
    labels = [e["start"] for e in no_nested.stages[0]["starts"]]
    assert labels and not any("nested" in lab or "special case" in lab for lab in labels)


# ------------------------------------------------------------------ protocol, stopping, type
def test_merl_protocol_default_is_apparatus():
    """``fit(data)`` fits MERL data with the apparatus factor (its exponent e fitted) and a
    plastic's body Lambertian; an explicit configuration is taken as given."""
    from twoscale import ModelConfig, TwoScaleParams
    from twoscale.fit import merl_protocol
    from twoscale.fit.material_type import resolve_configs

    auto = resolve_configs(None, None)
    assert [c.material for c in auto] == ["conductor", "plastic"]
    assert all(c.apparatus and not c.diffuse_fresnel for c in auto)
    # The knee exponent m of L(θ) = [1 − (2θ/π)^m]^e is fitted with e by default; the bare
    # apparatus switch keeps the paper's m = 2 (no parameter), and no apparatus means neither.
    assert all(c.apparatus_knee and {"e", "m"} <= set(c.param_names) for c in auto)
    assert "m" not in ModelConfig(apparatus=True).param_names
    assert "m" not in merl_protocol(apparatus_knee=False).param_names
    assert not {"e", "m"} & set(merl_protocol(apparatus=False).param_names)
    assert all(c == merl_protocol() for c in resolve_configs(None, "conductor"))
    assert all(c.apparatus for c in resolve_configs("auto", "plastic"))
    assert not any(c.apparatus for c in resolve_configs(ModelConfig(), "auto"))
    assert all(c.diffuse_fresnel for c in resolve_configs(ModelConfig(), "auto"))
    assert merl_protocol(diffuse_fresnel=True).diffuse_fresnel
    cfg = ModelConfig(material="conductor", apparatus=True, diffraction=False)
    true = TwoScaleParams.conductor(0.12, 1.2, (0.3, 0.5, 1.2), (3.5, 2.6, 2.0), e=0.7)
    data = synthetic(true, cfg, noise=0.005, seed=4)
    res = fit(data, config=cfg, schedule="preview")
    assert res.config["apparatus"] is True and res.params.e is not None
    assert float(res.params.e) == pytest.approx(0.7, abs=3 * res.std_errors["e"] + 1e-3)
    assert res.std_errors["e"] > 0


def test_capped_fit_is_kept_with_a_warning(ct_noisy):
    """A fit stopped by the step limit is a result with a warning, not an error."""
    far = [CookTorranceParams(1.0, [0.5, 0.5, 0.5], [0.5, 0.5, 0.5])]  # far from the truth
    # 12 steps: the first round (10) makes progress, the second is cut to 2 by the cap while the
    # RMS still falls fast (far from the optimum).
    res = fit(ct_noisy, config=CT, starts=far, schedule=[Stage(4096, 1, 12)])
    assert not res.converged and res.status == "step limit reached"
    assert any(w.startswith("not converged: step limit reached") for w in res.warnings)
    assert math.isfinite(res.rmse_log)


def test_stationary_rms_counts_as_converged(ct_noisy):
    """Rounds that no longer lower the RMS end the stage as converged, well before the cap."""
    res = fit(ct_noisy, config=CT, schedule=[Stage(4096, 1, max_steps=500, round_steps=5)])
    assert res.converged and res.steps < 500
    assert not any(w.startswith("not converged") for w in res.warnings)


def test_parameter_at_bound_is_named():
    """Data without MERL's fall-off, fitted with it: e ends at 0, and the warning says so."""
    truth = CookTorranceParams(0.2, [0.8, 0.6, 0.3], [0.05, 0.1, 0.2])
    data = synthetic(truth, CT, noise=0.0, seed=3)
    res = fit(data, config=CookTorranceConfig("ggx", apparatus=True), schedule="preview")
    assert float(res.params.e) < 1e-2
    assert any(w.startswith("e = ") and "lower end" in w for w in res.warnings), res.warnings


def test_failed_fit_raises(ct_noisy, monkeypatch):
    """Non-finite costs from every start are a FitError (the CLI's exit 3)."""
    import twoscale.fit.driver as driver
    import twoscale.fit.solver as solver

    def broken(cand, g, stage, data, n_active, m, opts, twin=None):
        return cand.y, math.nan, np.zeros((7, 7)), 3, False, "non-finite values"

    monkeypatch.setattr(solver, "refine", broken)
    with pytest.raises(driver.FitError, match="finite"):
        fit(ct_noisy, config=CT, schedule=[Stage(4096, 1, 5)])


def test_choose_type_tie_goes_to_the_physical_type():
    from twoscale import TwoScaleParams
    from twoscale.fit.material_type import choose_type

    metal = TwoScaleParams.conductor(0.1, 1.0, (0.3, 0.5, 1.2), (3.5, 2.6, 2.0))
    fake_metal = TwoScaleParams.conductor(0.1, 1.0, (1.5, 1.5, 1.5), (0.01, 0.02, 0.0))
    plastic = TwoScaleParams.plastic(0.1, 1.0, (1.5, 1.5, 1.5), (0.2, 0.3, 0.4))
    fake_plastic = TwoScaleParams.plastic(0.1, 1.0, (3.5, 3.5, 3.5), (1e-4, 1e-4, 1e-4))
    # A clear winner wins whatever its parameters.
    assert choose_type({"conductor": (0.10, metal), "plastic": (0.20, plastic)})[0] == "conductor"
    assert choose_type({"conductor": (0.20, metal), "plastic": (0.10, plastic)})[0] == "plastic"
    # Within 2 %: a conductor with k ≈ 0 is a dielectric; a plastic without diffuse is a metal.
    tie = choose_type({"conductor": (0.100, fake_metal), "plastic": (0.101, plastic)})
    assert tie[0] == "plastic" and "k <" in tie[1]
    tie = choose_type({"conductor": (0.101, metal), "plastic": (0.100, fake_plastic)})
    assert tie[0] == "conductor" and "no diffuse" in tie[1]
    # Both plausible: the lower RMS.
    assert choose_type({"conductor": (0.101, metal), "plastic": (0.100, plastic)})[0] == "plastic"
    # Both disguised (a low-k conductor and a bodiless plastic, as alum-bronze and
    # black-oxidized-steel fitted with Schlick's form): the bare interface is a metal's.
    tie = choose_type({"conductor": (0.101, fake_metal), "plastic": (0.100, fake_plastic)})
    assert tie[0] == "conductor" and "no diffuse" in tie[1]
    # A body in one channel is a body (a red wood whose luminance ρ_d is below 0.01).
    red_body = TwoScaleParams.plastic(0.1, 1.0, (1.5, 1.5, 1.5), (0.04, 1e-5, 1e-5))
    tie = choose_type({"conductor": (0.100, fake_metal), "plastic": (0.101, red_body)})
    assert tie[0] == "plastic" and "k <" in tie[1]
    # k ≈ 0.6-1 (a fabric fitted as a conductor, η < 1) is no metal's: every metal has k > 1.68
    # in the visible. Gold's k (1.8 in blue) is a metal's.
    fabric_as_metal = TwoScaleParams.conductor(0.7, 0.5, (0.7, 0.65, 0.6), (0.98, 0.75, 0.59))
    tie = choose_type({"conductor": (0.1000, fabric_as_metal), "plastic": (0.1005, plastic)})
    assert tie[0] == "plastic" and "k < 1.5" in tie[1]
    gold = TwoScaleParams.conductor(0.1, 1.0, (0.18, 0.42, 1.37), (3.4, 2.35, 1.8))
    assert choose_type({"conductor": (0.1005, gold), "plastic": (0.1000, plastic)})[0] == (
        "plastic"
    )  # both plausible: the lower RMS
    assert choose_type({"conductor": (0.1000, gold), "plastic": (0.1005, plastic)})[0] == (
        "conductor"
    )


def test_choose_type_a_conductor_without_the_measured_body_loses():
    """A conductor fit with the lower RMS loses to the plastic on a material whose diffuse body
    carries much of its light, whether it leaves the body out (it would render black with a
    highlight) or makes it with its lobes (a conductor has no diffuse layer) unless those lobes
    fit clearly better (a rough metal's tail); the faint scatter under a metal's highlight does
    not count."""
    from twoscale import TwoScaleParams
    from twoscale.fit.material_type import EVIDENCE_RTOL, choose_type

    cond = TwoScaleParams.conductor(0.01, 0.5, (1.0, 1.0, 1.0), (0.1, 0.1, 0.1))
    plastic = TwoScaleParams.plastic(0.01, 0.5, (1.1, 1.1, 1.1), (0.27, 0.03, 0.02))
    best = {"conductor": (0.07, cond), "plastic": (0.10, plastic)}
    red = np.array([0.088, 0.011, 0.0032])  # a red phenolic's floor (1/sr), π ρ ≈ 0.084
    albedo = np.full(3, 0.05)  # all the light it reflects: the body is most of it
    body = {"measured": red, "conductor": red * 1e-6, "plastic": red * 0.8, "albedo": albedo}
    chosen, reason = choose_type(best, body)
    assert chosen == "plastic" and "diffuse body" in reason
    # The conductor reproduces the floor with its lobes: still no diffuse layer, the plastic wins
    # when its own layer reproduces the body and the conductor's RMS is not lower by more than
    # EVIDENCE_RTOL...
    close = {"conductor": (0.10 / (1.0 + EVIDENCE_RTOL), cond), "plastic": (0.10, plastic)}
    chosen, reason = choose_type(close, {**body, "conductor": red * 0.9})
    assert chosen == "plastic" and "no diffuse layer" in reason and "90%" in reason
    # ...while lobes that make the floor and fit clearly better are a rough metal's (its tail
    # is a floor too)...
    chosen, reason = choose_type(best, {**body, "conductor": red * 0.9})
    assert chosen == "conductor" and "rough metal" in reason and "1.43×" in reason
    # ...and not when it does not (then the lower RMS).
    assert choose_type(best, {**body, "conductor": red * 0.9, "plastic": red * 0.3})[0] == (
        "conductor"
    )
    # A body carrying a fifth of the light (π ρ ≈ 0.084 of 0.4: a metal mixed with a fabric) still
    # counts: left out, it renders black around the highlight.
    assert choose_type(best, {**body, "albedo": np.full(3, 0.4)})[0] == "plastic"
    # The faint scatter under a bright metal's highlight (π ρ ≈ 0.017 of 0.6, 3 %): not a body.
    faint = {k: v * 0.2 for k, v in body.items() if k != "albedo"}
    assert choose_type(best, {**faint, "albedo": np.full(3, 0.6)})[0] == "conductor"
    # The plastic misses the body even more than the conductor: no reason to switch.
    assert choose_type(best, {**body, "plastic": red * 1e-8})[0] == "conductor"
    # Without body levels the rule is off.
    assert choose_type(best)[0] == "conductor"


def test_dielectric_albedo_bound():
    """The most a dielectric interface reflects, as the type choice weighs a highlight against:
    the hemispherical average of Fresnel's reflectance (0.0918 at η = 1.5, the textbook value),
    more for a higher index, less through MERL's apparatus fall-off."""
    from twoscale.fit.material_type import dielectric_albedo_bound

    assert dielectric_albedo_bound(None, 1.5) == pytest.approx(0.0918, abs=2e-4)
    assert dielectric_albedo_bound(None, 1.0) == pytest.approx(0.0, abs=1e-12)
    bare = dielectric_albedo_bound(None)
    assert bare > dielectric_albedo_bound(None, 1.5)
    late = dielectric_albedo_bound((1.0, 8.0))  # a knee late and steep: little is lost
    early = dielectric_albedo_bound((1.0, 1.0))  # falling from normal incidence on
    assert bare > late > early > 0.0 and late > 0.7 * bare and early < 0.3 * bare


def test_choose_type_without_a_body_the_highlight_decides():
    """No measured body: a highlight brighter than any dielectric interface reflects through
    the same fall-off is a metal's (conductor, though the plastic's RMS is 3 % lower, as on
    chrome and tungsten-carbide), a dim one a dielectric's (plastic, though the conductor's RMS
    is 2.2 % lower, as on black-phenolic); a much lower RMS still wins."""
    from twoscale import TwoScaleParams
    from twoscale.fit.material_type import EVIDENCE_RTOL, choose_type

    cond = TwoScaleParams.conductor(0.001, 0.4, (1.3, 1.5, 1.5), (0.5, 1e-3, 1e-4))
    plastic = TwoScaleParams.plastic(0.001, 0.4, (1.6, 1.5, 1.5), (0.003, 0.003, 0.004))
    floor = np.full(3, 1e-4)  # π ρ ≈ 3e-4: no body
    bright = {"measured": floor, "conductor": floor * 0.5, "plastic": floor * 3.0}
    bright |= {"albedo": np.full(3, 0.127), "fall_off": (1.06, 1.0)}  # bound 0.022
    chosen, reason = choose_type(
        {"conductor": (0.1495, cond), "plastic": (0.1451, plastic)}, bright
    )
    assert chosen == "conductor" and "more than a dielectric" in reason
    # Without the fall-off the bound is 0.120: a highlight of 0.11 is within a dielectric's reach.
    unfallen = {**bright, "albedo": np.full(3, 0.11), "fall_off": None}
    best = {"conductor": (0.1495, cond), "plastic": (0.1451, plastic)}
    assert choose_type(best, unfallen)[0] == "plastic"
    far = (1.0 + 1.5 * EVIDENCE_RTOL) * 0.1451
    assert choose_type({"conductor": (far, cond), "plastic": (0.1451, plastic)}, bright)[0] == (
        "plastic"
    )
    # A floor beyond a bare metal's faint scatter (9 % of the light, as in a mixture of aluminium
    # and alum-bronze) that the conductor fit leaves out: the highlight does not decide (the
    # conductor would render black where the measured sphere is warm brown); the RMS does.
    warm = np.full(3, 0.0032)  # π ρ ≈ 0.010 of 0.11: 9 %
    glow = {**bright, "measured": warm, "conductor": warm * 0.1, "plastic": warm * 0.9}
    glow["albedo"] = np.full(3, 0.11)
    chosen, reason = choose_type({"conductor": (0.1587, cond), "plastic": (0.1536, plastic)}, glow)
    assert chosen == "plastic" and reason == "lower RMS"
    # ...unless the conductor fit makes that floor with its lobes.
    chosen, _ = choose_type(
        {"conductor": (0.1587, cond), "plastic": (0.1536, plastic)},
        {**glow, "conductor": warm * 0.8},
    )
    assert chosen == "conductor"
    dim = {**bright, "albedo": np.full(3, 0.024), "fall_off": (1.63, 3.97)}  # bound 0.059
    chosen, reason = choose_type({"conductor": (0.0779, cond), "plastic": (0.0797, plastic)}, dim)
    assert chosen == "plastic" and "no more than a dielectric" in reason
    far = (1.0 + 1.5 * EVIDENCE_RTOL) * 0.0779
    assert choose_type({"conductor": (0.0779, cond), "plastic": (far, plastic)}, dim)[0] == (
        "conductor"
    )


def test_bihemispherical_albedo_of_a_lambertian_table():
    """The albedo the type choice weighs a body against: ρ for a Lambertian table (to the
    quadrature's 5 %), less where cells are invalid."""
    from twoscale.merl import bihemispherical_albedo

    values = np.broadcast_to(np.array([0.1, 0.5, 0.9]) / np.pi, (90, 90, 180, 3))
    valid = np.ones((90, 90, 180), bool)
    full = bihemispherical_albedo(values, valid)
    np.testing.assert_allclose(full, [0.1, 0.5, 0.9], rtol=0.05)
    part = bihemispherical_albedo(values, valid & (np.arange(90) < 60)[None, :, None])
    assert np.all(part < 0.99 * full) and np.all(part > 0.5 * full)


@pytest.mark.parametrize("material", ["conductor", "plastic"])
def test_type_choice_on_synthetic_materials(material, monkeypatch):
    """``material="auto"`` types a synthetic conductor as a conductor and a plastic as a plastic;
    the chosen configuration's evaluation (pictures, albedo table) is compiled in the background
    while the last stage runs, once. With ``conductor_floor`` (the conductor's truth has a
    faint floor), the types are compared without the floor and the chosen conductor's last
    stage adds it: the floor is recovered and the record's configuration has it."""
    import twoscale.fit.driver as driver
    from twoscale import ModelConfig, TwoScaleParams

    warmed = []
    real_warm = driver.warm_evaluation

    def spy(adapter, params):
        warmed.append(adapter.config)
        return real_warm(adapter, params)

    monkeypatch.setattr(driver, "warm_evaluation", spy)

    rho = np.array([0.012, 0.008, 0.005])  # the conductor's floor
    if material == "conductor":
        true = TwoScaleParams.conductor(
            0.08, 1.5, (0.2, 0.4, 1.1), (3.2, 2.5, 1.9), e=0.8, rho_d=rho
        )
    else:
        true = TwoScaleParams.plastic(0.08, 1.5, (1.5, 1.5, 1.5), (0.1, 0.3, 0.6), e=0.8)
    cfg = ModelConfig(material=material, diffraction=False, apparatus=True, conductor_floor=True)
    data = synthetic(true, cfg, noise=0.01, seed=6)
    stages = [Stage(4096, 1, 40), Stage(8192, 1, 20)]
    res = fit(
        data,
        config=ModelConfig(diffraction=False, apparatus=True, conductor_floor=True),
        material="auto",
        schedule=stages,
    )
    assert res.type_selection["chosen"] == material, res.type_selection
    assert res.material == material
    assert "rho_d" not in res.type_selection["params"]["conductor"]  # compared without it
    assert res.model_config.conductor_floor is (material == "conductor")
    if material == "conductor":
        assert all(e["start"].endswith("+ floor") for e in res.stages[-1]["starts"])
        np.testing.assert_allclose(np.asarray(res.params.rho_d), rho, rtol=0.1)
        assert res.std_errors["rho_d"] is not None
    assert [c.material for c in warmed] == [material]
    assert warmed[0] == res.model_config
    # The default metric is the blend of the scaled and the plain log residuals; the types are
    # compared on the plain log metric alone. With every scale s_c < 1, a fit's plain log
    # residuals are cell by cell smaller than its scaled ones (d/dx log(1 + x/s) > d/dx
    # log(1 + x)), so the type's RMS is below its stage RMS, which holds both.
    assert res.metric == "blend" and res.type_selection["metric"] == "log"
    assert np.all(np.asarray(res.log_scale) < 1.0)
    stage = res.stages[res.type_selection["stage"] - 1]
    fitted = min(e["rms"] for e in stage["starts"] if e["start"].startswith(material))
    assert res.type_selection["rms"][material] < fitted
    # Both types' best fits at the choosing stage are kept (the chosen one's is where the last
    # stage started from); the other type's can be read back and used.
    other = {"conductor": "plastic", "plastic": "conductor"}[material]
    kept = {m: TwoScaleParams.from_dict(d) for m, d in res.type_selection["params"].items()}
    assert set(kept) == {material, other}
    assert kept[other].material == other and kept[material].material == material
    assert res.type_selection["rms"][other] > res.type_selection["rms"][material]
    assert json.loads(json.dumps(res.type_selection))["params"] == res.type_selection["params"]


def test_type_choice_on_a_rough_synthetic_conductor():
    """A rough conductor of the model itself (β = 0.3, p = 0.5) puts a fifth of its light in the
    far tail that the floor level counts as a diffuse body; its lobes make that floor and fit it
    several times better than the plastic's Lambertian layer, so ``material="auto"`` types it a
    conductor (the body rule gave it to the plastic, at 6.5× the conductor's RMS on the default
    protocol, before its evidence guard)."""
    from twoscale import ModelConfig, TwoScaleParams
    from twoscale.fit.material_type import EVIDENCE_RTOL

    true = TwoScaleParams.conductor(0.3, 0.5, (0.2, 0.4, 1.1), (3.2, 2.5, 1.9), e=0.8)
    cfg = ModelConfig(material="conductor", diffraction=False, apparatus=True)
    data = synthetic(true, cfg, noise=0.01, seed=6)
    res = fit(
        data,
        config=ModelConfig(diffraction=False, apparatus=True),
        material="auto",
        schedule=[Stage(4096, 1, 40), Stage(8192, 1, 20)],
    )
    sel = res.type_selection
    assert sel["chosen"] == "conductor" and "rough metal" in sel["reason"], sel
    assert "floor carries" in sel["reason"]  # the body rule was the one that looked
    assert sel["rms"]["plastic"] > (1.0 + EVIDENCE_RTOL) * sel["rms"]["conductor"]
    assert res.rmse_log < 0.01


def test_few_starts_let_a_measured_body_decide_the_type(tmp_path):
    """``starts="few"`` (``--preview``) with ``material="auto"``: a measured diffuse body carrying
    at least ``BODY_SHARE`` of the light makes the plastic the type without fitting the conductor
    (the body rule's choice, recorded as decided from the data); a bare metal's data decides
    nothing, and the default starts still fit and compare both types."""
    from twoscale import ModelConfig, TwoScaleParams
    from twoscale.fit.material_type import BODY_SHARE, type_from_body
    from twoscale.model import LUMINANCE

    plastic = TwoScaleParams.plastic(0.08, 1.5, (1.5, 1.5, 1.5), (0.1, 0.3, 0.6), e=0.8)
    metal = TwoScaleParams.conductor(0.08, 1.5, (0.2, 0.4, 1.1), (3.2, 2.5, 1.9), e=0.8)
    cfg = ModelConfig(diffraction=False, apparatus=True)
    data = synthetic(plastic, dataclasses.replace(cfg, material="plastic"), noise=0.01, seed=6)
    bare = synthetic(metal, dataclasses.replace(cfg, material="conductor"), noise=0.01, seed=6)
    stats = data_stats(np.asarray(data.values), np.asarray(data.valid))
    decided = type_from_body(stats)
    assert decided is not None and decided[0] == "plastic", decided
    assert type_from_body(data_stats(np.asarray(bare.values), np.asarray(bare.valid))) is None
    assert type_from_body(dataclasses.replace(stats, albedo=None)) is None
    # Just below the share the body is not enough (the floor scaled to 0.99 of the threshold).
    w = np.asarray(LUMINANCE)
    share = np.pi * float(stats.floor @ w) / float(stats.albedo @ w)
    assert share > BODY_SHARE
    low = dataclasses.replace(stats, floor=stats.floor * (0.99 * BODY_SHARE / share))
    assert type_from_body(low) is None

    stages = [Stage(2048, 1, 20), Stage(4096, 1, 10)]
    res = fit(data, config=cfg, material="auto", schedule=stages, starts="few")
    ts = res.type_selection
    assert ts["from_data"] and ts["chosen"] == "plastic" and ts["rms"] == {}, ts
    assert res.material == "plastic"
    starts = [e["start"] for st in res.stages for e in st["starts"]]
    assert starts and not any(label.startswith("conductor") for label in starts), starts
    assert "type plastic: the measured diffuse body carries" in res.summary()
    back = load_result(res.save(tmp_path / "params.json"))
    assert back.type_selection == json.loads(json.dumps(ts))


#: The floor of the bodiless data of the type-rule tests below (1/sr per channel).
_FAINT = np.full(3, 1e-4)


def _bodiless_stats(highlight):
    """Data statistics with the faint floor :data:`_FAINT` and a highlight of albedo
    ``highlight`` above it (the rules read the floor, the albedo and nothing else)."""
    from twoscale.fit.material_type import body_share
    from twoscale.fit.starts import DataStats

    body, *_ = body_share(_FAINT, np.ones(3))
    return DataStats(np.ones(3), _FAINT, 0.1, np.full(3, highlight + body))


def _with_heavy_floor(stats):
    """``stats`` with its floor raised to carry 1.5× ``FAINT_SHARE`` of the light."""
    from twoscale.fit.material_type import FAINT_SHARE, body_share

    body, albedo, _ = body_share(stats.floor, stats.albedo)
    heavy = dataclasses.replace(stats, floor=stats.floor * (1.5 * FAINT_SHARE * albedo / body))
    assert body_share(heavy.floor, heavy.albedo)[2] > FAINT_SHARE
    return heavy


def test_type_from_highlight_rules():
    """:func:`type_from_highlight` (a preview's type for data without a body): a highlight
    brighter than a dielectric interface reflects through the fall-off is a conductor's when
    its RMS is within ``EVIDENCE_RTOL`` of the plastic's; a dimmer highlight, a floor beyond
    ``FAINT_SHARE`` of the light, or no albedo decide nothing (the full fits do)."""
    from twoscale.fit.material_type import (
        EVIDENCE_RTOL,
        dielectric_albedo_bound,
        type_from_highlight,
    )

    bound = dielectric_albedo_bound((1.0, 3.0))
    assert 0.0 < bound < dielectric_albedo_bound(None)
    stats = _bodiless_stats
    rms = {"conductor": 0.10, "plastic": 0.10}
    kind, reason = type_from_highlight(stats(1.5 * bound), rms, (1.0, 3.0))
    assert kind == "conductor" and "more than a dielectric" in reason, reason
    assert type_from_highlight(stats(0.5 * bound), rms, (1.0, 3.0)) is None
    # The same highlight against the bound without a fall-off (larger): not decided.
    assert type_from_highlight(stats(1.5 * bound), rms, None) is None
    # The plastic's RMS lower by more than EVIDENCE_RTOL: not decided here.
    worse = {"conductor": 0.10 * (1 + 1.5 * EVIDENCE_RTOL), "plastic": 0.10}
    assert type_from_highlight(stats(1.5 * bound), worse, (1.0, 3.0)) is None
    near = {"conductor": 0.10 * (1 + 0.5 * EVIDENCE_RTOL), "plastic": 0.10}
    assert type_from_highlight(stats(1.5 * bound), near, (1.0, 3.0))[0] == "conductor"
    # A floor carrying more than a bare metal's faint scatter, no albedo, one type: None.
    s = stats(1.5 * bound)
    assert type_from_highlight(_with_heavy_floor(s), rms, (1.0, 3.0)) is None
    assert type_from_highlight(dataclasses.replace(s, albedo=None), rms, (1.0, 3.0)) is None
    assert type_from_highlight(s, {"conductor": 0.1}, (1.0, 3.0)) is None


def test_highlight_suggests_conductor_before_any_fit():
    """:func:`highlight_suggests_conductor`: the highlight's test of :func:`type_from_highlight`
    alone (no fit's RMS), what a preview compiles ahead by; nothing for data with a body."""
    from twoscale.fit.material_type import (
        dielectric_albedo_bound,
        highlight_suggests_conductor,
        type_from_highlight,
    )

    bound = dielectric_albedo_bound((0.5, 2.0))
    for factor in (0.5, 0.99, 1.01, 1.5):
        stats = _bodiless_stats(factor * bound)
        want = type_from_highlight(stats, {"conductor": 0.1, "plastic": 0.1}, (0.5, 2.0))
        assert highlight_suggests_conductor(stats, (0.5, 2.0)) is (want is not None), factor
    # Against the bound without a fall-off (larger), the same highlight suggests no conductor.
    assert not highlight_suggests_conductor(_bodiless_stats(1.5 * bound), None)
    assert not highlight_suggests_conductor(_with_heavy_floor(_bodiless_stats(1.5 * bound)), None)
    assert not highlight_suggests_conductor(
        dataclasses.replace(_bodiless_stats(1.5 * bound), albedo=None), (0.5, 2.0)
    )


def _full_models_compiled_ahead(monkeypatch) -> list:
    """Spy on the fit's background compilation: the material of every full model (diffraction
    on) whose solve is queued, in order."""
    import twoscale.fit.solver as solver

    queued = []
    submit = solver.Warmup.submit

    def spy(self, g, y0):
        if g.adapter.config.diffraction:
            queued.append(g.adapter.config.material)
        return submit(self, g, y0)

    monkeypatch.setattr(solver.Warmup, "submit", spy)
    return queued


def test_preview_type_falls_back_on_the_lower_rms():
    """:func:`preview_type`: where the highlight does not decide a bodiless material's type, the
    special case with the lower RMS does (the plastic on a tie); a conductor the highlight
    decides stays one; a floor beyond ``FAINT_SHARE``, no albedo or one type decide nothing."""
    from twoscale.fit.material_type import (
        dielectric_albedo_bound,
        preview_type,
        type_from_highlight,
    )

    bound = dielectric_albedo_bound((1.0, 3.0))
    dim, bright = _bodiless_stats(0.5 * bound), _bodiless_stats(1.5 * bound)
    for rms, want in (
        ({"conductor": 0.12, "plastic": 0.10}, "plastic"),
        ({"conductor": 0.10, "plastic": 0.12}, "conductor"),
        ({"conductor": 0.10, "plastic": 0.10}, "plastic"),
    ):
        assert type_from_highlight(dim, rms, (1.0, 3.0)) is None
        kind, reason = preview_type(dim, rms, (1.0, 3.0))
        assert kind == want and "lower RMS" in reason, (rms, kind, reason)
        assert "full model not fitted" in reason
    # The highlight's rule first: a bright highlight within EVIDENCE_RTOL is the conductor's.
    near = {"conductor": 0.105, "plastic": 0.10}
    assert preview_type(bright, near, (1.0, 3.0)) == type_from_highlight(bright, near, (1.0, 3.0))
    assert preview_type(bright, near, (1.0, 3.0))[0] == "conductor"
    # Nothing decided where the rule does not apply.
    rms = {"conductor": 0.12, "plastic": 0.10}
    assert preview_type(_with_heavy_floor(dim), rms, (1.0, 3.0)) is None
    assert preview_type(dataclasses.replace(dim, albedo=None), rms, (1.0, 3.0)) is None
    assert preview_type(dim, {"plastic": 0.1}, (1.0, 3.0)) is None


def test_preview_of_a_bare_metal_fits_one_type(tmp_path, monkeypatch):
    """``starts="few"`` (``--preview``) on a bare metal's data (no floor): the special cases'
    highlight decides the conductor, whose full model alone is fitted (and compiled ahead, as
    its highlight suggests), with its Lambertian floor from the first stage (no conversion
    before a last stage); the record says so."""
    from twoscale import ModelConfig, TwoScaleParams
    from twoscale.fit import merl_protocol

    metal = TwoScaleParams.conductor(0.08, 1.5, (0.2, 0.4, 1.1), (3.2, 2.5, 1.9), e=0.8)
    # MERL-like data under the protocol's fall-off form.
    cfg = ModelConfig(
        diffraction=False,
        apparatus=True,
        material="conductor",
        apparatus_angles=MERL_APPARATUS_ANGLES,
    )
    bare = synthetic(metal, cfg, noise=0.01, seed=6)
    stages = [Stage(2048, 1, 15), Stage(4096, 1, 8)]
    logs = []
    ahead = _full_models_compiled_ahead(monkeypatch)
    res = fit(
        bare,
        config=merl_protocol(apparatus_knee=False),
        material="auto",
        schedule=stages,
        starts="few",
        progress=logs.append,
    )
    ts = res.type_selection
    assert ts["from_data"] and ts["chosen"] == "conductor" and ts["stage"] == 0, ts
    assert set(ts["rms"]) == {"conductor", "plastic"}, ts
    assert "the plastic's full model not fitted" in ts["reason"]
    assert res.material == "conductor" and res.config["conductor_floor"], res.config
    assert res.params.rho_d is not None and np.all(np.asarray(res.params.rho_d) > 0)
    full = [e["start"] for st in res.stages for e in st["starts"]]
    assert full and all(label.startswith("conductor") for label in full), full
    assert not any("floor added" in line for line in logs), logs
    assert ahead and set(ahead) == {"conductor"}, ahead
    assert "type conductor: no diffuse body" in res.summary()
    back = load_result(res.save(tmp_path / "params.json"))
    assert back.type_selection == json.loads(json.dumps(ts))


@pytest.mark.parametrize(
    ("guess", "winner"),
    [("conductor", "plastic"), ("conductor", "conductor"), ("plastic", "conductor")],
)
def test_preview_queues_the_decided_type_before_the_grids(monkeypatch, guess, winner):
    """A bodiless preview compiles ahead the full model of the type its highlight suggests;
    when the special cases decide the other type, that type's solve is queued at the decision,
    before the grid evaluations queued with it (it is needed first), and nothing is queued
    twice. The driver's path without a solve: the screening stages and the decision stubbed."""
    from twoscale import ModelConfig, TwoScaleParams
    from twoscale.fit import driver, merl_protocol
    from twoscale.fit.material_type import resolve_configs

    metal = TwoScaleParams.conductor(0.08, 1.5, (0.2, 0.4, 1.1), (3.2, 2.5, 1.9), e=0.8)
    cfg = ModelConfig(diffraction=False, apparatus=True, material="conductor")
    data = synthetic(metal, cfg, noise=0.01, seed=6)
    prep = types.SimpleNamespace(stats=data_stats(np.asarray(data.values), np.asarray(data.valid)))
    assert driver.faint_floor(prep.stats)  # a bodiless material: the preview decides early

    def screening(prep_, groups, cands, stages, opts, say, choose, warm=None):
        for i, c in enumerate(cands):
            c.cost = 0.1 + 0.01 * i
        return sorted(cands, key=lambda c: c.cost), [{"n_cells_used": 4096}], None, {}

    def decision(prep_, configs, start_lists, source, sub_groups, best, stages, settings, floors):
        keep = [gi for gi, c in enumerate(configs) if c.material == winner]
        record = {"chosen": winner, "reason": "stubbed"}
        return (
            [floors.get(configs[gi], configs[gi]) for gi in keep],
            [start_lists[gi] for gi in keep],
            [source[gi] for gi in keep],
            record,
        )

    monkeypatch.setattr(driver, "_run_schedule", screening)
    monkeypatch.setattr(driver, "_preview_decision", decision)
    monkeypatch.setattr(driver, "highlight_suggests_conductor", lambda *a: guess == "conductor")
    queue = []

    class Warm:  # records the order of what the fit queues for compiling
        def submit(self, g, y):
            if g.adapter.config.diffraction:
                queue.append(("solve", g.adapter.config.material))

        def submit_call(self, key, fn):
            queue.append(("call", key[0]))

    configs, floors = driver._split_floors(resolve_configs(merl_protocol(), "auto"))
    settings = driver.FitSettings(starts="few", stages=(Stage(4096, 1, 5), Stage(8192, 1, 5)))
    out, *_, decided = driver._make_starts(prep, configs, settings, lambda m: None, Warm(), floors)
    assert decided["chosen"] == winner and [c.material for c in out] == [winner]
    solves = [q for q in queue if q[0] == "solve"]
    assert solves[0] == ("solve", guess)  # compiled ahead, before the decision
    assert len(solves) == len(set(solves)) == (1 if guess == winner else 2), queue
    first_grid = queue.index(("call", "grid"))
    assert queue.index(("solve", winner)) < first_grid, queue


@pytest.mark.slow
def test_preview_of_a_bare_dielectric_fits_the_plastic_alone(monkeypatch):
    """``starts="few"`` on a dielectric interface without a body (ρ_d ≈ 0): its highlight is
    a dielectric's, so the highlight rule decides nothing, and the special cases' lower RMS
    gives the plastic, whose full model alone is fitted (the fast set checks the rule itself,
    ``test_preview_type_falls_back_on_the_lower_rms``, and the driver's path with a bare
    metal)."""
    from twoscale import ModelConfig, TwoScaleParams
    from twoscale.fit import merl_protocol

    coat = TwoScaleParams.plastic(0.08, 1.5, (1.5, 1.5, 1.5), (1e-4, 1e-4, 1e-4), e=0.8)
    # MERL-like data under the protocol's fall-off form: with data made
    # with the paper's L(θ_i) L(θ_o) instead (a form the protocol does not fit), the bare
    # conductor fitted this coat 0.7 % better (0.01953 against 0.01966, 2026-12-07) and the
    # preview typed it a conductor.
    cfg = ModelConfig(
        diffraction=False,
        apparatus=True,
        material="plastic",
        diffuse_fresnel=False,
        apparatus_angles=MERL_APPARATUS_ANGLES,
    )
    bare = synthetic(coat, cfg, noise=0.01, seed=7)
    ahead = _full_models_compiled_ahead(monkeypatch)
    res = fit(
        bare,
        config=merl_protocol(apparatus_knee=False),
        material="auto",
        schedule=[Stage(2048, 1, 15), Stage(4096, 1, 8)],
        starts="few",
    )
    ts = res.type_selection
    assert ts["from_data"] and ts["chosen"] == "plastic" and ts["stage"] == 0, ts
    assert "lower RMS" in ts["reason"] and ts["rms"]["plastic"] <= ts["rms"]["conductor"], ts
    assert res.material == "plastic"
    assert ahead and set(ahead) == {"plastic"}, ahead  # its dim highlight: compiled ahead
    full = [e["start"] for st in res.stages for e in st["starts"]]
    assert full and all(label.startswith("plastic") for label in full), full
    assert res.rmse_log < 0.05, res.rmse_log


def test_no_progress_raises(ct_noisy, monkeypatch):
    """Every solver step rejected from every start: a FitError (the CLI's exit 3), not a result."""
    import twoscale.fit.driver as driver
    import twoscale.fit.solver as solver

    real = solver.solve

    def stuck(problem, y0, *args):
        # y never moves, no accepted step
        return real(problem, y0, *args)._replace(y=y0, converged=False, moves=0)

    monkeypatch.setattr(solver, "solve", stuck)
    with pytest.raises(driver.FitError, match="progress"):
        fit(ct_noisy, config=CT, schedule=[Stage(4096, 1, 6)])


@pytest.mark.parametrize(
    ("solver_name", "ratio", "n_rounds"),
    # Levenberg-Marquardt: the step size is the damping's inverse, 4⁴ = 256 more damped per
    # round, scales 16× smaller; 256^r · INITIAL_DAMPING passes MAX_DAMPING = 1e5 at r = 4.
    # Dogleg: a trust radius in the scaled variables goes as 1/√damping, so 256² = 65,536 more
    # damped per round, scales 256× smaller; 65,536^r · 1e-3 passes 1e5 at r = 2.
    [("lm", 16.0, 4), ("dogleg", 256.0, 2)],
)
def test_rejected_rounds_carry_the_damping(monkeypatch, solver_name, ratio, n_rounds):
    """A round of solver steps that were all rejected hands its damping to the next round (which
    would otherwise repeat the same steps from the same point), and a start whose steps stay
    rejected while the damping grows past MAX_DAMPING has converged, before the step limit."""
    import types

    import optimistix as optx

    import twoscale.fit.solver as solver

    seen = []

    def rejected(g, y0, data, n_active, cap, m, scale, opts):
        seen.append((cap, np.asarray(scale)))
        # The trust region shrinks by 4 at each rejected step after the first (an evaluation).
        return solver.Solved(
            y0, optx.RESULTS.successful, False, cap, 0, 1.0, np.eye(2), 0.25 ** (cap - 1)
        )

    monkeypatch.setattr(solver, "_run_solve", rejected)
    cand = types.SimpleNamespace(y=np.zeros(2), moves=0, twin=None)
    g = types.SimpleNamespace(layout=types.SimpleNamespace(size=2))
    opts = types.SimpleNamespace(solver=solver_name)
    stage = Stage(4096, keep=1, max_steps=100, round_steps=5)
    y, rr, jtj, steps, converged, status = solver.refine(cand, g, stage, None, 1, 8000, opts)
    rounds = [sc for cap, sc in seen if cap > 1]
    # Each round starts more damped than the last (4 rejected steps): its scales are smaller.
    for a, b in zip(rounds[:-1], rounds[1:], strict=True):
        np.testing.assert_allclose(a / b, ratio)
    assert converged and status == "converged (no step lowers the RMS)", status
    assert steps == 5 * n_rounds and len(rounds) == n_rounds and cand.moves == 0


def test_few_starts_subset(ct_clean):
    """``starts="few"`` (the CLI's --preview): the special case from p = 1 only, the full model
    from the nested start and the lobe placed from its highlight only; an unknown start set is
    refused."""
    from twoscale import TwoScaleParams
    from twoscale.config import ModelConfig
    from twoscale.fit.candidates import NESTED_LABEL, nested_starts
    from twoscale.fit.driver import FEW_NESTED_GRID, _few_data_starts

    stats = data_stats(np.asarray(ct_clean.values), np.asarray(ct_clean.valid))
    cfg = ModelConfig(material="conductor", apparatus=True)
    special = adapter_for(ModelConfig(material="conductor", diffraction=False, apparatus=True))
    all_special = special.starts(stats)
    few_special = _few_data_starts(all_special)
    assert few_special and len(few_special) < len(all_special)
    assert all(label.split()[0] == "p=1" for label, _ in few_special)
    params = TwoScaleParams.conductor(0.1, 1.0, (0.2, 0.4, 1.3), (3.4, 2.4, 1.8), e=1.0)
    # What the driver asks for with starts="few": the nested start and the one placed from the
    # special case's highlight.
    nested = nested_starts(params, cfg, {}, FEW_NESTED_GRID)
    kept = [label for label, _ in nested]
    assert len(kept) == 2 and kept[0] == NESTED_LABEL
    assert kept[1].startswith("as narrow as the special case")
    # A start list without a p = 1 start keeps its middle start.
    other = [("a", 1), ("b", 2), ("c", 3)]
    assert _few_data_starts(other) == [("b", 2)]
    with pytest.raises(ValueError, match="few"):
        fit(ct_clean, config=CT, starts="several")


def test_narrow_start_placed_from_the_special_case():
    """The default start list of the full model ends with a strong diffraction lobe as narrow as
    the special case's EPD: b = λ/(2β) at the median wavelength (inside b's range), c and
    A_spec(0) of NARROW_START, the specular parameters those of the special case."""
    from twoscale import TwoScaleParams
    from twoscale.config import ModelConfig
    from twoscale.fit.adapters import sigma_s_for_a_spec
    from twoscale.fit.candidates import NARROW_START, NESTED_GRID, narrow_b, nested_starts
    from twoscale.params import bounds_for

    cfg = ModelConfig(material="plastic", apparatus=True)
    wl = float(np.median(cfg.wavelengths))
    special = TwoScaleParams.plastic(0.002, 0.4, (1.5, 1.5, 1.5), (0.2, 0.1, 0.05), e=1.0)
    starts = nested_starts(special, cfg, {})
    assert len(starts) == 2 + len(NESTED_GRID)
    label, last = starts[-1]
    c, a_spec = NARROW_START
    assert label.startswith("as narrow as the special case")
    np.testing.assert_allclose(float(last.b), wl / (2 * 0.002), rtol=1e-12)
    np.testing.assert_allclose(float(last.c), c, rtol=1e-12)
    np.testing.assert_allclose(
        float(last.sigma_s), sigma_s_for_a_spec(a_spec, float(last.b), c, wl), rtol=1e-12
    )
    assert float(last.beta) == 0.002 and float(last.p) == 0.4
    np.testing.assert_allclose(np.asarray(last.rho_d), (0.2, 0.1, 0.05))
    # Inside b's range at both ends: a mirror-like β, and a wide one.
    hi, lo = bounds_for("b", None).hi, bounds_for("b", None).lo
    assert narrow_b(1e-6, wl) == 0.9 * hi
    assert lo < narrow_b(1.0, wl) == wl / 2
    # A fixed b (or c) overrides the placed one; points it makes equal are fitted once: with
    # b = 7 µm the grid's two strong lobes (c = 1.5, A_spec(0) = 0.05) and the placed one are
    # the same start.
    fixed = nested_starts(special, cfg, {"b": 7.0})
    assert all(float(s.b) == 7.0 for _, s in fixed)
    assert float(fixed[-1][1].b) == 7.0
    keys = [(float(s.sigma_s), float(s.c)) for _, s in fixed]
    assert len(keys) == len(set(keys)) == len(starts) - 2


def test_start_reaching_a_finished_minimum_stops_early(ct_noisy):
    """A start whose path reaches the minimum of a start already finished on the stage stops
    there (it would only go on into the same minimum), and is dropped as that start's twin."""
    near = CookTorranceParams(0.2, [0.8, 0.6, 0.4], [0.03, 0.05, 0.1])
    far = CookTorranceParams(0.25, [0.6, 0.5, 0.3], [0.05, 0.05, 0.05])
    stages = [Stage(4096, keep=2, max_steps=60, round_steps=2)]
    res = fit(ct_noisy, config=CT, starts=[near, far], schedule=stages)
    first, second = res.stages[0]["starts"]
    assert "duplicate_of" not in first and first["status"].startswith("converged"), first
    assert second["duplicate_of"] == first["start"], second
    assert second["status"] == f"stopped: reached the minimum of [{first['start']}]", second
    alone = fit(ct_noisy, config=CT, starts=[far], schedule=stages).stages[0]["starts"][0]
    # Here the stall rule would have ended it as soon (a simple problem); on stand-ins of MERL
    # materials the rule saves whole rounds (campaigns/RESULTS.md).
    assert alone["status"].startswith("converged") and second["steps"] <= alone["steps"]
    assert alone["rms"] == pytest.approx(second["rms"], rel=1e-5)
    assert res.converged and res.rmse_fit == first["rms"]


def test_floor_warning_flags_a_visibly_wrong_body():
    """The fitted model's diffuse floor against the measured one (per channel, where the body is
    visible): red-specular-plastic fitted with ``--metric linear`` came out ρ_d = 1, 1, 0, a
    yellow sphere for a red one, with exit 0 and no word."""
    from twoscale.fit.evaluation import FLOOR_RATIO_WARN, FLOOR_VISIBLE, floor_warnings

    measured = np.array([0.03, 0.01, 0.008])  # 1/sr: a red body (π × 0.03 ≈ 0.09 visible)
    assert floor_warnings(measured * 1.4, measured) == []
    assert floor_warnings(measured / 1.4, measured, "linear") == []
    (line,) = floor_warnings(measured * np.array([4.55, 30.1, 1.0]), measured, "linear")
    assert "R: 4.55×, G: 30.1×" in line and "B:" not in line
    assert "the linear metric weighs the highlight" in line
    (line,) = floor_warnings(measured * np.array([1.0, 0.1, 0.1]), measured, "blend")
    # G (π × 0.01 ≈ 0.031) is visible, B (π × 0.008 ≈ 0.025) is not.
    assert "G: 0.1×" in line and "B:" not in line and "linear metric" not in line
    # Too faint to see in either: not flagged, whatever the ratio (a metal's far tail).
    faint = np.full(3, 0.5 * FLOOR_VISIBLE / math.pi)
    assert floor_warnings(faint * (FLOOR_RATIO_WARN * 0.6), faint / 2) == []
    # No measured floor at all, a visible fitted one: flagged.
    (line,) = floor_warnings(np.array([0.1, 0.0, 0.0]), np.zeros(3))
    assert "R: inf×" in line

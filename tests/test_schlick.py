"""Schlick's form of a dielectric coat's Fresnel reflectance (``ModelConfig(fresnel="schlick")``,
docs/model.md §3.1) and the fit's choice between it and the exact equations (§8)."""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import twoscale
from twoscale import ModelConfig, TwoScaleParams, fresnel
from twoscale.fit import Stage, fit, synthetic
from twoscale.fit.material_type import (
    FRESNEL_TIE_RTOL,
    FRESNEL_TRY_RTOL,
    choose_fresnel,
    fresnel_choice_applies,
    resolve_fresnel,
    schlick_worth_trying,
)

#: Compiled with most XLA optimisations off (tests/conftest.py): this module's time is compilation
#: (measured alone on the 2-core machine, 2026-12-06: fast set 23.4 → 18.4 s).
COMPILE_QUICKLY = True

EXACT = ModelConfig(material="plastic", diffuse_fresnel=False)
SCHLICK = dataclasses.replace(EXACT, fresnel="schlick")
PARAMS = TwoScaleParams.plastic(
    0.12, 1.3, (1.9, 1.7, 1.5), (0.25, 0.4, 0.6), sigma_s=0.02, b=1.2, c=2.0
)
WI = jnp.array([[0.3, 0.0, 0.954], [0.0, 0.8, 0.6], [0.99, 0.0, 0.141]])
WO = jnp.array([[-0.3, 0.0, 0.954], [0.5, -0.2, 0.843], [-0.7, 0.1, 0.707]])
WI, WO = (v / jnp.linalg.norm(v, axis=-1, keepdims=True) for v in (WI, WO))


def test_schlick_values_ends_and_dtype():
    eta = jnp.array([1.0, 1.5, 1.95, 4.0])
    f0 = ((eta - 1) / (eta + 1)) ** 2
    np.testing.assert_allclose(fresnel.schlick(1.0, eta), f0, rtol=1e-15)
    np.testing.assert_allclose(fresnel.schlick(1.0, eta), fresnel.dielectric(1.0, eta), rtol=1e-12)
    np.testing.assert_allclose(fresnel.schlick(0.0, eta), 1.0)
    c = math.cos(math.radians(60.0))
    e = (1 + math.sqrt(0.107)) / (1 - math.sqrt(0.107))  # F0 = 0.107, η ≈ 1.97
    np.testing.assert_allclose(fresnel.schlick(c, e), 0.107 + 0.893 * 0.5**5, rtol=1e-12)
    # Flatter than the exact curve at mid angles, steeper towards grazing (docstring's numbers).
    np.testing.assert_allclose(fresnel.dielectric(c, e), 0.158, atol=5e-4)
    c85 = math.cos(math.radians(85.0))
    np.testing.assert_allclose(fresnel.schlick(c85, e), 0.673, atol=5e-4)
    np.testing.assert_allclose(fresnel.dielectric(c85, e), 0.630, atol=5e-4)
    out = fresnel.schlick(jnp.float32(0.5), jnp.float32(1.5))
    assert out.dtype == jnp.float32
    # Gradients finite at both ends and at η = 1.
    for cos in (0.0, 1.0, 0.3):
        g = jax.grad(lambda x, e: fresnel.schlick(x, e), argnums=(0, 1))(cos, 1.0)
        assert all(np.isfinite(float(v)) for v in g)


def test_schlick_config():
    with pytest.raises(ValueError, match="conductor keeps"):
        ModelConfig(fresnel="schlick")
    with pytest.raises(ValueError, match="q_mode='full'"):
        ModelConfig(material="plastic", fresnel="schlick", q_mode="full")
    with pytest.raises(ValueError, match="fresnel"):
        ModelConfig(material="plastic", fresnel="approximate")
    from twoscale.fit.adapters import config_from_dict, config_to_dict

    assert config_from_dict(config_to_dict(SCHLICK)) == SCHLICK
    old = {k: v for k, v in config_to_dict(EXACT).items() if k != "fresnel"}  # an older record
    assert config_from_dict(old).fresnel == "exact"


@pytest.mark.parametrize("diffuse_fresnel", [False, True])
def test_schlick_replaces_the_coat_reflectance_only(diffuse_fresnel):
    ex = dataclasses.replace(EXACT, diffuse_fresnel=diffuse_fresnel)
    sc = dataclasses.replace(SCHLICK, diffuse_fresnel=diffuse_fresnel)
    a, b = twoscale.lobes(PARAMS, WI, WO, ex), twoscale.lobes(PARAMS, WI, WO, sc)
    h = (WI + WO) / jnp.linalg.norm(WI + WO, axis=-1, keepdims=True)
    cd = jnp.sum(WI * h, axis=-1)[:, None]
    ratio = fresnel.schlick(cd, PARAMS.eta) / fresnel.dielectric(cd, PARAMS.eta)
    # The specular lobe is A_s F D G ...; the diffraction lobe carries Q = 2F: both scale by F.
    for name in ("specular", "diffraction"):
        np.testing.assert_allclose(b[name], a[name] * ratio, rtol=1e-10)
    if diffuse_fresnel:  # the varnish's transmissions 1 − F follow the coat's form
        t = lambda f, c: 1.0 - f(c[:, None], PARAMS.eta)  # noqa: E731
        r = (t(fresnel.schlick, WI[:, 2]) * t(fresnel.schlick, WO[:, 2])) / (
            t(fresnel.dielectric, WI[:, 2]) * t(fresnel.dielectric, WO[:, 2])
        )
        np.testing.assert_allclose(b["diffuse"], a["diffuse"] * r, rtol=1e-10)
    else:  # the Lambertian body has no coat
        np.testing.assert_array_equal(b["diffuse"], a["diffuse"])


def test_fresnel_twins_share_one_compiled_function():
    """A run-time selector (``schlick=``) gives each static form's values, on the per-pair and
    the fit's per-bin paths (diffuse layer through the varnish included; the gradients: the
    slow test below); the fit's adapters carry the form as an array, so the exact and Schlick
    twins' problems are traced once, and each reports its own form."""
    from twoscale.fit.adapters import adapter_for, compile_key
    from twoscale.fit.residuals import Problem
    from twoscale.model import brdf_from_factors, half_diff_factors, merl_grid

    ex = dataclasses.replace(EXACT, diffuse_fresnel=True)
    grid = merl_grid("lower")
    ih, jd = jnp.array([0, 3, 40]), jnp.array([5, 60, 85])
    cos_i, cos_o, phi = jnp.array([0.9, 0.5, 0.2]), jnp.array([0.8, 0.6, 0.1]), jnp.zeros(3)

    def cells(cfg, s):
        f = half_diff_factors(PARAMS, grid, cfg, schlick=s)
        return brdf_from_factors(PARAMS, f, ih, jd, cos_i, cos_o, phi, cfg, schlick=s)

    for static, flag in ((ex, False), (dataclasses.replace(ex, fresnel="schlick"), True)):
        sel = np.asarray(flag)
        np.testing.assert_array_equal(
            twoscale.brdf(PARAMS, WI, WO, ex, schlick=sel), twoscale.brdf(PARAMS, WI, WO, static)
        )
        np.testing.assert_array_equal(cells(ex, sel), cells(static, None))
    with pytest.raises(ValueError, match="dielectric coat"):
        twoscale.brdf(PARAMS, WI, WO, dataclasses.replace(ex, fresnel="schlick"), schlick=True)
    with pytest.raises(ValueError, match="dielectric coat"):
        twoscale.brdf(
            TwoScaleParams.conductor(0.1, 1.0, 1.5, 2.0),
            WI,
            WO,
            ModelConfig(diffraction=False),
            schlick=True,
        )

    a_ex, a_sc = adapter_for(EXACT), adapter_for(SCHLICK)
    assert a_ex.config == EXACT and a_sc.config == SCHLICK
    assert compile_key(a_ex) == compile_key(a_sc) == EXACT
    assert adapter_for(ModelConfig()).config == ModelConfig()
    traces = []

    @eqx.filter_jit
    def value(problem, params):
        traces.append(problem.adapter.schlick)
        return problem.adapter.evaluate(params, WI, WO)

    out = [value(Problem(a, None, "blend"), PARAMS) for a in (a_ex, a_sc)]
    assert len(traces) == 1
    np.testing.assert_array_equal(out[0], twoscale.brdf(PARAMS, WI, WO, EXACT))
    np.testing.assert_array_equal(out[1], twoscale.brdf(PARAMS, WI, WO, SCHLICK))


@pytest.mark.slow
def test_fresnel_selector_gradients_equal_the_static_forms():
    """Slow set: the selector's gradients equal each static form's (the fit differentiates
    through the selector; its values are checked by the test above, its forward-mode derivatives by every fit
    of a dielectric in tests/test_fit.py and tests/test_schlick.py)."""
    ex = dataclasses.replace(EXACT, diffuse_fresnel=True)
    for static, flag in ((ex, False), (dataclasses.replace(ex, fresnel="schlick"), True)):
        sel = np.asarray(flag)
        g_sel = jax.grad(lambda p, s=sel: twoscale.brdf(p, WI, WO, ex, schlick=s).sum())(PARAMS)
        g_static = jax.grad(lambda p, c=static: twoscale.brdf(p, WI, WO, c).sum())(PARAMS)
        leaves = zip(*map(jax.tree_util.tree_leaves, (g_sel, g_static)), strict=True)
        for a, b in leaves:
            np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-300)


@pytest.mark.slow
def test_schlick_gradients_grid_path_and_float32():
    """Slow set (≈ 22 s on 2 cores): by default Schlick's form is checked by
    test_schlick_replaces_the_coat_reflectance_only, and the code it feeds (the coat's
    reflectance in the per-pair and grid paths, float32) by tests/test_model.py and
    tests/test_grid.py."""
    g = jax.grad(lambda p: twoscale.brdf(p, WI, WO, SCHLICK).sum())(PARAMS)
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves(g))
    assert float(jnp.abs(g.eta).sum()) > 0.0
    grid = np.asarray(twoscale.brdf_merl(PARAMS, SCHLICK))
    wi, wo = twoscale.merl.grid_directions()
    idx = (np.array([3, 40, 85]), np.array([10, 60, 80]), np.array([0, 50, 170]))
    np.testing.assert_allclose(
        grid[idx], np.asarray(twoscale.brdf(PARAMS, wi[idx], wo[idx], SCHLICK)), rtol=1e-9
    )
    p32 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), PARAMS)
    out = twoscale.brdf(p32, WI.astype(jnp.float32), WO.astype(jnp.float32), SCHLICK)
    assert out.dtype == jnp.float32 and bool(jnp.all(jnp.isfinite(out)))


def test_choose_fresnel_and_resolve():
    assert choose_fresnel(0.10, 0.10 * (1 - 2 * FRESNEL_TIE_RTOL))[0] == "schlick"
    assert choose_fresnel(0.10, 0.10 * (1 - 0.5 * FRESNEL_TIE_RTOL))[0] == "exact"  # a tie
    assert choose_fresnel(0.10, 0.12)[0] == "exact"
    assert choose_fresnel(0.10, math.inf)[0] == "exact"
    # Worth fitting the full model with Schlick's form too: from a smaller gain than the tie.
    assert FRESNEL_TRY_RTOL < FRESNEL_TIE_RTOL
    assert schlick_worth_trying(0.10, 0.10 * (1 - 0.5 * FRESNEL_TIE_RTOL))
    assert not schlick_worth_trying(0.10, 0.10 * (1 - 0.5 * FRESNEL_TRY_RTOL))
    assert not schlick_worth_trying(0.10, 0.12) and not schlick_worth_trying(0.10, math.inf)
    assert schlick_worth_trying(math.inf, 0.10)
    both = [ModelConfig(), EXACT]
    assert resolve_fresnel(both, None, protocol=True) == (both, "auto")
    assert resolve_fresnel(both, None, protocol=False) == (both, None)
    fixed, mode = resolve_fresnel(both, "schlick", protocol=False)
    assert mode is None and fixed == [ModelConfig(), SCHLICK]  # the conductor keeps its form
    with pytest.raises(ValueError, match="fresnel must be"):
        resolve_fresnel(both, "yes", protocol=False)
    assert fresnel_choice_applies(EXACT) and not fresnel_choice_applies(SCHLICK)
    assert not fresnel_choice_applies(ModelConfig())
    assert not fresnel_choice_applies(dataclasses.replace(EXACT, q_mode="full"))


@pytest.mark.parametrize("starts", ["default", "few"])
@pytest.mark.parametrize("winner", ["schlick", "exact", "near"])
def test_fresnel_auto_branches_on_the_special_case(monkeypatch, winner, starts):
    """The driver's ``fresnel="auto"`` path without a solve (the screening stages stubbed with
    the RMS each form should reach): the plastic's special case is fitted with both forms; when
    Schlick's fits it better by more than ``FRESNEL_TRY_RTOL`` the full model goes on with both
    forms, each from nested starts of its own special case, even where that is within the tie
    (``"near"``: 1 % better, the special case's choice the exact form); with ``starts="few"``,
    --preview, the special case's choice alone (with its tie); else the exact form alone. The
    real fits: the slow test below."""
    from types import SimpleNamespace

    from twoscale.baselines import CookTorranceConfig, CookTorranceParams
    from twoscale.fit import driver
    from twoscale.fit.material_type import resolve_configs
    from twoscale.fit.starts import data_stats

    data = synthetic(
        CookTorranceParams(0.2, [0.5, 0.5, 0.5], [0.1, 0.1, 0.1]), CookTorranceConfig("ggx")
    )
    prep = SimpleNamespace(stats=data_stats(np.asarray(data.values), np.asarray(data.valid)))
    screened = []

    def screening(prep_, groups, cands, stages, opts, say, choose, warm=None):
        forms = [groups[c.group].adapter.config.fresnel for c in cands]
        screened.append(forms)
        for c, form in zip(cands, forms, strict=True):
            c.cost = {"schlick": {"schlick": 0.5, "exact": 1.0}, "near": {"schlick": 0.99}}.get(
                winner, {}
            ).get(form, 1.0)
        log = [{"n_cells_used": 4096}]
        return sorted(cands, key=lambda c: c.cost), log, None, {}

    monkeypatch.setattr(driver, "_run_schedule", screening)
    settings = driver.FitSettings(
        starts=starts, stages=(Stage(4096, 1, 5), Stage(8192, 1, 5)), fresnel="auto"
    )
    warmed = []  # the full models' configurations whose solves were queued for compiling

    class Warm:
        def submit(self, g, y):
            if g.adapter.config.diffraction:
                warmed.append(g.adapter.config.fresnel)

        def submit_call(self, key, fn):
            pass

    configs, groups, cands, selection, decided = driver._make_starts(
        prep, resolve_configs(None, "plastic"), settings, lambda msg: None, Warm()
    )
    # The full model's solve is queued once, at once, before the special cases say which form
    # goes on: the compiled solve of a dielectric coat serves both forms (the form is an array
    # of the adapter, see test_fresnel_twins_share_one_compiled_function).
    assert warmed == ["exact"]
    assert len(screened) == 1 and set(screened[0]) == {"exact", "schlick"}
    assert cands and all(groups[c.group].adapter.config.diffraction for c in cands)
    special = selection["plastic"]["special_case"]
    assert special["chosen"] == ("exact" if winner == "near" else winner)
    assert special["n_cells"] == 4096
    forms = [c.fresnel for c in configs]
    if winner == "exact" or (winner == "near" and starts == "few"):
        assert forms == ["exact"]
        assert selection["plastic"]["chosen"] == "exact"
    elif starts == "few":
        assert forms == ["schlick"] and selection["plastic"]["chosen"] == "schlick"
        assert "special case" in selection["plastic"]["reason"]
    else:
        assert forms == ["exact", "schlick"]
    assert all(c.diffraction and c.material == "plastic" for c in configs)
    assert decided is None  # one material type: nothing for the highlight to decide
    nested = [groups[c.group].adapter.config.fresnel for c in cands if "nested" in c.label]
    assert sorted(nested) == sorted(forms), [c.label for c in cands]


@pytest.mark.slow
def test_fit_chooses_schlick_for_a_schlick_plastic_and_records_it(tmp_path):
    """``fresnel="auto"``: a plastic made with Schlick's form is fitted with it; the record keeps
    the comparison and loads back. Slow set (four configurations compiled, the default starts:
    the full model's comparison of the two forms, which starts="few" skips); by default
    test_fresnel_auto_branches_on_the_special_case runs the driver's branches and
    test_choose_fresnel_and_resolve the rule."""
    cfg = dataclasses.replace(SCHLICK, apparatus=True)
    true = TwoScaleParams.plastic(
        0.1, 1.2, (1.8, 1.7, 1.6), (0.1, 0.3, 0.5), sigma_s=0.01, b=1.0, c=2.0, e=0.8
    )
    data = synthetic(true, cfg, noise=0.01, seed=3)
    stages = [Stage(4096, 1, 30), Stage(8192, 1, 10)]
    res = fit(
        data,
        config=dataclasses.replace(EXACT, apparatus=True),
        fresnel="auto",
        schedule=stages,
    )
    sel = res.fresnel_selection["plastic"]
    # The special case favours Schlick's form, so the full model is fitted with both forms and
    # keeps it by its own RMS.
    assert sel["special_case"]["chosen"] == "schlick", sel
    assert sel["chosen"] == "schlick" and sel["stage"] == 1, sel
    assert sel["rms"]["schlick"] < (1 - FRESNEL_TIE_RTOL) * sel["rms"]["exact"]
    labels = [e["start"] for e in res.stages[0]["starts"]]
    assert any(lab.startswith("plastic (Schlick)") for lab in labels)
    assert any(lab.startswith("plastic nested") for lab in labels)
    assert res.model_config.fresnel == "schlick" and res.settings["fresnel"] == "auto"
    loaded = twoscale.load_result(res.save(tmp_path / "params.json"))
    assert loaded.fresnel_selection == res.fresnel_selection
    assert loaded.model_config == res.model_config

"""Starts and cross-seeding: every start lies strictly inside the parameter ranges
(:func:`twoscale.fit.candidates.inside_bounds`), and a type whose best start is behind after the
first stage gets a start with the leader's geometry and its own type parameters
(:func:`twoscale.fit.candidates.cross_seed`, :func:`twoscale.fit.driver._cross_seeds`)."""

import dataclasses
import math

import numpy as np

from twoscale import ModelConfig, TwoScaleParams
from twoscale.fit.adapters import START_K_MAX, adapter_for
from twoscale.fit.candidates import SHARED_FIELDS, START_U_MAX, cross_seed, make_candidates
from twoscale.fit.driver import _cross_seeds
from twoscale.fit.residuals import Problem
from twoscale.fit.starts import DataStats
from twoscale.params import bounds_for

CONDUCTOR = TwoScaleParams.conductor(
    0.05, 0.8, (1.2, 1.3, 1.4), (2.0, 2.5, 3.0), sigma_s=0.05, b=2.0, c=1.5, e=0.7, m=3.0
)
PLASTIC = TwoScaleParams.plastic(
    0.3, 2.0, (1.5, 1.6, 1.7), (0.1, 0.2, 0.3), sigma_s=0.2, b=30.0, c=3.0, e=1.5, m=6.0
)


def _setup(fixed=None):
    cfg = ModelConfig(apparatus=True, apparatus_knee=True)  # the MERL protocol's e and m
    configs = [dataclasses.replace(cfg, material=m) for m in ("conductor", "plastic")]
    return make_candidates(configs, [[("a", CONDUCTOR)], [("b", PLASTIC)]], fixed or {})


def _params(cand, group):
    return Problem(group.adapter, group.layout, "log").params(cand.y, group.frozen)


def test_cross_seed_takes_the_geometry_and_keeps_the_type_parameters():
    groups, (cc, pc) = _setup()
    seed = cross_seed(pc, groups[1], cc, groups[0])
    assert seed.group == cc.group and math.isinf(seed.cost)
    assert seed.label == "conductor with the geometry of [plastic b]"
    got = _params(seed, groups[0])
    assert got.material == "conductor" and got.rho_d is None
    for name in SHARED_FIELDS:
        np.testing.assert_allclose(getattr(got, name), getattr(PLASTIC, name), rtol=1e-9)
    for name in ("eta", "k"):
        np.testing.assert_allclose(getattr(got, name), getattr(CONDUCTOR, name), rtol=1e-9)

    back = _params(cross_seed(cc, groups[0], pc, groups[1]), groups[1])
    assert back.material == "plastic" and back.k is None
    for name in SHARED_FIELDS:
        np.testing.assert_allclose(getattr(back, name), getattr(CONDUCTOR, name), rtol=1e-9)
    for name in ("eta", "rho_d"):
        np.testing.assert_allclose(getattr(back, name), getattr(PLASTIC, name), rtol=1e-9)
    # Nothing to change (the same geometry already): no start.
    assert cross_seed(cc, groups[0], cc, groups[0]) is None


def test_cross_seed_leaves_fixed_parameters_alone():
    groups, (cc, pc) = _setup({"p": 1.0, "b": 5.0})
    got = _params(cross_seed(pc, groups[1], cc, groups[0]), groups[0])
    assert float(got.p) == 1.0 and abs(float(got.b) - 5.0) < 1e-12
    np.testing.assert_allclose(got.beta, PLASTIC.beta, rtol=1e-9)
    np.testing.assert_allclose(got.c, PLASTIC.c, rtol=1e-9)


def test_cross_seeds_go_to_the_types_behind_only():
    groups, (cc, pc) = _setup()
    said = []
    cc.cost, pc.cost = 0.3, 0.2
    (seed,) = _cross_seeds([cc, pc], groups, said.append)
    assert seed.group == cc.group and "geometry of [plastic b]" in seed.label
    assert "0.3 against 0.2" in said[-1]
    cc.cost = 0.1
    (seed,) = _cross_seeds([cc, pc], groups, said.append)
    assert seed.group == pc.group and "geometry of [conductor a]" in seed.label
    # One type (or no finite fit of the other): nothing to seed.
    assert _cross_seeds([cc], groups, said.append) == []
    pc.cost = math.inf
    assert _cross_seeds([cc, pc], groups, said.append) == []


def test_type_rms_is_the_plain_log_rms_of_the_same_cells():
    """The types are compared on the plain log metric; the driver computes it with the group's
    compiled (scaled-log or blend) solve on the buffer with every scale 1, which must equal the plain log
    metric's own sum of squares on the same cells."""
    import jax.numpy as jnp

    from twoscale.fit import Stage, driver, solver, synthetic

    cfg = ModelConfig(material="plastic", diffraction=False, apparatus=True)
    true = TwoScaleParams.plastic(0.1, 1.2, (1.5, 1.5, 1.5), (0.1, 0.3, 0.6), e=0.8)
    data = synthetic(true, cfg, noise=0.01, seed=3)
    prep = driver._prepare(data, None, 0)
    start = true.replace(beta=0.15, p=0.9).for_config(cfg)
    (g,), (cand,) = make_candidates([cfg], [[("a", start)]], {})
    n_active, n_cells = prep.stage_cells(Stage(4096, 1, 5))
    rr = solver.jit_sum_squares(
        Problem(g.adapter, g.layout, "log"), cand.y, g.frozen, prep.buffer, jnp.int32(n_active)
    )
    want = math.sqrt(float(rr) / (n_cells * 3))
    assert want > 0.0
    for metric in ("scaled-log", "blend"):  # both hold scaled residuals; both compare on "log"
        opts = solver.SolverSettings(metric, "lm", solver.RTOL, solver.ATOL, solver.SE_TOL)
        got = driver._type_rms(cand, g, opts, prep.buffer, n_active, n_cells)
        assert abs(got / want - 1.0) < 1e-10, metric
    # Fitted on the plain log metric already: the candidate's own cost.
    cand.cost = 0.123
    log_opts = solver.SolverSettings("log", "lm", solver.RTOL, solver.ATOL, solver.SE_TOL)
    assert driver._type_rms(cand, g, log_opts, prep.buffer, n_active, n_cells) == 0.123


def test_starts_on_or_beyond_a_bound_are_moved_inside():
    """A start value on or beyond a bound maps to |u| = 40, where no solver step moves it (a
    conductor start with k = 12.5 for k ≤ 10 stayed at 10: 1.7x the reachable RMS on the
    benchmark's synthetic conductor). Starts are moved to 1e-3 of the range inside; fixed
    parameters keep their values."""
    cfg = ModelConfig(apparatus=True)
    outside = TwoScaleParams.conductor(
        1.0, 0.8, (1.2, 7.0, 0.01), (12.5, 10.0, 0.0), sigma_s=0.0, b=2.0, c=5.0, e=0.7
    )
    groups, (cand,) = make_candidates([cfg], [[("edge", outside)]], {"c": 5.0})
    got = _params(cand, groups[0])
    assert np.all(np.abs(np.asarray(cand.y)) <= START_U_MAX + 1e-12)
    for name in ("beta", "eta", "k", "sigma_s"):
        bound = bounds_for(name, "conductor")
        x = np.atleast_1d(np.asarray(getattr(got, name)))
        assert np.all(x > bound.lo) and np.all(x < bound.hi), (name, x)
    k = np.asarray(got.k)
    assert 9.98 < k[0] < 10.0 and 9.98 < k[1] < 10.0 and 0.0 < k[2] < 0.02
    assert 0.0 < float(got.sigma_s) < 2e-3
    assert float(got.c) == 5.0  # fixed: untouched
    # Values inside the range are kept as they were.
    groups, (cand,) = make_candidates([cfg], [[("a", CONDUCTOR)]], {})
    for name in ("beta", "p", "eta", "k", "sigma_s", "b", "c", "e"):
        np.testing.assert_allclose(
            getattr(_params(cand, groups[0]), name), getattr(CONDUCTOR, name), rtol=1e-9
        )


def test_conductor_starts_keep_k_inside_its_range():
    """A bright, sharp peak asks for F0 near 1: the start's k stays at most START_K_MAX."""
    stats = DataStats(peak=np.array([5e4, 2e3, 50.0]), floor=np.full(3, 1e-3), width=0.01)
    for diffraction in (False, True):
        cfg = ModelConfig(apparatus=True, diffraction=diffraction)
        starts = adapter_for(cfg).starts(stats)
        k = np.array([np.asarray(p.k) for _, p in starts])
        assert np.all(k <= START_K_MAX) and np.all(k > 0)
        assert np.any(k == START_K_MAX)  # the red channel's F0 asked for more

"""Fit a BRDF model to MERL data: starts, coarse-to-fine schedule, Levenberg-Marquardt.

Protocol (docs/model.md §8): float64; cosine-weighted linear or log residuals over the valid cells
(optionally only ``θ_i, θ_o ≤ max_theta``); parameters optimised in unconstrained space; several
starts; RMSE reported on all valid cells. The schedule is coarse to fine: every start is fitted
on a small random subsample of the cells, the best few go on to a larger subsample, and the best
one is refined on all fitted cells. Every stage uses a fixed number of cells, so one compiled
solver serves all its starts.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence

import jax
import numpy as np

from twoscale.fit import solver as _solver
from twoscale.fit.adapters import START_E, START_M, adapter_for, compile_key, floor_albedo_start
from twoscale.fit.candidates import (
    NESTED_GRID,
    check_fixed,
    cross_seed,
    keep_best,
    make_candidates,
    nested_starts,
    same_solution,
)
from twoscale.fit.cells import CHUNK, pack, pair_cells, select_cells, with_scale
from twoscale.fit.evaluation import (
    data_warnings,
    fit_warnings,
    floor_warnings,
    predict_cells,
    rmse,
    rmse_within,
    standard_errors,
    warm_evaluation,
)
from twoscale.fit.material_type import (
    FRESNEL_TIE_RTOL,
    FRESNEL_TRY_RTOL,
    body_levels,
    choose_fresnel,
    choose_type,
    faint_floor,
    fall_off_of,
    fresnel_choice_applies,
    highlight_suggests_conductor,
    preview_type,
    resolve_configs,
    resolve_fresnel,
    schlick_worth_trying,
    type_from_body,
)
from twoscale.fit.record import FitResult, package_versions
from twoscale.fit.residuals import DEFAULT_METRIC, Problem, check_metric, residuals_per_cell
from twoscale.fit.schedule import Stage, resolve_schedule
from twoscale.fit.starts import data_stats, floor_level


class FitError(RuntimeError):
    """The fit could not produce a result (e.g. non-finite cost for every start)."""


@dataclasses.dataclass
class _Prepared:
    """Host-side preparation shared by every stage (and by the nested special-case fit)."""

    selection: object  # CellSelection
    stats: object  # DataStats
    pairs: object  # Pairs, in random order: each stage fits a prefix
    cells_upto: np.ndarray  # cells held by the first k + 1 pairs
    buffer: dict  # device buffer of all pairs
    log_scale: np.ndarray  # (C,): the "scaled-log" metric's scale, from the fitted cells
    valid_grid: np.ndarray  # (90, 90, 180) bool: the data's valid cells

    @property
    def n_fit(self) -> int:
        return len(self.selection.fit)

    def stage_cells(self, stage: Stage) -> tuple[int, int]:
        """``(n_active chunks, n_cells)`` of a stage: whole chunks, the nearest number of cells
        (every pair for the full stage)."""
        want = self.n_fit if stage.n_cells is None else min(stage.n_cells, self.n_fit)
        n_pairs = int(np.searchsorted(self.cells_upto, want)) + 1  # pairs holding `want` cells
        if stage.n_cells is None:
            n_active = -(-n_pairs // CHUNK)
        else:
            n_active = max(1, round(n_pairs / CHUNK))
        n_cells = int(self.cells_upto[min(n_active * CHUNK, len(self.pairs)) - 1])
        return n_active, n_cells


#: The metric the material types are compared with, when it is not the fitted one. The type is
#: a statement about the interface (the highlight's height, colour and change with θ_d), which
#: lives in the bright cells; the scaled log metric weighs every cell by its relative error, so
#: there the dark floor, which a plastic's diffuse layer fits and a conductor has no term for,
#: would decide. The same fits are therefore compared on the plain log metric (docs/model.md §8);
#: so are those of the blend, which holds the scaled log residuals too.
TYPE_METRIC = {"scaled-log": "log", "blend": "log"}


def _type_rms(cand, group, opts, buffer, n_active: int, n_cells: int) -> float:
    """A type's best start's RMS as :func:`choose_type` compares it: its cost, or on
    :data:`TYPE_METRIC`'s metric over the same cells.

    The plain log metric is the scaled one with every scale 1, so it is computed by the
    group's solve, compiled already, on the buffer with ``s = 1`` (one step, which only
    evaluates its start): no function is compiled for it (that cost ≈ 1 s per fit). With
    ``s = 1`` the blend's two residuals of a cell are equal: its RMS is the plain log one.
    """
    if opts.metric not in TYPE_METRIC:  # both metrics it maps map to "log"
        return cand.cost
    m = n_cells * group.adapter.config.n_channels * residuals_per_cell(opts.metric)
    unscaled = with_scale(buffer, 1.0)
    return math.sqrt(_solver.start_cost(cand.y, group, unscaled, n_active, m, opts) / m)


def _prepare(data, max_theta_deg, seed) -> _Prepared:
    selection = select_cells(data, max_theta_deg=max_theta_deg)
    stats = data_stats(np.asarray(data.values), np.asarray(data.valid))
    rng = np.random.default_rng(seed)
    # One buffer for every stage: the fitted cells in reciprocal pairs, in random order; each
    # stage fits a prefix (a uniform random subsample of the pairs).
    pairs = pair_cells(selection.fit)
    pairs = pairs.take(rng.permutation(len(pairs)))
    cells_upto = np.cumsum(pairs.w.sum(axis=1)).astype(np.int64)
    log_scale = selection.fit.log_scale()
    buffer, _ = pack(pairs, log_scale=log_scale)
    return _Prepared(selection, stats, pairs, cells_upto, buffer, log_scale, np.asarray(data.valid))


def _choose_groups(kept, groups, n_cells: int, stage: int, say):
    """Per material type, the group that goes on: its only one, or of its two Fresnel forms
    (``fresnel="auto"``) the one :func:`~twoscale.fit.material_type.choose_fresnel` picks from
    their best RMS on this stage. Returns ``({material: group index}, {material: choice})``."""
    best = {}  # group index -> best cost
    for c in kept:
        best[c.group] = min(best.get(c.group, math.inf), c.cost)
    forms: dict = {}
    for gi in best:
        form = getattr(groups[gi].adapter.config, "fresnel", "exact")
        forms.setdefault(groups[gi].adapter.material, {})[form] = gi
    chosen, choice = {}, {}
    for mat, by_form in forms.items():
        if len(by_form) == 1:
            chosen[mat] = next(iter(by_form.values()))
            continue
        ex, sc = by_form["exact"], by_form["schlick"]
        form, reason = choose_fresnel(best[ex], best[sc])
        chosen[mat] = sc if form == "schlick" else ex
        choice[mat] = {
            "rms": {"exact": best[ex], "schlick": best[sc]},
            "chosen": form,
            "reason": reason,
            "stage": stage,
            "n_cells": n_cells,
        }
        say(f"{mat} coat's Fresnel form: {form} ({reason}; full model)")
    return chosen, choice


def _twin_finder(cand, done):
    """``twin(y)`` for :func:`~twoscale.fit.solver.refine`: the label of the first start of
    ``done`` (finished on this stage) whose minimum ``cand`` at ``y`` has reached, or None."""

    def twin(y):
        probe = dataclasses.replace(cand, y=y)
        return next((d.label for d in done if same_solution(d, probe)), None)

    return twin


def _cross_seeds(kept, groups, say) -> list:
    """After the first stage: each material type whose best start is behind the best of all
    gets one more start, its own type parameters with the leader's geometry
    (:func:`~twoscale.fit.candidates.cross_seed`), refined with the others from the next stage
    on, so the type choice compares fits that searched the same basin."""
    best = {}  # material -> its best kept candidate
    for c in kept:
        mat = groups[c.group].adapter.material
        if math.isfinite(c.cost) and (mat not in best or c.cost < best[mat].cost):
            best[mat] = c
    if len(best) < 2:
        return []
    top = min(best.values(), key=lambda c: c.cost)
    out = []
    for c in best.values():
        if c is top:
            continue
        seed = cross_seed(top, groups[top.group], c, groups[c.group])
        if seed is not None:
            say(f"stage 1: [{seed.label}] added (rms {c.cost:.5g} against {top.cost:.5g})")
            out.append(seed)
    return out


def _run_schedule(
    prep: _Prepared, groups, cands, stages, opts, say, choose: bool, warm=None, floor=None
):
    """Fit every candidate through the stages; returns ``(candidates best first, stage log,
    type selection, Fresnel choice)``. The Fresnel form of a type fitted with both, then the
    material type, are chosen after the second-last stage (or the only one). ``warm``: a
    :class:`~twoscale.fit.solver.Warmup` that compiles the groups' solves ahead of their use.
    ``floor``: ``floor(kept, groups) -> kept``, called on the chosen type's candidates when a
    stage follows the choice (:func:`_floor_converter`: a conductor's floor)."""
    if warm is not None:
        for c in cands:  # in order of first use
            warm.submit(groups[c.group], c.y)
    stage_log = []
    type_selection = None
    fresnel_choice = {}
    for si, stage in enumerate(stages):
        n_active, n_cells = prep.stage_cells(stage)
        if warm is not None and choose and si == len(stages) - 1 and cands:
            # The configuration is final: its lobe evaluation (pictures, albedo table) compiles
            # while the last stage runs.
            g = groups[cands[0].group]
            p_best = Problem(g.adapter, g.layout, opts.metric).params(cands[0].y, g.frozen)
            warm.submit_call(
                ("lobes", compile_key(g.adapter)),
                lambda a=g.adapter, p=p_best: warm_evaluation(a, p),
            )
        entries = []
        done: list = []  # starts finished on this stage, each in a minimum of its own
        for ci, cand in enumerate(cands):
            g = groups[cand.group]
            m = n_cells * g.adapter.config.n_channels * residuals_per_cell(opts.metric)
            ts = time.perf_counter()
            if warm is not None:
                warm.wait(g)
            y, rr, jtj, steps, ok, msg = _solver.refine(
                cand, g, stage, prep.buffer, n_active, m, opts, _twin_finder(cand, tuple(done))
            )
            cost = math.sqrt(rr / m) if math.isfinite(rr) else math.inf
            cand.y, cand.cost, cand.steps, cand.status, cand.success = y, cost, steps, msg, ok
            cand.rr, cand.jtj, cand.m = rr, jtj, m
            say(
                f"stage {si + 1}/{len(stages)} ({n_cells} cells) start {ci + 1}/{len(cands)} "
                f"[{cand.label}]: rms {cost:.5g}, {steps} steps, {msg} "
                f"({time.perf_counter() - ts:.1f} s)"
            )
            entries.append({"start": cand.label, "rms": cost, "steps": steps, "status": msg})
            if math.isfinite(cost) and cand.twin is None:
                done.append(cand)
        stage_log.append({**stage.to_dict(), "n_cells_used": n_cells, "starts": entries})
        if not any(math.isfinite(c.cost) for c in cands):
            raise FitError("no start gave a finite fit (non-finite model values or residuals)")
        if si == 0 and not any(c.moves > 0 or c.success for c in cands):
            raise FitError("no start made any progress (every solver step was rejected)")
        kept, duplicates = keep_best(cands, groups, stage, si >= len(stages) - 2)
        for e in entries:
            if e["start"] in duplicates:
                e["duplicate_of"] = duplicates[e["start"]]
                say(f"stage {si + 1}: [{e['start']}] reached [{e['duplicate_of']}]: dropped")
        if choose and si == 0 and si < len(stages) - 2:
            kept = kept + _cross_seeds(kept, groups, say)
        if choose and len(groups) > 1 and (si == len(stages) - 2 or len(stages) == 1):
            chosen, fresnel_choice = _choose_groups(kept, groups, n_cells, si + 1, say)
            best = {}
            for mat, gi in chosen.items():
                c = min((c for c in kept if c.group == gi), key=lambda c: c.cost)
                g = groups[gi]
                best[mat] = (
                    _type_rms(c, g, opts, prep.buffer, n_active, n_cells),
                    Problem(g.adapter, g.layout, opts.metric).params(c.y, g.frozen),
                )
            by_material = {mat: groups[gi] for mat, gi in chosen.items()}
            if warm is not None:
                for g in by_material.values():
                    warm.wait_key(("grid", compile_key(g.adapter)))
            winner, reason = choose_type(best, body_levels(best, by_material, prep))
            rms = {k: v[0] for k, v in best.items()}
            type_selection = {
                "rms": rms,
                "metric": TYPE_METRIC.get(opts.metric, opts.metric),
                "chosen": winner,
                "reason": reason,
                "stage": si + 1,
                # Each type's best fit at this stage, so the one not chosen is not lost
                # (TwoScaleParams.from_dict reads it back).
                "params": {k: v[1].to_dict() for k, v in best.items()},
            }
            say(
                "material: "
                + ", ".join(f"{k} rms {v:.5g}" for k, v in rms.items())
                + f" -> {winner} ({reason})"
            )
            kept = [c for c in kept if c.group == chosen[winner]]
            if floor is not None and si < len(stages) - 1:
                kept = floor(kept, groups)
        cands = sorted(kept, key=lambda c: c.cost)
    return cands, stage_log, type_selection, fresnel_choice


#: Named start sets: ``"default"``, and ``"few"`` (what ``--preview`` uses): the special case
#: from p = 1 only (per material type), the full model from the nested start and the strong
#: lobe placed from the special case's highlight (:data:`~twoscale.fit.candidates.NARROW_START`)
#: only; other models from the middle one of their starts.
START_SETS = ("default", "few")


#: The nested-start grid of ``starts="few"`` (c, A_spec(0), b µm): none of
#: :data:`~twoscale.fit.candidates.NESTED_GRID`'s points, only the start placed from the
#: highlight. Measured on the 60 stand-ins' previews (2026-12-05) against the grid's strong lobe
#: at b = 30 µm, which it replaced: log RMSE lower on 8 (blue-metallic-paint2 0.158 → 0.113,
#: red-specular-plastic 0.189 → 0.160, hematite 0.162 → 0.146, pink-jasper 0.076 → 0.072, four
#: more by 0.4–1.9 %), higher on 2 (tungsten-carbide +0.3 %, fruitwood-241 +0.06 %), within
#: 0.05 % on 50.
FEW_NESTED_GRID = ()


def _split_floors(configs: list) -> tuple[list, dict]:
    """With several material types to choose from, the conductor's Lambertian floor
    (``ModelConfig.conductor_floor``) is left out until the type is chosen: returns the
    configurations to compare and ``{configuration without the floor: with it}``.

    Why: the types are told apart by the light a body carries (:func:`choose_type`'s body
    rule, which asks whether the conductor's fit makes the measured floor); a conductor with a
    floor of its own would blur that. Once the conductor has won, its last stage adds the floor
    (:func:`_floor_converter`): measured metals scatter a faint diffuse glow that the
    reference's conductor renders black (chrome: fitted RMS 0.2694 → 0.2466, tungsten-carbide
    0.2977 → 0.2608, ρ_d ≈ 0.003–0.006).
    """
    if len(configs) < 2:
        return configs, {}
    out, floors = [], {}
    for cfg in configs:
        if getattr(cfg, "conductor_floor", False) and cfg.has_diffuse:
            bare = dataclasses.replace(cfg, conductor_floor=False)
            floors[bare] = cfg
            cfg = bare
        out.append(cfg)
    return out, floors


def _types_holding(configs: list, fixed: dict, say) -> list:
    """The material types to compare that have every held parameter: holding ``k`` (a
    conductor's) or ``ρ_d`` (a plastic's body; a conductor's floor only after the type choice)
    fits those types only, and says so. :func:`~twoscale.fit.candidates.check_fixed` has
    refused names that no type has."""
    if len(configs) < 2 or not fixed:
        return configs
    kept = [c for c in configs if set(fixed) <= set(adapter_for(c).field_names)]
    if not kept:  # e.g. k and rho_d together: no single type has both
        raise ValueError(
            f"cannot fix {', '.join(sorted(fixed))} together: no material type has them all "
            "(pass --material / material=)"
        )
    if len(kept) < len(configs):
        left = sorted(
            {adapter_for(c).material for c in configs} - {adapter_for(c).material for c in kept}
        )
        chosen = sorted({adapter_for(c).material for c in kept})
        say(
            f"the held {', '.join(sorted(fixed))} leaves out the {', '.join(left)} type "
            f"(it has no such parameter): fitting the {', '.join(chosen)} only"
        )
    return kept


def _floor_converter(floors: dict, prep: _Prepared, settings, say, warm):
    """``floor(kept, groups)`` for :func:`_run_schedule`: the chosen conductor's candidates
    moved to its configuration with the floor (a group appended to ``groups``), their other
    parameters kept and ``ρ_d`` started at the data's floor (``π ρ_floor`` per channel)."""

    def convert(kept, groups):
        if not kept:
            return kept
        g = groups[kept[0].group]
        cfg = floors.get(g.adapter.config)
        if cfg is None:
            return kept
        rho0 = floor_albedo_start(prep.stats)
        problem = Problem(g.adapter, g.layout, settings.metric)
        starts = [(c.label, problem.params(c.y, g.frozen).replace(rho_d=rho0)) for c in kept]
        new_groups, new_cands = make_candidates([cfg], [starts], settings.fixed)
        groups.append(new_groups[0])
        for c, nc in zip(kept, new_cands, strict=True):
            nc.group, nc.label, nc.nested = len(groups) - 1, f"{c.label} + floor", c.nested
        if warm is not None:
            warm.submit(groups[-1], new_cands[0].y)
        say(
            "conductor: its Lambertian floor added for the last stage (ρ_d started at the "
            f"data's floor, {np.array2string(rho0, precision=3)})"
        )
        return new_cands

    return convert


def _preselect_type(configs: list, prep: _Prepared, settings, say):
    """With ``starts="few"`` and several material types: the type the data's diffuse body
    decides (:func:`~twoscale.fit.material_type.type_from_body`) is fitted alone. Returns
    ``(configs, type selection record or None)``."""
    materials = {getattr(c, "material", None) for c in configs}
    if settings.starts != "few" or len(materials) < 2:
        return configs, None
    decided = type_from_body(prep.stats)
    if decided is None or decided[0] not in materials:
        return configs, None
    winner, reason = decided
    say(f"material: {winner} ({reason})")
    kept = [c for c in configs if c.material == winner]
    return kept, {"rms": {}, "chosen": winner, "reason": reason, "stage": 0, "from_data": True}


def _few_data_starts(start_list):
    """The ``starts="few"`` subset of an adapter's starts: those from p = 1 (the two-scale
    models), or the middle start (models without p)."""
    out = [
        (label, s)
        for label, s in start_list
        if getattr(s, "p", None) is not None and float(s.p) == 1.0
    ]
    return out or start_list[len(start_list) // 2 :][:1]


@dataclasses.dataclass(frozen=True)
class FitSettings:
    """Every setting of a fit, validated, as one value (so no phase drops one on the way; the
    special-case fit of the nested starts runs with the same value)."""

    metric: str = DEFAULT_METRIC
    max_theta_deg: float | None = None
    fixed: dict = dataclasses.field(default_factory=dict)
    starts: str | tuple = "default"
    stages: tuple[Stage, ...] = resolve_schedule("default")
    solver: str = "lm"
    seed: int = 0
    rtol: float = _solver.RTOL
    atol: float = _solver.ATOL
    se_tol: float = _solver.SE_TOL
    nested: bool = True
    material: str | None = None
    fresnel: str | None = None  # "auto": the fit chooses a dielectric coat's Fresnel form

    def __post_init__(self):
        check_metric(self.metric)
        if isinstance(self.starts, str) and self.starts not in START_SETS:
            raise ValueError(
                f"starts must be one of {START_SETS} or a list of parameters, got {self.starts!r}"
            )
        _solver.make_solver(self.solver, self.rtol, self.atol)  # check the name before any work

    @property
    def solver_settings(self) -> _solver.SolverSettings:
        return _solver.SolverSettings(self.metric, self.solver, self.rtol, self.atol, self.se_tol)

    def to_dict(self, stats) -> dict:
        """The ``settings`` entry of the fit record."""
        return {
            "metric": self.metric,
            "max_theta_deg": self.max_theta_deg,
            "material": self.material,
            "fresnel": self.fresnel,
            "fixed": {k: np.asarray(v).tolist() for k, v in self.fixed.items()},
            "starts": self.starts if isinstance(self.starts, str) else f"{len(self.starts)} given",
            "nested": self.nested,
            "schedule": [s.to_dict() for s in self.stages],
            "solver": self.solver,
            "rtol": self.rtol,
            "atol": self.atol,
            "se_tol": self.se_tol,
            "stall_rtol": _solver.STALL_RTOL,
            "stall_resolution": _solver.STALL_RESOLUTION,
            "initial_damping": _solver.INITIAL_DAMPING,
            "seed": self.seed,
            "chunk": CHUNK,
            "convention": "lower",
            "data_stats": stats.to_dict(),
        }


def _make_starts(prep: _Prepared, configs, settings: FitSettings, say, warm=None, floors=None):
    """Phase 2: the groups and candidates of every configuration; returns
    ``(configs, groups, candidates, fresnel_selection, type_selection)``.

    Default starts are placed from the data; with ``nested`` and the diffraction lobe on, the
    full model starts from a fit of its diffraction-off special case (same settings, the
    screening stages: every stage but the last; :func:`~twoscale.fit.candidates.nested_starts`). With
    ``settings.fresnel == "auto"``, a dielectric type's special case is fitted with the exact
    Fresnel equations and with Schlick's form; if Schlick's fits it better by more than
    :data:`~twoscale.fit.material_type.FRESNEL_TRY_RTOL`
    (:func:`~twoscale.fit.material_type.schlick_worth_trying`), the full model is fitted with both
    forms (a configuration with Schlick's form is appended, with its own nested starts) and
    :func:`_run_schedule` keeps one by the full model's RMS; otherwise the exact form alone goes
    on. ``fresnel_selection``: ``{material: {"special_case": ..., "chosen", "reason"}}`` (the
    full model's comparison is added after the schedule), ``None`` when nothing was compared.

    With ``starts="few"`` (``--preview``), both types to choose from and a data floor no more
    than a bare metal's faint scatter, the special cases' fits decide the type
    (:func:`~twoscale.fit.material_type.preview_type`: the conductor by the highlight, else the
    lower RMS): only that type's full model is fitted, a conductor with its floor (``floors``:
    :func:`_split_floors`) from the first stage; ``type_selection`` records it (``None`` where
    nothing was decided: the schedule chooses).
    """
    configs = list(configs)
    if not isinstance(settings.starts, str):
        start_lists = [[(f"start {i}", s) for i, s in enumerate(settings.starts)]]
        return configs, *make_candidates(configs, start_lists, settings.fixed), None, None
    selection = None
    type_record = None
    few = settings.starts == "few"
    floors = floors or {}
    # A bodiless material's preview: the special cases' fits decide the type (preview_type).
    bodiless_preview = (
        few
        and faint_floor(prep.stats)
        and {"conductor", "plastic"} <= {getattr(c, "material", None) for c in configs}
    )

    def data_starts(cfg):
        out = adapter_for(cfg).starts(prep.stats)
        return _few_data_starts(out) if few else out

    start_lists = [data_starts(cfg) for cfg in configs]
    if settings.nested and any(adapter_for(cfg).diffraction for cfg in configs):
        spec_cfgs = [dataclasses.replace(cfg, diffraction=False) for cfg in configs]
        twins = {}  # index of a dielectric configuration -> index of its Schlick twin
        if settings.fresnel == "auto":
            for gi, cfg in enumerate(configs):
                if cfg.diffraction and fresnel_choice_applies(cfg):
                    twins[gi] = len(spec_cfgs)
                    spec_cfgs.append(dataclasses.replace(spec_cfgs[gi], fresnel="schlick"))
        sub_fixed = {k: v for k, v in settings.fixed.items() if k not in ("sigma_s", "b", "c")}
        sub_groups, sub_cands = make_candidates(
            spec_cfgs, [data_starts(c) for c in spec_cfgs], sub_fixed
        )

        def warm_full(cfgs, grids: bool = False):
            """Queue the full models' solves (or, with ``grids``, their evaluation on the MERL
            grid, which the type choice and the record use)."""
            full = [(cfg, adapter_for(cfg).starts(prep.stats)) for cfg in cfgs]
            full = [(cfg, sl[:1]) for cfg, sl in full if sl]
            if not full:
                return
            f_groups, f_cands = make_candidates(
                [cfg for cfg, _ in full], [sl for _, sl in full], settings.fixed
            )
            for gi, g in enumerate(f_groups):
                c = next(c for c in f_cands if c.group == gi)
                if not grids:
                    warm.submit(g, c.y)
                    continue
                p0 = Problem(g.adapter, g.layout, settings.metric).params(c.y, g.frozen)
                warm.submit_call(
                    ("grid", compile_key(g.adapter)), lambda a=g.adapter, p=p0: a.evaluate_grid(p)
                )

        ahead = None  # a bodiless preview's type whose full model is compiled ahead
        if warm is not None:
            # The special cases' solves first (in order of use), then the full models' (their
            # layouts do not depend on the start values, nor their compiled solves on a
            # dielectric coat's Fresnel form, an array of the adapter): compiled while the
            # special cases fit. A Schlick twin queues nothing new (the key of its exact twin).
            for c in sub_cands:
                warm.submit(sub_groups[c.group], c.y)
            if bodiless_preview:
                # Only one type's full model is fitted, decided after the special cases: the
                # type the data's highlight suggests (through the fall-off the fits start from)
                # is compiled ahead, a conductor with its floor; the other type's solve, if it
                # wins, is queued at the decision; every full model if nothing was decided (below).
                # Both or none ahead measured no faster: the two compilations share two cores.
                start_fall_off = (START_E, START_M) if configs[0].apparatus else None
                ahead = (
                    "conductor"
                    if highlight_suggests_conductor(prep.stats, start_fall_off)
                    else "plastic"
                )
                warm_full([floors.get(c, c) for c in configs if c.material == ahead])
            else:
                warm_full(configs)
        # The screening stages: every stage but the last, where a single candidate of the
        # chosen type is refined (the full model refines its own solution there).
        sub_stages = settings.stages[:-1]
        ts = time.perf_counter()
        best_sub, sub_log, _, _ = _run_schedule(
            prep,
            sub_groups,
            sub_cands,
            sub_stages or settings.stages[:1],
            settings.solver_settings,
            lambda msg: say(f"[diffraction off, for the nested starts] {msg}"),
            choose=False,
            warm=warm,
        )
        best = {}  # group index -> its best special-case candidate (best_sub is sorted)
        for c in best_sub:
            best.setdefault(c.group, c)
        source = list(range(len(configs)))  # the special-case group each full model starts from
        for gi, ti in twins.items():
            if gi not in best or ti not in best:
                continue
            form, reason = choose_fresnel(best[gi].cost, best[ti].cost)
            selection = selection or {}
            special = {
                "rms": {"exact": best[gi].cost, "schlick": best[ti].cost},
                "chosen": form,
                "reason": reason,
                "n_cells": sub_log[-1]["n_cells_used"],
            }
            # starts="few" (--preview): the special case's choice, one full model per type.
            preview = form == "schlick" and few
            both = not few and schlick_worth_trying(best[gi].cost, best[ti].cost)
            if preview:
                why = "starts='few': the diffraction-off special case's choice"
            elif both:  # replaced by the full model's comparison when it is made
                why = f"Schlick's form did not fit the full model better by more than {FRESNEL_TIE_RTOL:.0%}"
            else:
                why = (
                    "Schlick's form did not fit the diffraction-off special case better by more "
                    f"than {FRESNEL_TRY_RTOL:.1%}"
                )
            selection[configs[gi].material] = {
                "special_case": special,
                "chosen": "schlick" if preview else "exact",
                "reason": why,
            }
            say(f"{configs[gi].material} coat's Fresnel form, special case: {form} ({reason})")
            if preview:
                configs[gi] = dataclasses.replace(configs[gi], fresnel="schlick")
                source[gi] = ti
            elif both:  # both forms go on; the full model's RMS decides
                configs.append(dataclasses.replace(configs[gi], fresnel="schlick"))
                start_lists.append([])
                source.append(ti)
        if bodiless_preview and all(source[gi] in best for gi in range(len(configs))):
            configs, start_lists, source, type_record = _preview_decision(
                prep, configs, start_lists, source, sub_groups, best, sub_stages, settings, floors
            )
            if type_record is not None:
                say(f"material: {type_record['chosen']} ({type_record['reason']})")
        if warm is not None:
            # The full models' solves are queued already, except where a preview decided
            # nothing or the other type than the one compiled ahead: that solve goes before the
            # grids (to the first thread that comes free), not behind them.
            if bodiless_preview and (type_record is None or type_record["chosen"] != ahead):
                warm_full(configs)
            warm_full(configs, grids=True)
        for gi, cfg in enumerate(configs):
            if not cfg.diffraction or source[gi] not in best:
                continue
            g = sub_groups[source[gi]]
            p = Problem(g.adapter, g.layout, settings.metric).params(best[source[gi]].y, g.frozen)
            if type_record is not None and cfg.material == "conductor" and cfg.has_diffuse:
                # Its floor from the first stage; the special case had none.
                p = p.replace(rho_d=floor_albedo_start(prep.stats))
            grid = FEW_NESTED_GRID if few else NESTED_GRID
            start_lists[gi] = nested_starts(p, cfg, settings.fixed, grid)
        say(f"special-case fits done ({time.perf_counter() - ts:.1f} s)")
    if settings.fresnel == "auto" and selection is None:
        selection = {
            c.material: {
                "chosen": "exact",
                "reason": "not compared: no diffraction-off fits (nested=False or no start lists)",
            }
            for c in configs
            if fresnel_choice_applies(c) and c.diffraction
        } or None
    return configs, *make_candidates(configs, start_lists, settings.fixed), selection, type_record


def _preview_decision(
    prep, configs, start_lists, source, sub_groups, best, stages, settings, floors
):
    """:func:`_make_starts`' preview decision for a bodiless material: the types' special cases
    (``best``: special-case group -> its best candidate; ``source``: each configuration's
    special-case group) compared by :func:`~twoscale.fit.material_type.preview_type`.
    Returns ``(configs, start_lists, source, type_selection)``, the configurations of the
    winning type alone (a conductor with its floor), or the arguments and ``None``."""
    n_active, n_cells = prep.stage_cells((stages or settings.stages[:1])[-1])
    opts = settings.solver_settings
    rms, params = {}, {}
    for gi, cfg in enumerate(configs):
        g, c = sub_groups[source[gi]], best[source[gi]]
        r = _type_rms(c, g, opts, prep.buffer, n_active, n_cells)
        if r < rms.get(cfg.material, math.inf):
            rms[cfg.material] = r
            params[cfg.material] = (
                Problem(g.adapter, g.layout, opts.metric).params(c.y, g.frozen),
                g.adapter.config,
            )
    fall_off = fall_off_of(*params["plastic"]) if "plastic" in params else None
    decided = preview_type(prep.stats, rms, fall_off)
    if decided is None:
        return configs, start_lists, source, None
    winner, reason = decided
    keep = [gi for gi, cfg in enumerate(configs) if cfg.material == winner]
    record = {
        "rms": rms,
        "metric": TYPE_METRIC.get(opts.metric, opts.metric),
        "chosen": winner,
        "reason": reason,
        "stage": 0,
        "from_data": True,
        "params": {k: v[0].to_dict() for k, v in params.items()},
    }
    return (
        [floors.get(configs[gi], configs[gi]) for gi in keep],
        [start_lists[gi] for gi in keep],
        [source[gi] for gi in keep],
        record,
    )


def _record(data, prep: _Prepared, groups, cands, stage_log, selections, settings, t0, say):
    """Phase 5: the best candidate as a :class:`FitResult` (standard errors, warnings, RMSE of
    both metrics on every valid cell and on those within 80°, provenance); ``selections`` is
    ``(type_selection, fresnel_selection)``."""
    best = cands[0]
    g = groups[best.group]
    problem = Problem(g.adapter, g.layout, settings.metric)
    params = problem.params(best.y, g.frozen)
    std_errors, cov_info = standard_errors(g, problem, best)
    if stage_log[-1]["n_cells_used"] < prep.n_fit:
        cov_info["note_subsample"] = (
            f"errors computed on the last stage's {stage_log[-1]['n_cells_used']}-cell subsample"
        )
    warnings = data_warnings(prep.stats) + fit_warnings(g, best, params, cov_info)
    valid = prep.selection.valid
    pred = predict_cells(g.adapter, params, valid)
    grid = np.zeros((prep.valid_grid.size, pred.shape[-1]))
    grid[np.asarray(valid.index)] = pred
    fit_floor = floor_level(grid.reshape(*prep.valid_grid.shape, -1), prep.valid_grid)
    warnings += floor_warnings(fit_floor, prep.stats.floor, settings.metric)
    errs = rmse(pred, valid, prep.log_scale)
    wall = time.perf_counter() - t0
    say(
        f"done: rms log {errs['rmse_log']:.5g}, linear {errs['rmse_linear']:.5g} "
        f"({'converged' if best.success else 'not converged: ' + best.status}; {wall:.1f} s)"
    )
    return FitResult(
        params=params,
        model=g.adapter.name,
        config=g.adapter.config_to_dict(),
        metric=settings.metric,
        rmse_linear=errs["rmse_linear"],
        rmse_log=errs["rmse_log"],
        per_channel=errs["per_channel"],
        rmse_log_scaled=errs["rmse_log_scaled"],
        log_scale=prep.log_scale.tolist(),
        rmse_fit=best.cost,
        n_valid=len(valid),
        n_fit=prep.n_fit,
        converged=bool(best.success),
        status=best.status,
        steps=best.steps,
        wall_time=wall,
        std_errors=std_errors,
        covariance=cov_info,
        settings=settings.to_dict(prep.stats),
        versions=package_versions(),
        data={
            "name": data.name,
            "path": None if data.path is None else str(data.path),
            "size_bytes": data.size,
            "sha256": data.sha256,
            "n_measured_valid": prep.selection.n_measured_valid,
            "n_below_horizon": prep.selection.n_below_horizon,
        },
        stages=stage_log,
        type_selection=selections[0],
        fresnel_selection=selections[1],
        rmse_80=rmse_within(pred, valid, log_scale=prep.log_scale),
        warnings=warnings,
    )


def fit(
    data,
    *,
    config=None,
    material: str | None = None,
    metric: str = DEFAULT_METRIC,
    max_theta_deg: float | None = None,
    fixed: dict | None = None,
    starts: str | Sequence = "default",
    schedule: str | Sequence[Stage] = "default",
    solver: str = "lm",
    seed: int = 0,
    rtol: float = _solver.RTOL,
    atol: float = _solver.ATOL,
    se_tol: float = _solver.SE_TOL,
    nested: bool = True,
    fresnel: str | None = None,
    progress: Callable[[str], None] | None = None,
) -> FitResult:
    """Fit a BRDF model to a measured MERL table.

    Args:
        data: a :class:`twoscale.merl.MerlData` (values in 1/sr, validity mask).
        config: a :class:`twoscale.ModelConfig`, a :class:`~twoscale.baselines.CookTorranceConfig`
            (baseline), or ``None`` / ``"auto"``: the MERL protocol, :func:`~twoscale.fit.material_type.merl_protocol`
            (MERL's grazing fall-off modelled on the specular lobe, its exponent ``e`` and knee
            exponent ``m`` fitted; a plastic's body Lambertian; a conductor's faint Lambertian
            floor, added on the stages after the type choice, see :func:`_split_floors`) with
            the material type chosen by the fit. Pass
            ``ModelConfig()`` to fit the reference model without them.
        material: override the configuration's material type; ``"auto"`` tries conductor and
            plastic and keeps the better (compared on the last subsample stage; near-ties go to
            the physically consistent type, see :func:`~twoscale.fit.material_type.choose_type`).
        metric: ``"blend"`` (default: both log residuals of every cell, the scaled one and
            the plain one), ``"scaled-log"`` (the log metric with each channel's ρ cos θ_i
            divided by its median over the fitted cells), ``"log"`` (Löw et al. 2012) or
            ``"linear"``; all cosine-weighted (docs/model.md §8).
        max_theta_deg: fit only cells with ``θ_i, θ_o ≤`` this angle (errors still on all cells).
        fixed: ``{name: value}`` physical values of parameters held fixed (e.g. ``{"p": 1.0}``).
        starts: ``"default"`` (placed from the data), ``"few"`` (a subset of those: the
            special case from p = 1 only, the full model from the nested start and one strong
            diffraction lobe as narrow as the special case's highlight, and with
            ``fresnel="auto"`` the full model with the Fresnel form its special case chose
            only; with ``material="auto"`` a measured diffuse body carrying at least
            :data:`~twoscale.fit.material_type.BODY_SHARE` of the light makes the plastic the
            type before any fit, the conductor not fitted,
            :func:`~twoscale.fit.material_type.type_from_body`; the CLI's ``--preview``) or a
            list of
            parameter objects (needs a single material type).
        schedule: ``"default"``, ``"preview"`` (no last refinement), ``"full"`` (the last
            refinement on every fitted cell) or a list of :class:`Stage`.
            After each stage the best ``keep`` *distinct* solutions go on: a start that ended
            within :data:`DUPLICATE_SE` standard errors of a better one is dropped (its stage
            log entry says ``duplicate_of``), so no minimum is refined twice; a start whose path
            reaches the minimum of one already finished on the stage stops there (between two
            rounds of solver steps) and is dropped the same way.
        solver: ``"lm"`` (optimistix Levenberg-Marquardt) or ``"dogleg"``.
        seed: seed of the subsampling.
        rtol, atol: tolerances of optimistix's Cauchy test (scaled parameters, RMS norm).
        se_tol: also stop when the Gauss-Newton step is below this many standard errors.
        nested: with the default starts and the diffraction lobe on, first fit the same model
            with the diffraction lobe off (fewer parameters, cheap; every stage but the last), then
            start the full model from that solution: once with a weak diffraction lobe
            (``A_spec(0) = 0.95``, the *nested* start, carried through every subsample stage)
            and once per point of a small (c, A_spec(0)) grid. The full model contains the
            special case as the limit σ_s → 0, so it cannot end worse than it.
        fresnel: the Fresnel form of a dielectric coat (plastic, subsurface): ``"exact"``,
            ``"schlick"`` (see ``ModelConfig.fresnel``) or ``"auto"`` (with ``nested``): each
            dielectric type's diffraction-off special case is fitted with both forms; where
            Schlick's lowers that RMS by more than
            :data:`~twoscale.fit.material_type.FRESNEL_TRY_RTOL` (0.5 %), the full model is
            fitted with both and keeps Schlick's only if it lowers the full model's RMS by more
            than :data:`~twoscale.fit.material_type.FRESNEL_TIE_RTOL` (2 %), at the
            stage where the material type is chosen (``FitResult.fresnel_selection`` records
            both comparisons). ``None`` (default): ``"auto"`` under the MERL protocol
            (``config=None``), else the configuration's own form.
        progress: called with one line of text per start and stage (e.g. ``print``).

    Returns:
        A :class:`~twoscale.fit.FitResult`; ``warnings`` lists the problems of a usable fit
        (step limit reached, a parameter at the end of its range, a rank-deficient Jacobian).

    Raises:
        ValueError: bad arguments or no valid data. TypeError: ``data`` not a ``MerlData``.
        :class:`FitError`: no start gave a finite fit.

    Compilation: each configuration's solve is compiled in a background thread ahead of its
    first use, and while the last stage runs, the evaluation that pictures and the albedo table
    use (:func:`twoscale.plots.write_fit_pictures`; one compiled function per configuration, ≈ 2 s
    on 2 cores the first time in a process or compilation cache).
    """
    t0 = time.perf_counter()
    from twoscale.merl import MerlData

    if not isinstance(data, MerlData):
        raise TypeError(
            "twoscale.fit needs a twoscale.merl.MerlData (twoscale.merl.read(path), or "
            "MerlData(values, valid) from a (90, 90, 180, 3) array in 1/sr and a (90, 90, 180) "
            f"validity mask), got {type(data).__name__}"
        )
    if not jax.config.jax_enable_x64:
        raise RuntimeError(
            "twoscale.fit needs float64: call jax.config.update('jax_enable_x64', True) first"
        )
    settings = FitSettings(
        metric=metric,
        max_theta_deg=max_theta_deg,
        fixed=dict(fixed or {}),
        starts=starts if isinstance(starts, str) else tuple(starts),
        stages=resolve_schedule(schedule),
        solver=solver,
        seed=seed,
        rtol=rtol,
        atol=atol,
        se_tol=se_tol,
        nested=nested,
        material=material,
    )
    say = progress or (lambda _msg: None)
    configs = resolve_configs(config, material)
    protocol = config is None or (isinstance(config, str) and config == "auto")
    configs, fresnel_mode = resolve_fresnel(configs, fresnel, protocol)
    configs, floors = _split_floors(configs)
    check_fixed(settings.fixed, [*configs, *floors.values()])
    configs = _types_holding(configs, settings.fixed, say)
    settings = dataclasses.replace(settings, fresnel=fresnel_mode or fresnel)
    if not isinstance(settings.starts, str) and len(configs) > 1:
        raise ValueError("explicit starts need a single material type (pass material=...)")
    # Phase 1: the cells (host side) and their device buffer.
    prep = _prepare(data, settings.max_theta_deg, settings.seed)
    say(
        f"{prep.n_fit} cells fitted of {len(prep.selection.valid)} valid; metric "
        f"{settings.metric}; {len(settings.stages)} stages"
    )
    for line in data_warnings(prep.stats):
        say(f"warning: {line}")
    configs, preselection = _preselect_type(configs, prep, settings, say)
    # Phase 2: the candidates. Each configuration's solve is compiled in the background ahead
    # of its first use (solver.Warmup).
    warm = _solver.Warmup(prep.buffer, settings.solver_settings)
    try:
        configs, groups, cands, fresnel_selection, decided = _make_starts(
            prep, configs, settings, say, warm, floors
        )
        preselection = preselection or decided
        say(f"{len(cands)} starts")
        # Phases 3 and 4: every stage, and the material type after the second-last one.
        floor = _floor_converter(floors, prep, settings, say, warm) if floors else None
        cands, stage_log, type_selection, fresnel_choice = _run_schedule(
            prep, groups, cands, settings.stages, settings.solver_settings, say, True, warm, floor
        )
    finally:
        warm.close()
    for mat, entry in (fresnel_selection or {}).items():
        if mat in fresnel_choice:
            entry.update(fresnel_choice[mat])
    # Phase 5: the record.
    selections = (type_selection or preselection, fresnel_selection)
    return _record(data, prep, groups, cands, stage_log, selections, settings, t0, say)

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

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from twoscale.baselines import CookTorranceConfig
from twoscale.fit.adapters import adapter_for
from twoscale.fit.record import FitResult, package_versions
from twoscale.fit.residuals import (
    CHUNK,
    DIRECTION_CHUNKS,
    Layout,
    Problem,
    check_metric,
    compressed_residuals,
    pack,
    pack_directions,
    pair_cells,
    predict,
    select_cells,
    sum_squares,
)
from twoscale.fit.starts import data_stats, floor_level

MATERIALS = ("conductor", "plastic", "subsurface")
#: Material types tried by ``material="auto"`` (subsurface is only fitted when asked for).
AUTO_MATERIALS = ("conductor", "plastic")


@dataclasses.dataclass(frozen=True)
class Stage:
    """One stage of the schedule.

    Attributes:
        n_cells: cells fitted (a uniform random subsample of the fitted cells; None = all).
        keep: how many of the best solutions go on to the next stage (per material type).
        max_steps: solver steps allowed per start: a safety net, not the usual end (see
            ``round_steps``).
        round_steps: the solver runs in rounds of this many steps (the first step of a round
            evaluates its starting point; at least 2); a start has converged when
            the solver's own tests say so, or when a round lowers the RMS by less than
            :data:`STALL_RTOL` (relative): further steps would not change the fit.
    """

    n_cells: int | None
    keep: int
    max_steps: int
    round_steps: int = 10

    def __post_init__(self):
        if self.max_steps < 1 or self.round_steps < 1 or self.keep < 1:
            raise ValueError(f"Stage needs keep, max_steps, round_steps ≥ 1, got {self}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


#: Default: every start on ≈ 4 096 cells, the best 2 (per material type) on ≈ 32 768, the best
#: one on 262 144 (rounds of 5 steps there: each step is a pass over those cells). Refining on
#: all ≈ 1.1 M valid cells instead ("full") changed the log RMSE on all cells by < 1e-4 on the
#: stand-ins measured (fit/RESULTS.md) at 4× the cost of that stage.
DEFAULT_SCHEDULE = (
    Stage(n_cells=4096, keep=2, max_steps=60),
    Stage(n_cells=32768, keep=1, max_steps=60),
    Stage(n_cells=262144, keep=1, max_steps=25, round_steps=5),
)
#: Preview: the same without the last refinement (errors still reported on all valid cells).
PREVIEW_SCHEDULE = DEFAULT_SCHEDULE[:2]
#: Full: the last refinement on every fitted cell.
FULL_SCHEDULE = DEFAULT_SCHEDULE[:2] + (Stage(n_cells=None, keep=1, max_steps=25, round_steps=5),)
SCHEDULES = {"default": DEFAULT_SCHEDULE, "preview": PREVIEW_SCHEDULE, "full": FULL_SCHEDULE}

#: Solver tolerances: optimistix's Cauchy test (on the scaled parameters and the compressed
#: residual, RMS norm), and the standard-error test of :func:`_small_step` (either one stops).
RTOL = 1e-7
ATOL = 1e-9
SE_TOL = 0.05
#: A round of ``Stage.round_steps`` solver steps that lowers the RMS by less than this fraction
#: ends the start as converged (the RMS is stationary to the 4 digits a report shows).
STALL_RTOL = 1e-4


class FitError(RuntimeError):
    """The fit could not produce a result (e.g. non-finite cost for every start)."""


#: Static bound of the solver loop; the per-stage limit (``Stage.max_steps``) is a dynamic value,
#: so stages with different limits share one compiled solve.
MAX_STEPS_BOUND = 1000


def _small_step(state, options):
    """Has the Gauss-Newton step from the last accepted point shrunk below ``se_tol`` standard errors?

    With the compressed residual ``r̃ = [q, t]``, the full Gauss-Newton step ``δ`` satisfies
    ``δᵀ JᵀJ δ = |q|²`` and the residual variance is ``σ² ≈ t²/(m − n)``, so the step measured in
    standard errors is ``|q| √(m − n)/t``. Stopping when it is below ``se_tol`` (default 0.05)
    ends the fit once further steps cannot change the parameters by a meaningful fraction of
    their uncertainty — the useful notion of convergence for tens of thousands of noisy residuals.
    """
    r_c = state.f_info.residual
    q2 = jnp.sum(r_c[:-1] ** 2)
    t2 = r_c[-1] ** 2
    dof = jnp.maximum(options["n_resid"] - (r_c.shape[0] - 1), 1)
    small = q2 * dof < options["se_tol"] ** 2 * t2
    return small & (state.num_accepted_steps >= 1)


class _LevenbergMarquardt(optx.LevenbergMarquardt):
    """:class:`optimistix.LevenbergMarquardt` that also stops when the step is negligible against
    the standard errors (:func:`_small_step`) or at ``options["step_cap"]`` steps (dynamic,
    unlike ``max_steps``, so stages with different limits share one compiled solve)."""

    def terminate(self, fn, y, args, options, state, tags):
        terminate, result = super().terminate(fn, y, args, options, state, tags)
        stop = _small_step(state, options) | (state.num_steps >= options["step_cap"])
        return terminate | stop, result


class _Dogleg(optx.Dogleg):
    """:class:`optimistix.Dogleg` with the same extra stopping rules as :class:`_LevenbergMarquardt`."""

    def terminate(self, fn, y, args, options, state, tags):
        terminate, result = super().terminate(fn, y, args, options, state, tags)
        stop = _small_step(state, options) | (state.num_steps >= options["step_cap"])
        return terminate | stop, result


def _make_solver(name: str, rtol: float, atol: float):
    if name == "lm":
        return _LevenbergMarquardt(rtol=rtol, atol=atol, norm=optx.rms_norm)
    if name == "dogleg":
        return _Dogleg(rtol=rtol, atol=atol, norm=optx.rms_norm)
    raise ValueError(f"solver must be 'lm' or 'dogleg', got {name!r}")


#: Initial Levenberg-Marquardt damping relative to the diagonal of JᵀJ (see :func:`_scales`).
INITIAL_DAMPING = 1e-3
#: Largest scale of a free parameter in unconstrained units (for parameters with ~no influence).
_MAX_SCALE = 10.0


def _scales(jtj: np.ndarray) -> np.ndarray:
    """Per-parameter scales ``σ_j = 1/(√(JᵀJ)_jj √μ0)``: the solver works on ``z = (y − y0)/σ``.

    optimistix's Levenberg-Marquardt damps with ``λ I`` and starts at ``λ = 1``; in ``z`` the
    Gauss-Newton matrix has diagonal ``1/μ0``, so its first step has relative damping
    ``μ0`` = :data:`INITIAL_DAMPING` whatever the units of the parameters (Marquardt's scaling).
    """
    d = np.sqrt(np.maximum(np.diag(np.asarray(jtj)), 0.0))
    with np.errstate(divide="ignore"):
        s = 1.0 / (d * math.sqrt(INITIAL_DAMPING))
    return np.where(np.isfinite(s), np.minimum(s, _MAX_SCALE), _MAX_SCALE)


@eqx.filter_jit
def _solve(
    problem, y0, frozen, data, n_active, step_cap, n_resid, scale, rtol, atol, se_tol, solver_name
):
    """Least-squares solve from ``y0`` on the active chunks of ``data``, at most ``step_cap`` steps.

    The solver works on ``z = (y − y0)/scale``. Its first step only evaluates the residuals and
    their Jacobian at ``y0`` (so a solve of ``step_cap`` steps makes ``step_cap − 1`` moves).
    Returns ``(y, result, converged, steps, accepted moves, rᵀr at y0, rᵀr at y, JᵀJ at y)`` (``JᵀJ`` in ``y``,
    from the solver's final linearisation, and ``rᵀr`` from its compressed residual: no extra
    linearisation). ``converged``: the solver's own test or the standard-error test, not the
    step limit.
    """
    solver = _make_solver(solver_name, rtol, atol)

    def fn(z, args):
        return compressed_residuals(problem, y0 + scale * z, *args)

    options = {"step_cap": step_cap, "n_resid": n_resid, "se_tol": se_tol}
    sol = optx.least_squares(
        fn,
        solver,
        jnp.zeros_like(y0),
        args=(frozen, data, n_active),
        options=options,
        max_steps=MAX_STEPS_BOUND,
        throw=False,
    )
    y = y0 + scale * sol.value
    j_c = sol.state.f_info.jac.as_matrix() / scale[None, :]  # back to y
    # |r̃|² = rᵀr at the last accepted point (compressed residuals).
    rr = jnp.sum(sol.state.f_info.residual**2)
    rr0 = sum_squares(problem, y0, frozen, data, n_active)  # a primal pass: the round's reference
    converged = (sol.state.terminate | _small_step(sol.state, options)) & (
        sol.result == optx.RESULTS.successful
    )
    moves = sol.state.num_accepted_steps - 1  # accepted steps after the evaluation of y0
    return y, sol.result, converged, sol.stats["num_steps"], moves, rr0, rr, j_c.T @ j_c


@eqx.filter_jit
def _sum_squares(problem, y, frozen, data, n_active):
    return sum_squares(problem, y, frozen, data, n_active)


@eqx.filter_jit
def _predict(fn, params, data, n_active, n_out):
    return predict(fn, params, data, n_active, n_out)


@eqx.filter_jit
def _physical_free(problem, y, frozen, spec):
    """Flat physical values of the free parameters, and their Jacobian in ``y``."""

    def phys(yy):
        params = problem.params(yy, frozen)
        free, _ = eqx.partition(params, spec)
        leaves = jax.tree_util.tree_leaves(free)
        return jnp.concatenate([jnp.ravel(x) for x in leaves])

    return phys(y), jax.jacfwd(phys)(y)


@dataclasses.dataclass
class _Candidate:
    """One start travelling through the schedule."""

    label: str
    group: int  # index into the list of groups (configuration, free-parameter layout)
    y: jax.Array
    cost: float = math.inf  # RMS of the residuals on the last stage's cells
    steps: int = 0
    status: str = "not run"
    success: bool = False
    rr: float = math.nan  # rᵀr at y on the last stage's cells
    jtj: np.ndarray | None = None  # JᵀJ at y on the last stage's cells
    m: int = 0  # residuals in that stage
    nested: bool = False  # the nested start: carried through every stage (see fit(nested=...))
    moves: int = 0  # accepted solver steps so far


#: Two solutions closer than this many standard errors are the same minimum (see :func:`fit`).
DUPLICATE_SE = 0.5


def _same_solution(a: _Candidate, b: _Candidate, tol: float = DUPLICATE_SE) -> bool:
    """Are ``a`` and ``b`` (same group, same stage) within ``tol`` standard errors of each other?

    The distance is measured with ``a``'s Gauss-Newton matrix and residual variance:
    ``δᵀ JᵀJ δ / σ²`` with ``δ = y_a − y_b`` and ``σ² = rᵀr/(m − n)``, the squared length of
    ``δ`` in standard errors along the best-determined and worst-determined directions alike.
    """
    if a.group != b.group or a.jtj is None or a.y.shape != b.y.shape:
        return False
    n = int(a.y.shape[0])
    d = np.asarray(a.y) - np.asarray(b.y)
    if n == 0 or not np.all(np.isfinite(d)):
        return n == 0
    sigma2 = a.rr / max(a.m - n, 1)
    if not (math.isfinite(sigma2) and sigma2 > 0.0):
        return False
    dist2 = float(d @ np.asarray(a.jtj) @ d) / sigma2
    return dist2 < tol * tol


@dataclasses.dataclass
class _Group:
    adapter: object
    spec: object
    frozen: object
    layout: Layout


#: A_spec(0) of the diffraction lobe added to the nested start (weak, but with a non-zero
#: gradient in σ_s: at σ_s = 0 exactly, ∂A_s/∂σ_s = 0 and the solver could not leave it).
NESTED_A_SPEC = 0.95
NESTED_LABEL = "nested"
#: The other full-model starts from the special case: ``(c, A_spec(0), b µm)``. A diffraction
#: lobe carrying 70 % or 30 % of the specular energy at normal incidence with a halo of
#: half-width ≈ 15° (b = 1 µm); a strong lobe (A_spec(0) = 0.05, 95 % of the energy) with a
#: narrow core and a power-law tail (b = 30 µm), the basin of sharp highlights that widen towards
#: grazing θ_d (phenolics, plastics: the winning start on 4 of 8 stand-ins tried); and a strong,
#: wide lobe (b = 0.3 µm). Starts that end in the same minimum are dropped after the first stage.
NESTED_GRID = (
    (1.5, 0.3, 1.0),
    (2.5, 0.7, 1.0),
    (1.5, 0.05, 30.0),
    (1.5, 0.05, 0.3),
)


def _nested_starts(params, cfg, fixed: dict) -> list[tuple[str, object]]:
    """Starts of the full model ``cfg`` from the fit of its diffraction-off special case.

    The specular parameters (β, p, η, k or ρ_d, e) are those of the special case's fit; the
    nano-scale ones are the nested start (``A_spec(0)`` = :data:`NESTED_A_SPEC`: the special case
    itself, with a weak diffraction lobe whose gradient is not 0) and the points of
    :data:`NESTED_GRID`.
    """
    from twoscale.fit.adapters import START_B, START_C, sigma_s_for_a_spec

    wl = float(np.median(np.asarray(cfg.wavelengths)))
    out = []
    for label, a_spec, c, b in [(NESTED_LABEL, NESTED_A_SPEC, START_C[0], START_B)] + [
        (f"from the special case, c={c:g} A_spec(0)={a:g} b={b:g}", a, c, b)
        for c, a, b in NESTED_GRID
    ]:
        c = float(fixed.get("c", c))
        b = float(fixed.get("b", b))
        sigma_s = float(fixed.get("sigma_s", sigma_s_for_a_spec(a_spec, b, c, wl)))
        out.append((label, params.replace(sigma_s=sigma_s, b=b, c=c).for_config(cfg)))
    return out


def merl_protocol(*, diffraction: bool = True, apparatus: bool = True, diffuse_fresnel=False):
    """The model configuration the fitter uses for MERL data unless told otherwise.

    ``ModelConfig(apparatus=True, diffuse_fresnel=False)`` (material chosen by the fit):

    - MERL's apparatus factor on the specular lobe, its exponent ``e`` fitted (docs/model.md
      §3.11): MERL's values fall off at grazing angles, and without it the shape parameters
      are bent to fit that fall-off;
    - a plastic's body Lambertian (§3.9): MERL's plastics and fabrics do not darken towards
      grazing angles as the varnish's Fresnel transmission makes the reference body do. On the
      Neural-BRDF stand-ins tried (plastic fits of yellow-plastic, red-fabric2, pink-plastic,
      white-fabric) the Lambertian body lowered the log RMSE by 13 %, 23 %, 18 % and 35 %
      (specular-red-phenolic: equal), and only with it do pink-plastic and white-fabric beat
      GGX + Lambert. ``fit/RESULTS.md`` has the whole campaign.
    """
    from twoscale.config import ModelConfig

    return ModelConfig(
        diffraction=diffraction, apparatus=apparatus, diffuse_fresnel=diffuse_fresnel
    )


def _resolve_configs(config, material) -> list:
    """The model configurations to try (several for ``material='auto'``)."""
    if isinstance(config, CookTorranceConfig):
        if material not in (None, "auto"):
            raise ValueError("material does not apply to the Cook-Torrance baseline")
        return [config]

    if config is None or (isinstance(config, str) and config == "auto"):
        base = merl_protocol()  # see fit(config=...)
        if material is None:
            material = "auto"
    elif isinstance(config, str):
        raise ValueError(
            f"config must be a ModelConfig, a CookTorranceConfig or 'auto', got {config!r}"
        )
    else:
        base = config
    if material is None:
        return [base]
    if material == "auto":
        return [dataclasses.replace(base, material=m) for m in AUTO_MATERIALS]
    if material not in MATERIALS:
        raise ValueError(f"material must be one of {MATERIALS} or 'auto', got {material!r}")
    return [dataclasses.replace(base, material=material)]


def _apply_fixed(params, fixed: dict, adapter):
    """Set the fixed fields (physical values) and return (params, spec of free leaves)."""
    spec = jax.tree_util.tree_map(lambda _: True, params)
    for name, value in fixed.items():
        if name not in adapter.field_names:
            raise ValueError(
                f"cannot fix {name!r}: parameters of this model are {', '.join(adapter.field_names)}"
            )
        current = getattr(params, name)
        if current is None:
            raise ValueError(f"cannot fix {name!r}: this configuration does not use it")
        new = jnp.broadcast_to(jnp.asarray(value, dtype=jnp.float64), jnp.shape(current))
        params = eqx.tree_at(lambda p, n=name: getattr(p, n), params, new)
        spec = eqx.tree_at(lambda s, n=name: getattr(s, n), spec, False)
    return params, spec


def _schedule(schedule) -> tuple[Stage, ...]:
    if isinstance(schedule, str):
        if schedule not in SCHEDULES:
            raise ValueError(f"schedule must be one of {tuple(SCHEDULES)} or a list of Stage")
        return SCHEDULES[schedule]
    stages = tuple(schedule)
    if not stages or not all(isinstance(s, Stage) for s in stages):
        raise ValueError("schedule must be a non-empty sequence of Stage")
    return stages


def _result_message(result) -> str:
    for item, msg in (
        (optx.RESULTS.successful, ""),
        (optx.RESULTS.nonlinear_max_steps_reached, "maximum number of steps reached"),
        (optx.RESULTS.nonlinear_divergence, "diverged"),
        (optx.RESULTS.nonfinite, "non-finite values"),
    ):
        if bool(result == item):
            return msg
    return "linear solve failed"


def _errors(pred: np.ndarray, cells) -> dict:
    """RMSE of both metrics, overall and per channel, for predictions on ``cells``."""
    cos = cells.cos_i[:, None]
    lin = (pred - cells.rho) * cos
    log = np.log1p(np.maximum(pred, 0.0) * cos) - np.log1p(cells.rho * cos)
    return {
        "rmse_linear": float(np.sqrt(np.mean(lin**2))),
        "rmse_log": float(np.sqrt(np.mean(log**2))),
        "per_channel": {
            "rmse_linear": np.sqrt(np.mean(lin**2, axis=0)).tolist(),
            "rmse_log": np.sqrt(np.mean(log**2, axis=0)).tolist(),
        },
    }


def predict_cells(adapter, params, cells) -> np.ndarray:
    """Model values ``(N, C)`` at the cells (one compiled pass per model configuration).

    Adapters with ``evaluate_grid`` (the two-scale model) evaluate the whole MERL grid by its
    fast path (:func:`twoscale.model.brdf_grid`) and take the cells from it; the others go
    through the fixed-shape direction buffer.
    """
    if hasattr(adapter, "evaluate_grid"):
        grid = np.asarray(adapter.evaluate_grid(params, "lower"))
        return grid.reshape(-1, grid.shape[-1])[np.asarray(cells.index)]
    return evaluate_at(adapter.evaluate, params, cells.wi, cells.wo, adapter.config.n_channels)


def evaluate_at(fn, params, wi, wo, n_out: int) -> np.ndarray:
    """``fn(params, wi, wo) -> (N, n_out)`` at NumPy directions ``(N, 3)``, through the
    fixed-shape buffer (so every call with the same ``fn`` shares one compiled function)."""
    wi = np.asarray(wi, dtype=np.float64).reshape(-1, 3)
    wo = np.asarray(wo, dtype=np.float64).reshape(-1, 3)
    n = wi.shape[0]
    cap = DIRECTION_CHUNKS * CHUNK
    out = []
    for start in range(0, max(n, 1), cap):
        sl = slice(start, min(start + cap, n))
        buf, n_active = pack_directions(wi[sl], wo[sl])
        pred = np.asarray(_predict(fn, params, buf, jnp.int32(n_active), n_out))
        out.append(pred.reshape(-1, n_out)[: wi[sl].shape[0]])
    return np.concatenate(out, axis=0)


def _standard_errors(group: _Group, problem: Problem, cand: _Candidate) -> tuple[dict, dict]:
    """Standard errors ``σ² (JᵀJ)⁺`` at the solution, mapped to physical units (delta method)."""
    n = int(cand.y.shape[0])
    names = group.adapter.field_names
    if n == 0:
        return {k: None for k in names}, {"method": "none", "note": "every parameter fixed"}
    jtj = np.asarray(cand.jtj)
    dof = max(cand.m - n, 1)
    sigma2 = float(cand.rr) / dof
    # Scale to unit diagonal before the eigen-decomposition: rank is judged on correlations.
    d = np.sqrt(np.maximum(np.diag(jtj), 0.0))
    d_safe = np.where(d > 0, d, 1.0)
    corr = jtj / np.outer(d_safe, d_safe)
    evals, evecs = np.linalg.eigh(corr)
    keep = evals > 1e-10 * max(evals.max(), np.finfo(float).tiny)
    rank = int(keep.sum())
    inv = (evecs[:, keep] / evals[keep]) @ evecs[:, keep].T
    cov_u = sigma2 * inv / np.outer(d_safe, d_safe)
    _, jac = _physical_free(problem, cand.y, group.frozen, group.spec)
    jac = np.asarray(jac)
    cov_p = jac @ cov_u @ jac.T
    se_flat = np.sqrt(np.maximum(np.diag(cov_p), 0.0))
    std = _by_name(group, se_flat)
    info = {
        "method": "sigma^2 (J^T J)^+ at the solution (unconstrained space), "
        "delta method to physical units",
        "sigma2": sigma2,
        "dof": dof,
        "n_free": n,
        "rank": rank,
        "rank_deficient": rank < n,
        "condition": float(evals.max() / max(evals.min(), np.finfo(float).tiny)),
    }
    if rank < n:
        # Which parameters span the (near) null space: the large components of its eigenvectors.
        null = _by_name(group, np.abs(evecs[:, ~keep]).max(axis=1))
        weak = [k for k, v in null.items() if v is not None and np.max(v) > 0.3]
        info["note"] = (
            f"Jacobian rank {rank} < {n} free parameters: pseudo-inverse used; "
            f"{', '.join(weak) or 'some parameters'} not determined by the data "
            "(their errors are unreliable)"
        )
    return std, info


def _by_name(group: _Group, flat) -> dict:
    """Flat values over the free leaves → ``{field: float | list | None}``."""
    tree = group.layout.unravel(jnp.asarray(flat))
    out = {}
    for name in group.adapter.field_names:
        leaf = getattr(tree, name, None)
        if leaf is None:
            out[name] = None
        else:
            arr = np.asarray(leaf)
            out[name] = float(arr) if arr.ndim == 0 else arr.tolist()
    return out


@dataclasses.dataclass
class _Prepared:
    """Host-side preparation shared by every stage (and by the nested special-case fit)."""

    selection: object  # CellSelection
    stats: object  # DataStats
    pairs: object  # Pairs, in random order: each stage fits a prefix
    cells_upto: np.ndarray  # cells held by the first k + 1 pairs
    buffer: dict  # device buffer of all pairs
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


def _prepare(data, max_theta_deg, seed) -> _Prepared:
    selection = select_cells(data, max_theta_deg=max_theta_deg)
    stats = data_stats(np.asarray(data.values), np.asarray(data.valid))
    rng = np.random.default_rng(seed)
    # One buffer for every stage: the fitted cells in reciprocal pairs, in random order; each
    # stage fits a prefix (a uniform random subsample of the pairs).
    pairs = pair_cells(selection.fit)
    pairs = pairs.take(rng.permutation(len(pairs)))
    cells_upto = np.cumsum(pairs.w.sum(axis=1)).astype(np.int64)
    buffer, _ = pack(pairs)
    return _Prepared(selection, stats, pairs, cells_upto, buffer, np.asarray(data.valid))


def _make_candidates(configs, start_lists, fixed: dict):
    """Groups (one per configuration) and their candidates from ``[(label, params)]`` lists."""
    groups: list[_Group] = []
    cands: list[_Candidate] = []
    for cfg, start_list in zip(configs, start_lists, strict=True):
        adapter = adapter_for(cfg)
        group = None
        for label, p0 in start_list:
            p0, spec = _apply_fixed(p0, fixed, adapter)
            free, frozen = eqx.partition(adapter.to_unconstrained(p0), spec)
            layout = Layout.of(free)
            if group is None:
                group = _Group(adapter, spec, frozen, layout)
                groups.append(group)
            elif layout != group.layout:
                raise ValueError("all starts must have the same parameter structure")
            cands.append(
                _Candidate(
                    f"{adapter.material} {label}",
                    len(groups) - 1,
                    layout.ravel(free),
                    nested=label.startswith(NESTED_LABEL),
                )
            )
    return groups, cands


@dataclasses.dataclass(frozen=True)
class _SolverSettings:
    """Everything a stage's solves need besides the data and the candidate."""

    metric: str
    solver: str
    rtol: float
    atol: float
    se_tol: float


def _refine(cand: _Candidate, g: _Group, stage: Stage, data, n_active: int, m: int, opts):
    """Run the solver on one candidate for one stage, in rounds (see :class:`Stage`).

    Returns ``(y, rr, jtj, steps, converged, status)``; ``cand.moves`` counts the accepted
    solver steps (0 after a stage: no step from the start lowered the cost).
    """
    problem = Problem(g.adapter, g.layout, opts.metric)
    n = g.layout.size

    def solve(y0, cap, scale):
        return _solve(
            problem,
            y0,
            g.frozen,
            data,
            jnp.int32(n_active),  # dynamic: one compiled solve serves every stage
            jnp.int32(cap),  # dynamic too
            jnp.int32(m),
            jnp.asarray(scale),
            opts.rtol,
            opts.atol,
            opts.se_tol,
            opts.solver,
        )

    y = cand.y
    if n == 0:
        rr = float(_sum_squares(problem, y, g.frozen, data, jnp.int32(n_active)))
        return y, rr, np.zeros((0, 0)), 0, True, "every parameter fixed"
    if cand.jtj is None:
        # A solve of one step only linearises at y: JᵀJ for the scales (Marquardt's scaling).
        *_, jtj = solve(y, 1, np.ones(n))
        jtj = np.asarray(jtj)
    else:
        jtj = np.asarray(cand.jtj) * (m / max(cand.m, 1))  # JᵀJ grows with m
    steps, rr = 0, math.nan
    while steps < stage.max_steps:
        # At least 2: the first step of a solve only evaluates its starting point.
        cap = max(2, min(stage.round_steps, stage.max_steps - steps))
        y_new, res, conv, k, moves, rr0, rr_new, jtj_new = solve(y, cap, _scales(jtj))
        rr0, rr_new = float(rr0), float(rr_new)
        msg = _result_message(res)
        steps += int(k)
        cand.moves += int(moves)
        if not (math.isfinite(rr_new) and np.all(np.isfinite(np.asarray(y_new)))):
            return y, rr, jtj, steps, False, msg or "non-finite values"
        fell = (rr0 - rr_new) / rr0 if math.isfinite(rr0) and rr0 > 0 else math.inf
        y, rr, jtj = y_new, rr_new, np.asarray(jtj_new)
        if bool(conv):
            return y, rr, jtj, steps, True, "converged"
        if msg and res != optx.RESULTS.nonlinear_max_steps_reached:
            return y, rr, jtj, steps, False, msg
        # RMS relative change ≈ half the relative change of rᵀr; a round whose steps were all
        # rejected says nothing (the damping was still growing).
        if int(moves) > 0 and 0.5 * fell < STALL_RTOL:
            return y, rr, jtj, steps, True, f"converged (RMS changed < {STALL_RTOL:g} in a round)"
    return y, rr, jtj, steps, False, "step limit reached"


def _keep_best(cands, groups, stage: Stage, last: bool):
    """The best ``stage.keep`` *distinct* solutions per group (and the nested start, unless
    ``last``: the next stage is the last), and ``{dropped label: label of the better twin}``."""
    finite = [c for c in cands if math.isfinite(c.cost)]
    kept, duplicates = [], {}
    for gi in range(len(groups)):
        mine = sorted((c for c in finite if c.group == gi), key=lambda c: c.cost)
        chosen: list[_Candidate] = []
        for c in mine:
            # A solution within DUPLICATE_SE standard errors of a better kept one is the same
            # minimum reached from another start: dropped, so no minimum is refined twice.
            twin = next((k for k in chosen if _same_solution(k, c)), None)
            if twin is not None:
                duplicates[c.label] = twin.label
                continue
            # The nested start goes on even when a subsample ranks it lower, so that a later
            # stage compares it with the others on more cells.
            if last:
                if len(chosen) < stage.keep:
                    chosen.append(c)
            elif sum(not k.nested for k in chosen) < stage.keep or c.nested:
                chosen.append(c)
        kept.extend(chosen)
    return kept, duplicates


#: Two material types whose best RMS differ by less than this fraction fit equally well; the
#: physically consistent one is chosen (:func:`_choose_type`).
TYPE_TIE_RTOL = 0.02
#: A conductor fit whose extinction stays below this in every channel reflects like a dielectric.
DIELECTRIC_K = 0.5
#: A plastic fit whose diffuse albedo (luminance) is below this has no diffuse layer: a metal.
METAL_RHO_D = 0.01
#: A measured diffuse body counts when its Lambertian albedo ``π ρ_floor`` (luminance of the
#: floor level, :func:`~twoscale.fit.starts.floor_level`) reaches this: a visible body colour.
BODY_ALBEDO = 0.01
#: A conductor fit that reproduces less than this fraction of a counting body leaves it out: the
#: log metric weighs a dim body little against a bright highlight, so such a fit can have the
#: lower RMS and still render as a black object with a highlight. The plastic wins.
MISSING_BODY = 0.5


def _choose_type(best: dict, body: dict | None = None) -> tuple[str, str]:
    """Pick a material type from ``{type: (rms, params)}``; returns ``(type, reason)``.

    ``body``: ``{"measured": (C,), type: (C,), ...}``, the floor level
    (:func:`~twoscale.fit.starts.floor_level`) of the data and of each type's fit.

    A conductor fit that leaves a measured diffuse body out (the body's albedo ``π ρ_floor`` at
    least :data:`BODY_ALBEDO`, the fit's floor below :data:`MISSING_BODY` of it, and the plastic
    fit's closer) loses to the plastic whatever its RMS: it would render black with a highlight.
    Otherwise the lower RMS wins, unless the two are within :data:`TYPE_TIE_RTOL`: then a
    conductor fit with ``k < DIELECTRIC_K`` in every channel is a dielectric in disguise (plastic
    wins), and a plastic fit without a diffuse layer (luminance ``ρ_d < METAL_RHO_D``) is a metal
    in disguise (conductor wins).
    """
    order = sorted(best, key=lambda t: best[t][0])
    winner = order[0]
    if len(order) < 2 or {"conductor", "plastic"} - set(best):
        return winner, "lower RMS"
    rms_c, p_c = best["conductor"]
    rms_p, p_p = best["plastic"]
    if body is not None:
        w = np.array([0.2126, 0.7152, 0.0722])
        measured = float(np.asarray(body["measured"]) @ w)
        frac_c = float(np.asarray(body["conductor"]) @ w) / max(measured, 1e-300)
        frac_p = float(np.asarray(body["plastic"]) @ w) / max(measured, 1e-300)
        if (
            math.pi * measured >= BODY_ALBEDO
            and frac_c < MISSING_BODY
            and abs(math.log(max(frac_p, 1e-300))) < abs(math.log(max(frac_c, 1e-300)))
        ):
            return "plastic", (
                f"the conductor fit leaves the measured diffuse body out (its floor is "
                f"{frac_c:.0%} of the measured one, albedo π ρ = {math.pi * measured:.3g}; "
                f"plastic: {frac_p:.0%})"
            )
    if abs(rms_c - rms_p) > TYPE_TIE_RTOL * min(rms_c, rms_p):
        return winner, "lower RMS"
    k = np.asarray(p_c.k)
    rho_d = float(np.asarray(p_p.rho_d) @ np.array([0.2126, 0.7152, 0.0722]))
    if np.all(k < DIELECTRIC_K):
        return (
            "plastic",
            f"RMS within {TYPE_TIE_RTOL:.0%}; the conductor fit has k < {DIELECTRIC_K}",
        )
    if rho_d < METAL_RHO_D:
        return "conductor", (
            f"RMS within {TYPE_TIE_RTOL:.0%}; the plastic fit has no diffuse layer (ρ_d = {rho_d:.3g})"
        )
    return winner, f"RMS within {TYPE_TIE_RTOL:.0%}; lower RMS"


def _body_levels(best: dict, groups, prep: _Prepared) -> dict | None:
    """Floor levels (:func:`~twoscale.fit.starts.floor_level`) of the data and of each type's
    best fit (the model on the MERL grid), for :func:`_choose_type`; None without a grid path."""
    out = {"measured": prep.stats.floor}
    for mat, (_rms, params) in best.items():
        g = next(g for g in groups if g.adapter.material == mat)
        if not hasattr(g.adapter, "evaluate_grid"):
            return None
        grid = np.asarray(g.adapter.evaluate_grid(params, "lower"))
        out[mat] = floor_level(grid, prep.valid_grid)
    return out


def _run_schedule(prep: _Prepared, groups, cands, stages, opts, say, choose_type: bool):
    """Fit every candidate through the stages; returns ``(candidates best first, stage log,
    type selection)``. The material type is chosen after the second-last stage (or the only one)."""
    stage_log = []
    type_selection = None
    for si, stage in enumerate(stages):
        n_active, n_cells = prep.stage_cells(stage)
        entries = []
        for ci, cand in enumerate(cands):
            g = groups[cand.group]
            m = n_cells * g.adapter.config.n_channels
            ts = time.perf_counter()
            y, rr, jtj, steps, ok, msg = _refine(cand, g, stage, prep.buffer, n_active, m, opts)
            cost = math.sqrt(rr / m) if math.isfinite(rr) else math.inf
            cand.y, cand.cost, cand.steps, cand.status, cand.success = y, cost, steps, msg, ok
            cand.rr, cand.jtj, cand.m = rr, jtj, m
            say(
                f"stage {si + 1}/{len(stages)} ({n_cells} cells) start {ci + 1}/{len(cands)} "
                f"[{cand.label}]: rms {cost:.5g}, {steps} steps, {msg} "
                f"({time.perf_counter() - ts:.1f} s)"
            )
            entries.append({"start": cand.label, "rms": cost, "steps": steps, "status": msg})
        stage_log.append({**stage.to_dict(), "n_cells_used": n_cells, "starts": entries})
        if not any(math.isfinite(c.cost) for c in cands):
            raise FitError("no start gave a finite fit (non-finite model values or residuals)")
        if si == 0 and not any(c.moves > 0 or c.success for c in cands):
            raise FitError("no start made any progress (every solver step was rejected)")
        kept, duplicates = _keep_best(cands, groups, stage, si >= len(stages) - 2)
        for e in entries:
            if e["start"] in duplicates:
                e["duplicate_of"] = duplicates[e["start"]]
                say(f"stage {si + 1}: [{e['start']}] reached [{e['duplicate_of']}]: dropped")
        if choose_type and len(groups) > 1 and (si == len(stages) - 2 or len(stages) == 1):
            best = {}
            for c in kept:
                g = groups[c.group]
                mat = g.adapter.material
                if mat not in best or c.cost < best[mat][0]:
                    params = Problem(g.adapter, g.layout, opts.metric).params(c.y, g.frozen)
                    best[mat] = (c.cost, params)
            winner, reason = _choose_type(best, _body_levels(best, groups, prep))
            rms = {k: v[0] for k, v in best.items()}
            type_selection = {"rms": rms, "chosen": winner, "reason": reason, "stage": si + 1}
            say(
                "material: "
                + ", ".join(f"{k} rms {v:.5g}" for k, v in rms.items())
                + f" -> {winner} ({reason})"
            )
            kept = [c for c in kept if groups[c.group].adapter.material == winner]
        cands = sorted(kept, key=lambda c: c.cost)
    return cands, stage_log, type_selection


#: A parameter whose unconstrained value exceeds this in magnitude is within 0.1 % of an end of
#: its range (the sigmoid maps ±6.9 to 0.001 and 0.999).
AT_BOUND_U = 6.9


def _fit_warnings(group: _Group, cand: _Candidate, params, cov_info: dict) -> list[str]:
    """One line per problem of a usable fit: step limit, parameters at a bound, rank deficiency."""
    out = []
    if not cand.success:
        out.append(f"not converged: {cand.status} after {cand.steps} steps (result kept)")
    y = np.asarray(cand.y)
    values = group.adapter.params_to_dict(params)
    start = 0
    for name, shape, size in zip(
        group.layout.names, group.layout.shapes, group.layout.sizes, strict=True
    ):
        u = y[start : start + size]
        start += size
        vals = np.ravel(np.asarray(values.get(name), dtype=np.float64))
        for j in np.flatnonzero(np.abs(u) > AT_BOUND_U):
            which = f"{name}[{j}]" if shape else name
            side = "lower" if u[j] < 0 else "upper"
            v = vals[j] if vals.size > j else math.nan
            out.append(f"{which} = {v:.4g} is at the {side} end of its range")
    if cov_info.get("rank_deficient"):
        out.append(cov_info.get("note", "rank-deficient Jacobian"))
    return out


def _errors_within(pred: np.ndarray, cells, max_theta_deg: float = 80.0) -> dict | None:
    """:func:`_errors` on the cells with ``θ_i, θ_o ≤ max_theta_deg`` (None if there is none)."""
    ok = cells.within(max_theta_deg)
    if not ok.any():
        return None
    e = _errors(pred[ok], cells.take(np.flatnonzero(ok)))
    return {"log": e["rmse_log"], "linear": e["rmse_linear"], "n_cells": int(ok.sum())}


def fit(
    data,
    *,
    config=None,
    material: str | None = None,
    metric: str = "log",
    max_theta_deg: float | None = None,
    fixed: dict | None = None,
    starts: str | Sequence = "default",
    schedule: str | Sequence[Stage] = "default",
    solver: str = "lm",
    seed: int = 0,
    rtol: float = RTOL,
    atol: float = ATOL,
    se_tol: float = SE_TOL,
    nested: bool = True,
    progress: Callable[[str], None] | None = None,
) -> FitResult:
    """Fit a BRDF model to a measured MERL table.

    Args:
        data: a :class:`twoscale.merl.MerlData` (values in 1/sr, validity mask).
        config: a :class:`twoscale.ModelConfig`, a :class:`~twoscale.baselines.CookTorranceConfig`
            (baseline), or ``None`` / ``"auto"``: the MERL protocol, :func:`merl_protocol`
            (MERL's grazing fall-off modelled on the specular lobe, its exponent ``e`` fitted; a
            plastic's body Lambertian) with the material type chosen by the fit. Pass
            ``ModelConfig()`` to fit the reference model without them.
        material: override the configuration's material type; ``"auto"`` tries conductor and
            plastic and keeps the better (compared on the last subsample stage; near-ties go to
            the physically consistent type, see :func:`_choose_type`).
        metric: ``"log"`` (default, Löw et al. 2012) or ``"linear"``; both cosine-weighted.
        max_theta_deg: fit only cells with ``θ_i, θ_o ≤`` this angle (errors still on all cells).
        fixed: ``{name: value}`` physical values of parameters held fixed (e.g. ``{"p": 1.0}``).
        starts: ``"default"`` (placed from the data) or a list of parameter objects (needs a
            single material type).
        schedule: ``"default"``, ``"preview"`` (no last refinement), ``"full"`` (the last
            refinement on every fitted cell) or a list of :class:`Stage`.
            After each stage the best ``keep`` *distinct* solutions go on: a start that ended
            within :data:`DUPLICATE_SE` standard errors of a better one is dropped (its stage
            log entry says ``duplicate_of``), so no minimum is refined twice.
        solver: ``"lm"`` (optimistix Levenberg-Marquardt) or ``"dogleg"``.
        seed: seed of the subsampling.
        rtol, atol: tolerances of optimistix's Cauchy test (scaled parameters, RMS norm).
        se_tol: also stop when the Gauss-Newton step is below this many standard errors.
        nested: with the default starts and the diffraction lobe on, first fit the same model
            with the diffraction lobe off (fewer parameters, cheap; the subsample stages), then
            start the full model from that solution: once with a weak diffraction lobe
            (``A_spec(0) = 0.95``, the *nested* start, carried through every subsample stage)
            and once per point of a small (c, A_spec(0)) grid. The full model contains the
            special case as the limit σ_s → 0, so it cannot end worse than it.
        progress: called with one line of text per start and stage (e.g. ``print``).

    Returns:
        A :class:`~twoscale.fit.FitResult`; ``warnings`` lists the problems of a usable fit
        (step limit reached, a parameter at the end of its range, a rank-deficient Jacobian).

    Raises:
        ValueError: bad arguments or no valid data. :class:`FitError`: no start gave a finite fit.
    """
    t0 = time.perf_counter()
    if not jax.config.jax_enable_x64:
        raise RuntimeError(
            "twoscale.fit needs float64: call jax.config.update('jax_enable_x64', True) first"
        )
    check_metric(metric)
    stages = _schedule(schedule)
    say = progress or (lambda _msg: None)
    fixed = dict(fixed or {})
    configs = _resolve_configs(config, material)
    if not isinstance(starts, str) and len(configs) > 1:
        raise ValueError("explicit starts need a single material type (pass material=...)")
    if isinstance(starts, str) and starts != "default":
        raise ValueError(f"starts must be 'default' or a list of parameters, got {starts!r}")
    _make_solver(solver, rtol, atol)  # check the name before any work
    opts = _SolverSettings(metric, solver, rtol, atol, se_tol)

    prep = _prepare(data, max_theta_deg, seed)
    stats = prep.stats
    say(
        f"{prep.n_fit} cells fitted of {len(prep.selection.valid)} valid; metric {metric}; "
        f"{len(stages)} stages"
    )
    # Start lists, one per configuration.
    if not isinstance(starts, str):
        start_lists = [[(f"start {i}", s) for i, s in enumerate(starts)]]
    else:
        start_lists = [adapter_for(cfg).starts(stats) for cfg in configs]
        use_nested = nested and any(getattr(cfg, "diffraction", False) for cfg in configs)
        if use_nested:
            # The diffraction-off special case of every configuration, on the subsample stages.
            spec_cfgs = [dataclasses.replace(cfg, diffraction=False) for cfg in configs]
            sub_fixed = {k: v for k, v in fixed.items() if k not in ("sigma_s", "b", "c")}
            sub_groups, sub_cands = _make_candidates(
                spec_cfgs, [adapter_for(c).starts(stats) for c in spec_cfgs], sub_fixed
            )
            sub_stages = tuple(st for st in stages if st.n_cells is not None) or stages[:1]
            ts = time.perf_counter()
            best_sub, _, _ = _run_schedule(
                prep,
                sub_groups,
                sub_cands,
                sub_stages,
                opts,
                lambda msg: say(f"[diffraction off, for the nested starts] {msg}"),
                choose_type=False,
            )
            for gi, cfg in enumerate(configs):
                mine = [c for c in best_sub if c.group == gi]
                if not mine or not cfg.diffraction:
                    continue
                g = sub_groups[gi]
                p = Problem(g.adapter, g.layout, metric).params(mine[0].y, g.frozen)
                start_lists[gi] = _nested_starts(p, cfg, fixed)
            say(f"special-case fits done ({time.perf_counter() - ts:.1f} s)")
    groups, cands = _make_candidates(configs, start_lists, fixed)
    say(f"{len(cands)} starts")
    cands, stage_log, type_selection = _run_schedule(
        prep, groups, cands, stages, opts, say, choose_type=True
    )

    best = cands[0]
    g = groups[best.group]
    problem = Problem(g.adapter, g.layout, metric)
    params = problem.params(best.y, g.frozen)
    std_errors, cov_info = _standard_errors(g, problem, best)
    if stage_log[-1]["n_cells_used"] < prep.n_fit:
        cov_info["note_subsample"] = (
            f"errors computed on the last stage's {stage_log[-1]['n_cells_used']}-cell subsample"
        )
    warnings = _fit_warnings(g, best, params, cov_info)

    valid = prep.selection.valid
    pred = predict_cells(g.adapter, params, valid)
    errs = _errors(pred, valid)
    wall = time.perf_counter() - t0
    say(
        f"done: rms log {errs['rmse_log']:.5g}, linear {errs['rmse_linear']:.5g} "
        f"({'converged' if best.success else 'not converged: ' + best.status}; {wall:.1f} s)"
    )
    settings = {
        "metric": metric,
        "max_theta_deg": max_theta_deg,
        "material": material,
        "fixed": {k: np.asarray(v).tolist() for k, v in fixed.items()},
        "starts": starts if isinstance(starts, str) else f"{len(starts)} given",
        "nested": nested,
        "schedule": [s.to_dict() for s in stages],
        "solver": solver,
        "rtol": rtol,
        "atol": atol,
        "se_tol": se_tol,
        "stall_rtol": STALL_RTOL,
        "initial_damping": INITIAL_DAMPING,
        "seed": seed,
        "chunk": CHUNK,
        "convention": "lower",
        "data_stats": stats.to_dict(),
    }
    return FitResult(
        params=params,
        model=g.adapter.name,
        config=g.adapter.config_to_dict(),
        metric=metric,
        rmse_linear=errs["rmse_linear"],
        rmse_log=errs["rmse_log"],
        per_channel=errs["per_channel"],
        rmse_fit=best.cost,
        n_valid=len(valid),
        n_fit=prep.n_fit,
        converged=bool(best.success),
        status=best.status,
        steps=best.steps,
        wall_time=wall,
        std_errors=std_errors,
        covariance=cov_info,
        settings=settings,
        versions=package_versions(),
        data={
            "name": getattr(data, "name", None),
            "path": None if getattr(data, "path", None) is None else str(data.path),
            "size_bytes": getattr(data, "size", None),
            "sha256": getattr(data, "sha256", None),
            "n_measured_valid": prep.selection.n_measured_valid,
            "n_below_horizon": prep.selection.n_below_horizon,
        },
        stages=stage_log,
        type_selection=type_selection,
        rmse_80=_errors_within(pred, valid),
        warnings=warnings,
    )

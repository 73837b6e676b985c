"""One stage's solves: an optimistix least-squares solver with the fit's stopping rules, run in
rounds on the compressed residuals of a fixed-shape cell buffer (docs/model.md §8).

:func:`refine` takes one candidate through one stage; :func:`solve` is the compiled solve (one
per model configuration and buffer shape, shared by every start and stage).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from twoscale.fit.adapters import compile_key
from twoscale.fit.candidates import Candidate, Group
from twoscale.fit.residuals import Problem, compressed_residuals, sum_squares
from twoscale.fit.schedule import Stage

#: Solver tolerances: optimistix's Cauchy test (on the scaled parameters and the compressed
#: residual, RMS norm), and the standard-error test of :func:`small_step` (either one stops).
RTOL = 1e-7


ATOL = 1e-9


SE_TOL = 0.05


#: A round of ``Stage.round_steps`` solver steps that lowers the RMS by less than this fraction
#: ends the start as converged (the RMS is stationary to the 4 digits a report shows).
STALL_RTOL = 1e-4


#: On a subsample of ``m`` residuals, the RMS itself is known to about ``1/√(2m)`` (relative):
#: a round that lowers it by less than this fraction of ``1/√m`` also ends the start
#: (:func:`stall_rtol`). On the screening stages (4 096 cells: ≈ 9e-4; 32 768: ≈ 3e-4) that stops
#: the slow creep along flat valleys that no comparison on such a subsample could resolve; on
#: 262 144 cells and more, :data:`STALL_RTOL` is the larger one.
STALL_RESOLUTION = 0.1


def stall_rtol(m: int) -> float:
    """Relative RMS change per round below which a start on ``m`` residuals has converged."""
    return max(STALL_RTOL, STALL_RESOLUTION / math.sqrt(max(m, 1)))


#: Static bound of the solver loop; the per-stage limit (``Stage.max_steps``) is a dynamic value,
#: so stages with different limits share one compiled solve.
MAX_STEPS_BOUND = 1000


def small_step(state, options):
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


class StopRules(optx.AbstractLeastSquaresSolver):
    """An optimistix least-squares solver with two more ways to stop: the step is negligible
    against the standard errors (:func:`small_step`), or ``options["step_cap"]`` steps were made
    (dynamic, unlike ``max_steps``, so stages with different limits share one compiled solve).

    Everything else is the wrapped solver's: its state (whose fields ``f_info.residual``,
    ``f_info.jac``, ``num_accepted_steps``, ``num_steps`` and ``terminate`` of optimistix's
    Gauss-Newton family this module reads; pyproject pins optimistix to the releases checked),
    its steps and its own termination test.
    """

    solver: optx.AbstractLeastSquaresSolver

    @property
    def rtol(self):
        return self.solver.rtol

    @property
    def atol(self):
        return self.solver.atol

    @property
    def norm(self):
        return self.solver.norm

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        return self.solver.init(fn, y, args, options, f_struct, aux_struct, tags)

    def step(self, fn, y, args, options, state, tags):
        return self.solver.step(fn, y, args, options, state, tags)

    def terminate(self, fn, y, args, options, state, tags):
        terminate, result = self.solver.terminate(fn, y, args, options, state, tags)
        stop = small_step(state, options) | (state.num_steps >= options["step_cap"])
        return terminate | stop, result

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return self.solver.postprocess(fn, y, aux, args, options, state, tags, result)


def make_solver(name: str, rtol: float, atol: float):
    """The solver ``name`` (``"lm"`` or ``"dogleg"``) with the fit's stopping rules."""
    if name == "lm":
        return StopRules(optx.LevenbergMarquardt(rtol=rtol, atol=atol, norm=optx.rms_norm))
    if name == "dogleg":
        return StopRules(optx.Dogleg(rtol=rtol, atol=atol, norm=optx.rms_norm))
    raise ValueError(f"solver must be 'lm' or 'dogleg', got {name!r}")


#: Initial Levenberg-Marquardt damping relative to the diagonal of JᵀJ (see :func:`scales`).
INITIAL_DAMPING = 1e-3


#: Largest scale of a free parameter in unconstrained units (for parameters with ~no influence).
_MAX_SCALE = 10.0


#: Relative damping (Levenberg-Marquardt's λ over the diagonal of JᵀJ) past which :func:`refine`
#: stops a start whose steps are all rejected: its steps are then about a hundred-thousandth of a
#: gradient step and still do not lower the cost, so it sits at its minimum to the precision of
#: the residuals.
MAX_DAMPING = 1e5


def scales(jtj: np.ndarray) -> np.ndarray:
    """Per-parameter scales ``σ_j = 1/(√(JᵀJ)_jj √μ0)``: the solver works on ``z = (y − y0)/σ``.

    optimistix's Levenberg-Marquardt damps with ``λ I`` and starts at ``λ = 1``; in ``z`` the
    Gauss-Newton matrix has diagonal ``1/μ0``, so its first step has relative damping
    ``μ0`` = :data:`INITIAL_DAMPING` whatever the units of the parameters (Marquardt's scaling).
    """
    d = np.sqrt(np.maximum(np.diag(np.asarray(jtj)), 0.0))
    with np.errstate(divide="ignore"):
        s = 1.0 / (d * math.sqrt(INITIAL_DAMPING))
    return np.where(np.isfinite(s), np.minimum(s, _MAX_SCALE), _MAX_SCALE)


class Solved(NamedTuple):
    """What one call of :func:`solve` returns (arrays; a pytree)."""

    y: jax.Array  # where the solve ended (y0 after a solve of one step)
    result: optx.RESULTS
    converged: jax.Array  # the solver's own test or the standard-error test, not the step limit
    steps: jax.Array  # solver steps made, the first one (evaluating y0) included
    moves: jax.Array  # accepted steps after the evaluation of y0
    rr: jax.Array  # rᵀr at y
    jtj: jax.Array  # JᵀJ at y
    step_size: jax.Array  # the trust region's size in z at the end (1 at the start)


@eqx.filter_jit
def solve(
    problem, y0, frozen, data, n_active, step_cap, n_resid, scale, rtol, atol, se_tol, solver_name
):
    """Least-squares solve from ``y0`` on the active chunks of ``data``, at most ``step_cap`` steps.

    The solver works on ``z = (y − y0)/scale``. Its first step only evaluates the residuals and
    their Jacobian at ``y0`` (so a solve of ``step_cap`` steps makes ``step_cap − 1`` moves).
    Returns a :class:`Solved` (``JᵀJ`` in ``y``, from the solver's final linearisation, and
    ``rᵀr`` from its compressed residual: no extra pass over the data; a solve of one step gives
    them at ``y0``; Levenberg-Marquardt's damping is the inverse of the step size).
    """
    solver = make_solver(solver_name, rtol, atol)

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
    converged = (sol.state.terminate | small_step(sol.state, options)) & (
        sol.result == optx.RESULTS.successful
    )
    moves = sol.state.num_accepted_steps - 1  # accepted steps after the evaluation of y0
    return Solved(
        y,
        sol.result,
        converged,
        sol.stats["num_steps"],
        moves,
        rr,
        j_c.T @ j_c,
        sol.state.search_state.step_size,
    )


@eqx.filter_jit
def jit_sum_squares(problem, y, frozen, data, n_active):
    return sum_squares(problem, y, frozen, data, n_active)


def result_message(result) -> str:
    for item, msg in (
        (optx.RESULTS.successful, ""),
        (optx.RESULTS.nonlinear_max_steps_reached, "maximum number of steps reached"),
        (optx.RESULTS.nonlinear_divergence, "diverged"),
        (optx.RESULTS.nonfinite, "non-finite values"),
    ):
        if bool(result == item):
            return msg
    return "linear solve failed"


@dataclasses.dataclass(frozen=True)
class SolverSettings:
    """Everything a stage's solves need besides the data and the candidate."""

    metric: str
    solver: str
    rtol: float
    atol: float
    se_tol: float


def _run_solve(g: Group, y0, data, n_active: int, cap: int, m: int, scale, opts):
    """One call of the compiled :func:`solve` for a candidate of group ``g``."""
    return solve(
        Problem(g.adapter, g.layout, opts.metric),
        y0,
        g.frozen,
        data,
        # NumPy arrays, not jnp ones: the compiled call takes them as they are, where creating
        # each with JAX first is an eager operation (≈ 2 ms each while other threads trace).
        np.asarray(n_active, np.int32),  # dynamic: one compiled solve serves every stage
        np.asarray(cap, np.int32),  # dynamic too
        np.asarray(m, np.int32),
        np.asarray(scale, y0.dtype),
        opts.rtol,
        opts.atol,
        opts.se_tol,
        opts.solver,
    )


def _group_key(g: Group, opts) -> tuple:
    return (compile_key(g.adapter), g.layout, opts.metric, opts.solver)


#: Background threads that compile ahead (:class:`Warmup`). Two compile the special cases' and
#: the full models' solves side by side while the fit waits for them on an empty compilation
#: cache: pvc's ``--preview`` 33.3 → 27.3–27.9 s end to end, its default CLI 38.6 → 34.6 s
#: (2-core machine, 2026-12-05); three were no faster (28.8 s); with a warm cache the same time
#: (nickel's preview 14.6–15.3 s either way).
WARMUP_THREADS = 2


class Warmup:
    """Compiles the solves of groups that a fit will need, in :data:`WARMUP_THREADS` background
    threads (in the order they were queued).

    Each call of :meth:`submit` queues a call of the compiled :func:`solve` on no cells (one
    solver step that only evaluates its start): its result is discarded, but the call traces
    and compiles the solve, and JAX keeps the compiled function for every later call with the
    same configuration and shapes. XLA compiles without holding Python's lock, so the fit's
    current solves (a few thousand cells) and the compilation of the next configurations
    overlap. :meth:`wait` is called before a group's first solve, so no solve is compiled
    twice; a warm-up that fails only costs its time (the fit's own call then compiles, or
    raises, as without it).
    """

    def __init__(self, data, opts):
        self._data, self._opts = data, opts
        self._pool = concurrent.futures.ThreadPoolExecutor(
            WARMUP_THREADS, thread_name_prefix="twoscale-warmup"
        )
        self._futures: dict = {}

    def submit(self, g: Group, y0) -> None:
        key = _group_key(g, self._opts)
        if key not in self._futures and g.layout.size > 0:
            self._futures[key] = self._pool.submit(
                lambda: jax.block_until_ready(
                    _run_solve(g, y0, self._data, 0, 1, 1, np.ones(g.layout.size), self._opts)
                )
            )

    def submit_call(self, key, fn) -> None:
        """Queue ``fn()`` (e.g. a call that compiles another function the fit will use) under
        ``key``; :meth:`wait_key` waits for it."""
        if key not in self._futures:
            self._futures[key] = self._pool.submit(lambda: jax.block_until_ready(fn()))

    def wait(self, g: Group) -> None:
        self.wait_key(_group_key(g, self._opts))

    def wait_key(self, key) -> None:
        future = self._futures.get(key)
        if future is not None:
            concurrent.futures.wait([future])

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


def start_cost(y, g: Group, data, n_active: int, m: int, opts) -> float:
    """``rᵀr`` at ``y`` on the active chunks of ``data``: the group's compiled solve, one step
    (which only evaluates its start), so no other function is compiled for it."""
    n = g.layout.size
    if n == 0:
        problem = Problem(g.adapter, g.layout, opts.metric)
        return float(jit_sum_squares(problem, y, g.frozen, data, jnp.int32(n_active)))
    return float(_run_solve(g, y, data, n_active, 1, m, np.ones(n), opts).rr)


def refine(cand: Candidate, g: Group, stage: Stage, data, n_active: int, m: int, opts, twin=None):
    """Run the solver on one candidate for one stage, in rounds (see :class:`Stage`).

    Returns ``(y, rr, jtj, steps, converged, status)``; ``cand.moves`` counts the accepted
    solver steps (0 after a stage: no step from the start lowered the cost). ``twin(y)``, when
    given, is asked after every round that did not end the start: the label of a start already
    finished on this stage whose minimum ``y`` has reached (within
    :data:`~twoscale.fit.candidates.DUPLICATE_SE` standard errors), or None. On a label the start
    stops there (``cand.twin`` = that label): it would only have gone on into the same minimum.
    """
    cand.twin = None
    n = g.layout.size

    def run(y0, cap, scale):
        return _run_solve(g, y0, data, n_active, cap, m, scale, opts)

    y = cand.y
    if n == 0:
        rr = start_cost(y, g, data, n_active, m, opts)
        return y, rr, np.zeros((0, 0)), 0, True, "every parameter fixed"
    # A solve of one step only linearises at y: rᵀr there (each round's reference, for the stall
    # rule; a round then starts where the last one ended) and JᵀJ for the scales (Marquardt's
    # scaling), on this stage's cells.
    first = run(y, 1, np.ones(n))
    rr, jtj = float(first.rr), np.asarray(first.jtj)
    steps = 0
    stall = stall_rtol(m)
    # The damping a round starts from, relative to INITIAL_DAMPING: where the last round left
    # it, never below 1 (see below).
    damp = 1.0
    power = 2.0 if opts.solver == "dogleg" else 1.0  # a trust radius in z scales as 1/√damp
    while steps < stage.max_steps:
        # At least 2: the first step of a solve only evaluates its starting point.
        cap = max(2, min(stage.round_steps, stage.max_steps - steps))
        out = run(y, cap, scales(jtj) / math.sqrt(damp))
        rr0, rr_new = rr, float(out.rr)
        msg = result_message(out.result)
        moves = int(out.moves)
        steps += int(out.steps)
        cand.moves += moves
        if not (math.isfinite(rr_new) and np.all(np.isfinite(np.asarray(out.y)))):
            return y, rr, jtj, steps, False, msg or "non-finite values"
        fell = (rr0 - rr_new) / rr0 if math.isfinite(rr0) and rr0 > 0 else math.inf
        y, rr, jtj = out.y, rr_new, np.asarray(out.jtj)
        if bool(out.converged):
            return y, rr, jtj, steps, True, "converged"
        if msg and out.result != optx.RESULTS.nonlinear_max_steps_reached:
            return y, rr, jtj, steps, False, msg
        cand.twin = None if twin is None else twin(y)
        if cand.twin is not None:
            return y, rr, jtj, steps, False, f"stopped: reached the minimum of [{cand.twin}]"
        # RMS relative change ≈ half the relative change of rᵀr; a round whose steps were all
        # rejected says nothing (the damping was still growing).
        if moves > 0 and 0.5 * fell < stall:
            return y, rr, jtj, steps, True, f"converged (RMS changed < {stall:.2g} in a round)"
        # The next round starts from the damping this one ended with (never below the usual
        # start): each round restarts the solver, and one that starts from the same point
        # with the same scales as a round whose steps were all rejected repeats those steps
        # (fruitwood-241's last stage: five rounds, 25 steps, none accepted, 2026-12-05).
        size = float(out.step_size)
        damp = max(1.0, damp / size**power) if math.isfinite(size) and size > 0 else damp
        if moves == 0 and damp * INITIAL_DAMPING > MAX_DAMPING:
            return y, rr, jtj, steps, True, "converged (no step lowers the RMS)"
    return y, rr, jtj, steps, False, "step limit reached"

"""Evaluating a fit: model values at cells, RMSE of both metrics, standard errors, warnings."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from twoscale.fit.candidates import Candidate, Group
from twoscale.fit.cells import CHUNK, DIRECTION_CHUNKS, pack_directions
from twoscale.fit.residuals import Problem, predict


@eqx.filter_jit
def jit_predict(fn, params, data, n_active, n_out):
    return predict(fn, params, data, n_active, n_out)


@eqx.filter_jit
def physical_free(problem, y, frozen, spec):
    """Flat physical values of the free parameters, and their Jacobian in ``y``."""

    def phys(yy):
        params = problem.params(yy, frozen)
        free, _ = eqx.partition(params, spec)
        leaves = jax.tree_util.tree_leaves(free)
        return jnp.concatenate([jnp.ravel(x) for x in leaves])

    return phys(y), jax.jacfwd(phys)(y)


def rmse(pred: np.ndarray, cells, log_scale=None) -> dict:
    """RMSE of the metrics, overall and per channel, for predictions on ``cells``: linear, log
    and scaled log (with ``log_scale`` ``(C,)``, default ``cells.log_scale()``)."""
    cos = cells.cos_i[:, None]
    lin = (pred - cells.rho) * cos
    pos = np.maximum(pred, 0.0)

    def log_diff(weight):  # the log metric's residuals with cos θ_i / s as the weight
        return np.log1p(pos * weight) - np.log1p(cells.rho * weight)

    s = cells.log_scale() if log_scale is None else np.asarray(log_scale)
    log, slog = log_diff(cos), log_diff(cos / s)
    return {
        "rmse_linear": float(np.sqrt(np.mean(lin**2))),
        "rmse_log": float(np.sqrt(np.mean(log**2))),
        "rmse_log_scaled": float(np.sqrt(np.mean(slog**2))),
        "per_channel": {
            "rmse_linear": np.sqrt(np.mean(lin**2, axis=0)).tolist(),
            "rmse_log": np.sqrt(np.mean(log**2, axis=0)).tolist(),
            "rmse_log_scaled": np.sqrt(np.mean(slog**2, axis=0)).tolist(),
        },
    }


def rmse_within(
    pred: np.ndarray, cells, max_theta_deg: float = 80.0, log_scale=None
) -> dict | None:
    """:func:`rmse` on the cells with ``θ_i, θ_o ≤ max_theta_deg`` (None if there is none);
    the scaled log uses ``log_scale`` (default: that of all ``cells``)."""
    ok = cells.within(max_theta_deg)
    if not ok.any():
        return None
    s = cells.log_scale() if log_scale is None else log_scale
    e = rmse(pred[ok], cells.take(np.flatnonzero(ok)), s)
    return {
        "log": e["rmse_log"],
        "scaled_log": e["rmse_log_scaled"],
        "linear": e["rmse_linear"],
        "n_cells": int(ok.sum()),
    }


def predict_cells(adapter, params, cells) -> np.ndarray:
    """Model values ``(N, C)`` at the cells (one compiled pass per model configuration).

    Factorised adapters (the two-scale model) evaluate the whole MERL grid by its fast path
    (:func:`twoscale.model.brdf_grid`) and take the cells from it; the others go through the
    fixed-shape direction buffer.
    """
    if adapter.factorised:
        grid = np.asarray(adapter.evaluate_grid(params, "lower"))
        return grid.reshape(-1, grid.shape[-1])[np.asarray(cells.index)]
    return evaluate_at(adapter.evaluate, params, cells.wi, cells.wo, adapter.config.n_channels)


#: Chunks of the buffer for calls of :func:`evaluate_at` with few directions (pictures:
#: 18,526 at most): packing and scanning the whole MERL-sized buffer cost ≈ 70 ms a call.
SMALL_DIRECTION_CHUNKS = 16


def evaluate_at(fn, params, wi, wo, n_out: int, *, small: bool = False) -> np.ndarray:
    """``fn(params, wi, wo) -> (N, n_out)`` at NumPy directions ``(N, 3)``, through a
    fixed-shape buffer (:data:`SMALL_DIRECTION_CHUNKS` chunks for up to that many directions,
    else MERL-sized: every call with the same ``fn`` and size class shares one compiled function).
    ``small``: the small buffer whatever ``N`` (several calls of its compiled function)."""
    wi = np.asarray(wi, dtype=np.float64).reshape(-1, 3)
    wo = np.asarray(wo, dtype=np.float64).reshape(-1, 3)
    n = wi.shape[0]
    small = small or n <= SMALL_DIRECTION_CHUNKS * CHUNK
    n_chunks = SMALL_DIRECTION_CHUNKS if small else DIRECTION_CHUNKS
    cap = n_chunks * CHUNK
    out = []
    for start in range(0, max(n, 1), cap):
        sl = slice(start, min(start + cap, n))
        buf, n_active = pack_directions(wi[sl], wo[sl], n_chunks)
        pred = np.asarray(jit_predict(fn, params, buf, jnp.int32(n_active), n_out))
        out.append(pred.reshape(-1, n_out)[: wi[sl].shape[0]])
    return np.concatenate(out, axis=0)


def standard_errors(group: Group, problem: Problem, cand: Candidate) -> tuple[dict, dict]:
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
    _, jac = physical_free(problem, cand.y, group.frozen, group.spec)
    jac = np.asarray(jac)
    cov_p = jac @ cov_u @ jac.T
    se_flat = np.sqrt(np.maximum(np.diag(cov_p), 0.0))
    std = by_name(group, se_flat)
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
        null = by_name(group, np.abs(evecs[:, ~keep]).max(axis=1))
        weak = [k for k, v in null.items() if v is not None and np.max(v) > 0.3]
        info["note"] = (
            f"Jacobian rank {rank} < {n} free parameters: pseudo-inverse used; "
            f"{', '.join(weak) or 'some parameters'} not determined by the data "
            "(their errors are unreliable)"
        )
    return std, info


def by_name(group: Group, flat) -> dict:
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


#: A parameter whose unconstrained value exceeds this in magnitude is within 0.1 % of an end of
#: its range (the sigmoid maps ±6.9 to 0.001 and 0.999).
AT_BOUND_U = 6.9


#: A measured table whose bihemispherical albedo (:func:`twoscale.merl.bihemispherical_albedo`)
#: is above this in some channel reflects more light than it receives: an energy-conserving
#: BRDF's is at most 1 (the 60 stand-ins': 0.017-0.46), and no model of the library can reach
#: such data, so the fit is flagged (values not in 1/sr, a scale applied twice).
ALBEDO_IMPLAUSIBLE = 1.5


def data_warnings(stats) -> list[str]:
    """One line per problem of the data that no fit can mend (see :data:`ALBEDO_IMPLAUSIBLE`)."""
    if stats.albedo is None:
        return []
    albedo = np.asarray(stats.albedo, dtype=np.float64)
    if not np.max(albedo) > ALBEDO_IMPLAUSIBLE:
        return []
    return [
        f"the data reflects more light than it receives (albedo {np.max(albedo):.3g} in channel "
        f"{int(np.argmax(albedo))}; at most 1 for a physical material): values not in 1/sr? "
        "(MERL's files hold the raw values, scaled by the reader), the fit cannot match them"
    ]


#: A fitted diffuse floor more than this factor above or below the measured one, in a channel
#: where either is visible (:data:`FLOOR_VISIBLE`), is flagged: the fit's pictures then show
#: the wrong body. Good fits of the 60 stand-ins keep it within tens of percent.
FLOOR_RATIO_WARN = 3.0
#: ``π ×`` a floor level (the albedo of a Lambertian body at that level) below which a body is
#: too faint to see next to a highlight; a metal's far tail is usually below it.
FLOOR_VISIBLE = 0.03


def floor_warnings(fitted, measured, metric: str | None = None) -> list[str]:
    """One line when the fitted model's diffuse floor is off the measured one by more than
    :data:`FLOOR_RATIO_WARN` in a channel where the body is visible (both are
    :func:`~twoscale.fit.starts.floor_level`: the median over ``θ_h ∈ [50°, 70°]``,
    ``θ_d ≤ 30°``). A fit can minimise its metric and still render a body of the wrong colour:
    the linear metric weighs the highlight's thousands of 1/sr and hardly a body of 0.02 1/sr
    (red-specular-plastic with ``--metric linear``: ρ_d = 1, 1, 0, a yellow sphere for a red
    one, at exit 0 without a word)."""
    fitted = np.asarray(fitted, dtype=np.float64)
    measured = np.asarray(measured, dtype=np.float64)
    names = "RGB" if fitted.size == 3 else None
    off = []
    for c, (f, m) in enumerate(zip(fitted, measured, strict=True)):
        if math.pi * max(f, m) < FLOOR_VISIBLE:
            continue
        ratio = f / m if m > 0.0 else math.inf
        if not 1.0 / FLOOR_RATIO_WARN <= ratio <= FLOOR_RATIO_WARN:
            off.append(f"{names[c] if names else c}: {ratio:.3g}×")
    if not off:
        return []
    hint = (
        " (the linear metric weighs the highlight, hardly the body; the default metric fits both)"
        if metric == "linear"
        else ""
    )
    return [
        f"the fitted diffuse floor is off the measured one ({', '.join(off)}; θ_h 50–70°, "
        f"θ_d ≤ 30°): the pictures show a body of the wrong colour or brightness{hint}"
    ]


def fit_warnings(group: Group, cand: Candidate, params, cov_info: dict) -> list[str]:
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


def warm_evaluation(adapter, params) -> np.ndarray:
    """Compile the evaluation that a fit's pictures and albedo table use (two-scale: its lobes,
    :meth:`~twoscale.fit.adapters.TwoScaleAdapter.evaluate_lobes`; otherwise the model) by
    calling it at one direction pair."""
    d = np.array([[0.0, 0.0, 1.0]])
    n_ch = adapter.config.n_channels
    if hasattr(adapter, "evaluate_lobes"):
        from twoscale.fit.adapters import LOBES

        return evaluate_at(adapter.evaluate_lobes, params, d, d, len(LOBES) * n_ch)
    return evaluate_at(adapter.evaluate, params, d, d, n_ch)


def material_evaluator(adapter, params):
    """``f(wi, wo) -> (N, L, C)``: a two-scale fit's material without MERL's apparatus factor
    (``e = 0`` makes it 1 above the horizon), each lobe apart in the order of
    :data:`~twoscale.fit.adapters.LOBES` (0 for a lobe switched off; their sum is the BRDF),
    through the compiled evaluation of the pictures (:func:`warm_evaluation`), in calls of the
    small buffer."""
    from twoscale.fit.adapters import LOBES

    if adapter.config.apparatus and params.e is not None:
        params = params.replace(e=jnp.zeros_like(params.e))
    n_ch = adapter.config.n_channels

    def f(wi, wo):
        vals = evaluate_at(adapter.evaluate_lobes, params, wi, wo, len(LOBES) * n_ch, small=True)
        return vals.reshape(-1, len(LOBES), n_ch)

    return f

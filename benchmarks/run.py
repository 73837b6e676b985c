"""Measure and publish the speed / accuracy trade of ``twoscale``.

    python -m benchmarks.run [--quick] [--out DIR] [--only speed,trade,variants] [--device]

Writes ``speed.md``, ``trade.md`` and ``variants.md`` (and ``speed_<platform>.md`` with
``--device`` on an accelerator) under ``benchmarks/results/`` and prints them. Every time is the
median of repeated warm runs; compile time is reported separately. ``--quick`` shrinks every
size (for development and the smoke test); its figures are not the reference ones.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import jax
import numpy as np

from benchmarks import common
from benchmarks.common import fmt, fmt_time, table

N_GRID = 90 * 90 * 180
TARGETS = {
    "merl_ratio": 1.0,  # brdf_merl ÷ plain JAX GGX + Lambert, same run
    "dirs_ratio": 3.0,  # brdf at any directions ÷ plain JAX GGX + Lambert, same run
    "jacobian": 0.3,
    "fit": 60.0,
    "preview": 10.0,
    "scipy_ratio": 10.0,
    "rss": 4e9,
}


@dataclasses.dataclass
class Sizes:
    grid_stride: int = 1  # every k-th MERL cell for the evaluation timings
    repeats: int = 9
    fit_repeats: int = 2
    ref_cells: int = 20000  # exact-path reference subsample
    scipy_cells: int = 32768
    scipy_max_nfev: int = 60
    materials: tuple = ("nickel", "red-specular-plastic")
    fits: bool = True
    trade_fits: bool = True
    # Table variants refitted in the trade section (each is a fresh process that compiles its
    # fit: ≈ 30 s on 2 cores).
    trade_fit_variants: tuple = ("cubic (default)", "multilinear", "cubic, every 2nd node")
    fit_schedule: str = "default"
    preview_schedule: str = "preview"
    mitsuba: bool = True
    # The variants section fits every variant (first and warm run), or with "last" only the
    # last (the MERL protocol), once: the quick run's smoke test of that path.
    variant_fits: str = "all"


QUICK = Sizes(
    grid_stride=64,
    repeats=3,
    fit_repeats=1,
    ref_cells=1000,
    scipy_cells=1024,
    scipy_max_nfev=10,
    materials=("nickel",),
    trade_fit_variants=("cubic (default)", "multilinear"),
    fit_schedule="tiny",
    preview_schedule="tiny",
    variant_fits="last",
)
SMOKE = dataclasses.replace(
    QUICK,
    grid_stride=4000,
    repeats=1,
    ref_cells=64,
    scipy_cells=256,
    scipy_max_nfev=2,
    fits=False,
    trade_fits=False,
    mitsuba=False,
)


def _params():
    from benchmarks.fit_worker import TRUE_PARAMS

    return TRUE_PARAMS()


def _grid(stride: int = 1):
    """MERL lower-edge directions of every ``stride``-th cell, ``(N, 3)`` each (NumPy)."""
    from twoscale import merl

    wi, wo = merl.MerlData(
        values=np.zeros(merl.SHAPE + (3,)), valid=np.ones(merl.SHAPE, bool)
    ).directions("lower")
    wi = np.asarray(wi, dtype=np.float64).reshape(-1, 3)[::stride]
    wo = np.asarray(wo, dtype=np.float64).reshape(-1, 3)[::stride]
    return wi, wo


def _reference_cells(n: int, seed: int = 0):
    """A fixed random subsample of ``n`` above-horizon MERL cells."""
    wi, wo = _grid(1)
    above = np.flatnonzero((wi[:, 2] > 0) & (wo[:, 2] > 0))
    idx = np.sort(np.random.default_rng(seed).choice(above, size=min(n, above.size), replace=False))
    return wi[idx], wo[idx]


def _eval_time(params, wi, wo, config, repeats: int, dtype=None):
    import jax.numpy as jnp

    import twoscale

    dtype = dtype or jnp.float64
    a, b = jnp.asarray(wi, dtype), jnp.asarray(wo, dtype)
    p = params.astype(dtype)
    f = jax.jit(lambda pp, x, y: twoscale.brdf(pp, x, y, config))
    t = common.timed(lambda: f(p, a, b), repeats)
    return t


def _grid_time(params, config, repeats: int, dtype=None):
    """One warm evaluation of the whole MERL grid by the grid path (``brdf_grid``)."""
    import jax.numpy as jnp

    import twoscale

    dtype = dtype or jnp.float64
    grid = twoscale.model.merl_grid("lower", dtype)
    p = params.astype(dtype)
    f = jax.jit(lambda pp, g: twoscale.brdf_grid(pp, g, config))
    return common.timed(lambda: f(p, grid), repeats)


def _target(name: str, value: float, lower_is_better: bool = True) -> str:
    goal = TARGETS[name]
    ok = value <= goal if lower_is_better else value >= goal
    return "PASS" if ok else "MISS"


# ------------------------------------------------------------------------------------- speed
def _mitsuba_eval(wi, wo, repeats: int):
    """Mitsuba 3 ``roughconductor`` (GGX and Beckmann, llvm_ad_rgb) ``bsdf.eval`` on the directions.

    Returns ``({distribution: timed dict}, note)``, or ``(None, reason)`` when Mitsuba or its LLVM
    backend cannot be loaded (libLLVM is found as :mod:`twoscale.mitsuba` finds it).
    """
    try:
        from twoscale.mitsuba import _import

        mi, dr = _import("llvm_ad_rgb")
    except Exception as err:  # noqa: BLE001 - any failure to import / initialise skips the row
        return None, f"Mitsuba 3 unavailable ({type(err).__name__}: {err})"
    n = wi.shape[0]
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(*(np.ascontiguousarray(wi[:, j], dtype=np.float32) for j in range(3)))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    wo_m = mi.Vector3f(*(np.ascontiguousarray(wo[:, j], dtype=np.float32) for j in range(3)))
    ctx = mi.BSDFContext()
    out = {}
    for dist in ("ggx", "beckmann"):
        bsdf = mi.load_dict(
            {
                "type": "roughconductor",
                "distribution": dist,
                "alpha": 0.1,
                "material": "Au",
                "sample_visible": False,
            }
        )

        def run(bsdf=bsdf):
            val = bsdf.eval(ctx, si, wo_m)
            dr.eval(val)
            dr.sync_thread()
            return None

        out[dist] = common.timed(run, repeats)
        out[dist].pop("out")
    lib = os.environ.get("DRJIT_LIBLLVM_PATH", "libLLVM")
    return out, f"Mitsuba {mi.__version__}, drjit {dr.__version__}, float32, {Path(lib).name}"


def _mitsuba_subprocess(sizes: Sizes):
    """Run :mod:`benchmarks.mitsuba_worker` (a crash of Dr.Jit's LLVM backend skips the row)."""
    import json
    import subprocess

    root = str(Path(__file__).resolve().parents[1])
    env = dict(os.environ, PYTHONPATH=root)
    cmd = [
        sys.executable,
        "-m",
        "benchmarks.mitsuba_worker",
        str(sizes.grid_stride),
        str(sizes.repeats),
    ]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=root, timeout=600)
    except subprocess.TimeoutExpired:
        return None, "Mitsuba 3 timed out"
    lines = [x for x in proc.stdout.splitlines() if x.startswith("{")]
    if proc.returncode or not lines:
        err = [x for x in proc.stderr.splitlines() if x.strip()]
        return (
            None,
            f"Mitsuba 3 failed (exit {proc.returncode}): {err[0][:160] if err else 'no output'}",
        )
    r = json.loads(lines[-1])
    if "error" in r:
        return None, r["error"]
    return r, r["note"]


def _protocol_configs() -> dict:
    """The MERL protocol's two model configurations (what the default CLI fits), by name."""
    from twoscale.fit.material_type import resolve_configs

    return {
        "plastic": resolve_configs(None, "plastic")[0],
        "conductor with its floor": resolve_configs(None, "conductor")[0],
    }


def _jacobian_time(repeats: int, stride: int, config=None):
    """Normal equations ``(JᵀJ, Jᵀr, rᵀr)`` over all fitted cells, as the fit computes them
    (``config``: the model configuration; the reference conductor ``ModelConfig()`` by default)."""
    import equinox as eqx
    import jax.numpy as jnp

    import twoscale
    from benchmarks.fit_worker import synthetic_material
    from twoscale.fit import cells as cl
    from twoscale.fit import residuals as rs
    from twoscale.fit.adapters import adapter_for
    from twoscale.fit.starts import data_stats

    data = synthetic_material()
    sel = cl.select_cells(data)
    cells = sel.fit.take(np.arange(0, len(sel.fit), stride))
    pairs = cl.pair_cells(cells)
    buffer, n_active = cl.pack(pairs)
    adapter = adapter_for(twoscale.ModelConfig() if config is None else config)
    _, p0 = adapter.starts(data_stats(np.asarray(data.values), np.asarray(data.valid)))[0]
    free, frozen = eqx.partition(adapter.to_unconstrained(p0), True)
    layout = rs.Layout.of(free)
    problem = rs.Problem(adapter, layout, rs.DEFAULT_METRIC)
    y = layout.ravel(free)
    f = eqx.filter_jit(rs.normal_equations)
    t = common.timed(lambda: f(problem, y, frozen, buffer, jnp.int32(n_active)), repeats)
    seeds = problem.seeds()[0].shape[0]
    return t, {
        "cells": len(cells),
        "pairs": len(pairs),
        "residuals": len(cells) * 3 * rs.residuals_per_cell(rs.DEFAULT_METRIC),
        "metric": rs.DEFAULT_METRIC,
        "params": layout.size,
        "seeds": seeds,
    }


def _scipy_vs_twoscale(sizes: Sizes):
    """Same cells, same start, same log metric: twoscale.fit (one stage) vs SciPy least_squares."""
    from scipy.optimize import least_squares

    import twoscale
    from benchmarks import numpy_model as nm
    from benchmarks.fit_worker import synthetic_material
    from twoscale.fit.adapters import adapter_for
    from twoscale.fit.cells import select_cells
    from twoscale.fit.schedule import Stage
    from twoscale.fit.starts import data_stats
    from twoscale.params import bounds_for

    data = synthetic_material()
    sel = select_cells(data)
    rng = np.random.default_rng(3)
    keep = np.zeros(data.valid.size, bool)
    keep[
        rng.choice(sel.valid.index, size=min(sizes.scipy_cells, len(sel.valid)), replace=False)
    ] = True
    sub = twoscale.MerlData(
        values=data.values, valid=keep.reshape(data.valid.shape), path=None, name="subset"
    )
    cells = select_cells(sub).valid
    adapter = adapter_for(twoscale.ModelConfig())
    label, p0 = adapter.starts(data_stats(np.asarray(data.values), np.asarray(data.valid)))[5]

    # twoscale: one stage on all the subset's cells, the same single start.
    stage = [Stage(n_cells=None, keep=1, max_steps=100)]
    ts = []
    for _ in range(2):
        t0 = time.perf_counter()
        res = twoscale.fit(
            sub,
            config=twoscale.ModelConfig(material="conductor"),
            starts=[p0],
            schedule=stage,
            metric="log",  # SciPy's residuals below: the plain log metric
        )
        ts.append(time.perf_counter() - t0)

    # SciPy: TRF with bounds (the same valid ranges), 2-point finite-difference Jacobian.
    names = nm.PARAM_NAMES
    lo = np.concatenate(
        [np.full(3 if n in ("eta", "k") else 1, bounds_for(n, "conductor").lo) for n in names]
    )
    hi = np.concatenate(
        [np.full(3 if n in ("eta", "k") else 1, bounds_for(n, "conductor").hi) for n in names]
    )
    x0 = np.clip(nm.pack(p0.to_dict()), lo, hi)
    cos = cells.cos_i[:, None]
    target = np.log1p(cells.rho * cos)

    def resid(x):
        pred = nm.brdf(nm.unpack(x), cells.wi, cells.wo)
        return (np.log1p(np.maximum(pred, 0.0) * cos) - target).ravel()

    t0 = time.perf_counter()
    sp = least_squares(
        resid,
        x0,
        jac="2-point",
        bounds=(lo, hi),
        method="trf",
        x_scale="jac",
        max_nfev=sizes.scipy_max_nfev,
    )
    t_sp = time.perf_counter() - t0
    rmse_sp = float(np.sqrt(np.mean(sp.fun**2)))
    return {
        "cells": len(cells),
        "start": label,
        "twoscale_first": ts[0],
        "twoscale": ts[-1],
        "twoscale_runs": ts[1:],
        "twoscale_rmse": res.rmse_log,
        "twoscale_steps": res.steps,
        "scipy": t_sp,
        "scipy_rmse": rmse_sp,
        "scipy_nfev": int(sp.nfev),
        "scipy_njev": int(sp.njev or 0),
        "scipy_status": sp.message,
    }


def _spread(t: dict, scale: float = 1.0) -> str:
    """``min–max`` of the warm runs (scaled), and how many there were."""
    runs = [r * scale for r in t["runs"]]
    return f"{fmt_time(min(runs))}–{fmt_time(max(runs))} ({len(runs)})"


def speed(sizes: Sizes, label: str = "") -> tuple[str, list[str]]:
    import jax.numpy as jnp

    import twoscale
    from benchmarks import numpy_model as nm
    from benchmarks import reference

    wi, wo = _grid(sizes.grid_stride)
    n = wi.shape[0]
    scale = N_GRID / n
    params = _params()
    rows, verdicts = [], []
    # The peer every figure is divided by: plain JAX GGX + Lambert at the same pairs, this run.
    refs = {}
    for dtype in (jnp.float64, jnp.float32):
        args = reference.ggx_inputs(wi, wo, dtype)
        refs[dtype] = common.timed(lambda a=args: reference.ggx_lambert(*a), sizes.repeats)
    ggx = refs[jnp.float64]["median"] * scale

    def row(what, t, sc=1.0, compile_=None, rss="—", target="", ref=ggx):
        med = t["median"] * sc
        rows.append(
            [
                what,
                fmt_time(med),
                _spread(t, sc),
                f"{med / ref:.2f}×",
                fmt_time(t["compile"] if compile_ is None else compile_),
                rss,
                target,
            ]
        )
        return med

    for dtype, name in ((jnp.float64, "float64"), (jnp.float32, "float32")):
        row(
            f"Plain JAX GGX + Lambert (`benchmarks/reference.py`: Schlick F0, separable Smith G) "
            f"at the 1,458,000 pairs, {name}",
            refs[dtype],
            scale,
            ref=refs[dtype]["median"] * scale,
            target="reference (1×)" + (" for the float32 rows" if dtype == jnp.float32 else ""),
        )
    # The MERL-grid fast path (the whole grid: the structure it exploits has no stride).
    grid = twoscale.model.merl_grid("lower")
    f_grid = jax.jit(lambda pp, g: twoscale.brdf_grid(pp, g, twoscale.ModelConfig()))
    t_grid = common.timed(lambda: f_grid(params, grid), sizes.repeats)
    ev = t_grid["median"]
    merl_ratio = ev / ggx
    row(
        "`twoscale.brdf_merl` (grid path: per-bin factors, G per cell), float64, tables, full model",
        t_grid,
        target=f"{_target('merl_ratio', merl_ratio)} (≤ 1× JAX GGX)",
    )
    ev_dirs = {}
    for dtype, name in ((jnp.float64, "float64"), (jnp.float32, "float32")):
        t_eval = _eval_time(params, wi, wo, twoscale.ModelConfig(), sizes.repeats, dtype)
        ref = refs[dtype]["median"] * scale
        ev_dirs[name] = t_eval["median"] * scale
        ratio = ev_dirs[name] / ref
        row(
            f"`twoscale.brdf` at the same 1,458,000 direction pairs (any directions), {name}, "
            "tables, full model",
            t_eval,
            scale,
            ref=ref,
            target=f"{_target('dirs_ratio', ratio)} (≤ 3× JAX GGX, {name})",
        )
    t_np = common.timed(lambda: nm.brdf(params.to_dict(), wi, wo), max(1, sizes.repeats // 2))
    row("NumPy reference model (`benchmarks/numpy_model.py`), float64", t_np, scale, compile_=0.0)
    mts, note = (None, "skipped (smoke)") if not sizes.mitsuba else _mitsuba_subprocess(sizes)
    if mts is not None:
        ref32 = refs[jnp.float32]["median"] * scale
        for dist, t in mts["timings"].items():
            med = t["median"] * scale
            row(
                f"Mitsuba 3 `roughconductor` {dist} `bsdf.eval`, llvm_ad_rgb ({note})",
                t,
                scale,
                ref=ref32,
                target=f"twoscale float32 / Mitsuba = {ev_dirs['float32'] / med:.1f}× "
                "(ratio column: to JAX GGX float32)",
            )
    else:
        rows.append(["Mitsuba 3 `roughconductor`", "—", "—", "—", "—", "—", "skipped: " + note])
    t_jac, info = _jacobian_time(sizes.repeats, sizes.grid_stride)
    jac = row(
        f"Full Jacobian: normal equations JᵀJ, Jᵀr over {info['cells'] * sizes.grid_stride:,} cells "
        f"({info['residuals'] * sizes.grid_stride:,} residuals of the fit's default metric "
        f"`{info['metric']}`, {info['params']} params, "
        f"{info['seeds']} compressed JVP seeds, reciprocal pairs)",
        t_jac,
        sizes.grid_stride,
        compile_=t_jac["compile"],
    )
    rows[-1][-1] = f"{_target('jacobian', jac)} (≤ 0.3 s)"
    # The passes the default CLI's fits run: the MERL protocol's configurations (apparatus
    # factor L(θ_d)² with its knee; the plastic's Lambertian body, the conductor's floor).
    for name, cfg in _protocol_configs().items():
        t_p, info_p = _jacobian_time(sizes.repeats, sizes.grid_stride, cfg)
        row(
            f"Same normal equations, the MERL protocol's {name} (what the default CLI fits: "
            f"{info_p['params']} params, {info_p['seeds']} seeds)",
            t_p,
            sizes.grid_stride,
            compile_=t_p["compile"],
        )
    if sizes.fits:
        for sched, key in ((sizes.fit_schedule, "fit"), (sizes.preview_schedule, "preview")):
            r = common.run_worker(["--schedule", sched, "--repeats", str(sizes.fit_repeats)])
            goal = "≤ 60 s" if key == "fit" else "≤ 10 s"
            rss_ok = _target("rss", r["peak_rss_bytes"])
            row(
                f"{'Full fit (default schedule and starts)' if key == 'fit' else 'Preview fit'}: "
                f"{r['n_fit']:,} cells, synthetic conductor, rmse_log {r['rmse_log']:.3g}",
                {
                    "median": r["median"],
                    "runs": r["runs"][1:] or r["runs"],
                    "compile": r["compile"],
                },
                rss=f"{r['peak_rss_bytes'] / 1e9:.2f} GB",
                target=f"{_target(key, r['median'])} ({goal}); memory {rss_ok} (≤ 4 GB)",
            )
            verdicts.append(f"{key}: {fmt_time(r['median'])} {_target(key, r['median'])}")
    else:
        rows.append(["Fits", "—", "—", "—", "—", "—", "skipped (smoke)"])
    cmp_ = _scipy_vs_twoscale(sizes)
    ratio = cmp_["scipy"] / cmp_["twoscale"]
    row(
        f"Fit of {cmp_['cells']:,} cells from one start ({cmp_['start']}): twoscale.fit, one stage "
        f"({cmp_['twoscale_steps']} LM steps, rmse_log {cmp_['twoscale_rmse']:.3g})",
        {"median": cmp_["twoscale"], "runs": cmp_["twoscale_runs"], "compile": 0.0},
        compile_=max(cmp_["twoscale_first"] - cmp_["twoscale"], 0),
    )
    row(
        f"Same cells and start: SciPy `least_squares` (TRF, bounds, 2-point FD Jacobian, NumPy model; "
        f"{cmp_['scipy_nfev']} evals + {cmp_['scipy_njev']} Jacobians, max_nfev {sizes.scipy_max_nfev}; "
        f"rmse_log {cmp_['scipy_rmse']:.3g})",
        {"median": cmp_["scipy"], "runs": [cmp_["scipy"]], "compile": 0.0},
        target=f"SciPy / twoscale = {ratio:.1f}× {_target('scipy_ratio', ratio, lower_is_better=False)} (≥ 10×)",
    )
    verdicts = [
        f"brdf_merl {merl_ratio:.2f}× JAX GGX {_target('merl_ratio', merl_ratio)}",
        *(
            f"brdf {k} {v / (refs[jnp.float64 if k == 'float64' else jnp.float32]['median'] * scale):.2f}× "
            f"JAX GGX {_target('dirs_ratio', v / (refs[jnp.float64 if k == 'float64' else jnp.float32]['median'] * scale))}"
            for k, v in ev_dirs.items()
        ),
        f"jacobian {fmt_time(jac)} {_target('jacobian', jac)}",
        *verdicts,
        f"scipy ratio {ratio:.1f}× {_target('scipy_ratio', ratio, False)}",
    ]
    scaled = (
        f" Evaluation timed on every {sizes.grid_stride}-th cell, scaled ×{scale:.0f} to the full grid."
        if sizes.grid_stride > 1
        else ""
    )
    body = (
        f"## Speed{label}\n\nFull MERL grid: 90×90×180 = 1,458,000 direction pairs × 3 channels, "
        f"full model (conductor, specular + diffraction), float64, `tables` path.{scaled}\n\n"
        + table(
            [
                "what",
                "time (median, warm)",
                "spread (min–max, runs)",
                "÷ JAX GGX (same run)",
                "compile",
                "peak RSS",
                "target / ratio",
            ],
            rows,
        )
        + "\n"
    )
    return body, verdicts


# ------------------------------------------------------------------------------------- trade
def _errors(v, ref):
    ok = ref > 0
    rel = np.abs(v - ref)[ok] / ref[ok]
    return float(np.max(rel)), float(np.median(rel))


def _pareto(rows, t_idx, e_idx):
    """Mark rows not dominated in (time, error)."""
    pts = [(r[t_idx], r[e_idx]) for r in rows]
    out = []
    for i, (t, e) in enumerate(pts):
        dom = any(
            (t2 <= t and e2 <= e) and (t2 < t or e2 < e) for j, (t2, e2) in enumerate(pts) if j != i
        )
        out.append(not dom)
    return out


def trade(sizes: Sizes) -> str:
    import jax.numpy as jnp

    import twoscale
    from benchmarks.variants import harmonics_available, table_variant

    params = _params()
    wi, wo = _grid(sizes.grid_stride)
    scale = N_GRID / wi.shape[0]
    ri, ro = _reference_cells(sizes.ref_cells)
    base = twoscale.ModelConfig()
    exact = twoscale.ModelConfig(path="exact")
    t_ref = _eval_time(params, ri, ro, exact, max(1, sizes.repeats // 3))
    ref = np.asarray(t_ref["out"])
    records = []  # [label, time, compile, max, median, note, grid time]

    def add(label, cfg, order=3, stride=1, dtype=None, note=""):
        with table_variant(order, stride):
            t = _eval_time(params, wi, wo, cfg, sizes.repeats, dtype)
            tg = _grid_time(params, cfg, sizes.repeats, dtype)
            v = np.asarray(
                twoscale.brdf(
                    params.astype(dtype or jnp.float64),
                    ri.astype(np.float32) if dtype == jnp.float32 else ri,
                    ro.astype(np.float32) if dtype == jnp.float32 else ro,
                    cfg,
                ),
                dtype=np.float64,
            )
        mx, md = _errors(v, ref)
        records.append([label, t["median"] * scale, t["compile"], mx, md, note, tg["median"]])

    add("tables, cubic B-spline, float64 (default)", base)
    records.append(
        [
            "exact (quadrature), float64",
            t_ref["median"] * N_GRID / ri.shape[0],
            t_ref["compile"],
            0.0,
            0.0,
            f"timed on the {ri.shape[0]:,}-cell reference subsample, scaled to the full grid; it *is* "
            "the reference. Grid path not run: the exact Smith quadrature keeps 768 nodes per "
            "direction, ≈ 9 GB per temporary array for the whole grid",
            None,
        ]
    )
    add("tables, multilinear (order 1), float64", base, order=1)
    add("tables, cubic, every 2nd node, float64", base, stride=2)
    add("tables, multilinear, every 2nd node, float64", base, order=1, stride=2)
    add("tables, cubic, float32", base, dtype=jnp.float32)
    pareto = _pareto(records, 1, 4)
    rows = [
        [
            ("**" + r[0] + "** ⟵ Pareto" if p else r[0]),
            fmt_time(r[1]),
            "—" if r[6] is None else fmt_time(r[6]),
            fmt_time(r[2]),
            fmt(r[3]),
            fmt(r[4]),
            r[5],
        ]
        for r, p in zip(records, pareto, strict=True)
    ]
    text = (
        "## Accuracy against the exact path\n\n"
        f'Reference: `path="exact"`, float64, on a fixed random subsample of {ri.shape[0]:,} '
        "above-horizon MERL cells (seed 0). Errors: relative, over cells × channels where the "
        "reference is > 0. Time: one full-grid evaluation (1,458,000 pairs × 3 channels), by "
        "`brdf` at the 1,458,000 direction pairs (any directions) and by the grid path "
        "`brdf_grid` (the same values, to 1e-9 in float64: `tests/test_grid.py`; the errors are those of `brdf`). Pareto front in (`brdf` time, "
        "median error) marked.\n\n"
        + table(
            [
                "variant",
                "time / full grid (`brdf`)",
                "grid path (`brdf_grid`)",
                "compile (`brdf`)",
                "max rel. err",
                "median rel. err",
                "note",
            ],
            rows,
        )
        + "\n"
    )

    # Spectral sampling: against 30 samples (tables path, float64; spectral → sRGB).
    spec_rows = []
    cfgs = {
        n: twoscale.ModelConfig(wavelengths=tuple(twoscale.spectral.spectral_wavelengths(n)))
        for n in (10, 30)
    }
    ref30 = np.asarray(twoscale.brdf(params, ri, ro, cfgs[30]))
    for label, cfg in (
        ("RGB (3 wavelengths)", base),
        ("10 spectral samples → sRGB", cfgs[10]),
        ("30 spectral samples → sRGB", cfgs[30]),
    ):
        t = _eval_time(params, wi, wo, cfg, sizes.repeats)
        tg = _grid_time(params, cfg, sizes.repeats)
        v = np.asarray(twoscale.brdf(params, ri, ro, cfg))
        mx, md = _errors(v, ref30)
        spec_rows.append(
            [
                label,
                fmt_time(t["median"] * scale),
                fmt_time(tg["median"]),
                fmt_time(t["compile"]),
                fmt(mx),
                fmt(md),
            ]
        )
    text += (
        "\n## Wavelength sampling\n\nSame parameters (η, k given at the RGB wavelengths are "
        "upsampled, `spectral.upsample_rgb`); errors against the 30-sample spectral model "
        "(tables, float64), i.e. what RGB rendering changes, not an approximation error.\n\n"
        + table(
            [
                "wavelengths",
                "time / full grid (`brdf`)",
                "grid path",
                "compile (`brdf`)",
                "max rel. diff",
                "median rel. diff",
            ],
            spec_rows,
        )
        + "\n"
    )

    # Harmonic band limit.
    lobe_harmonic = harmonics_available()
    if lobe_harmonic is None:
        text += "\n## Harmonic band limit\n\nSkipped: `twoscale.harmonics.lobe_harmonic` does not exist yet.\n"
    else:
        text += _harmonics(lobe_harmonic, sizes)

    # Fitted RMSE change on stand-in materials (preview schedule).
    from campaigns.nbrdf import default_npz

    if sizes.trade_fits and not default_npz().is_file():
        text += (
            "\n## Fitted RMSE (Neural-BRDF stand-ins)\n\nSkipped: the stand-ins' weights "
            f"`{default_npz()}` are absent (set `TWOSCALE_SHARED` to the shared folder).\n"
        )
    elif sizes.trade_fits:
        fit_rows = []
        for mat in sizes.materials:
            base_r = None
            for label, extra in (
                ("cubic (default)", []),
                ("multilinear", ["--order", "1"]),
                ("cubic, every 2nd node", ["--stride", "2"]),
            ):
                if label not in sizes.trade_fit_variants:
                    continue
                r = common.run_worker(
                    [
                        "--schedule",
                        sizes.preview_schedule,
                        "--repeats",
                        "1",
                        "--material",
                        mat,
                        "--config",
                        "protocol",
                        *extra,
                    ]
                )
                base_r = base_r or r
                fit_rows.append(
                    [
                        mat,
                        label,
                        r["material"],
                        fmt(r["rmse_log"], 5),
                        f"{(r['rmse_log'] / base_r['rmse_log'] - 1) * 100:+.2f} %",
                        fmt_time(r["median"]),
                    ]
                )
        text += (
            f"\n## Fitted RMSE (Neural-BRDF stand-ins, `{sizes.preview_schedule}` schedule, "
            "the MERL protocol as the CLI fits it, material type auto)\n\nRMSE of the log "
            "metric on all valid cells; change relative to "
            "the cubic float64 tables. Exact path and float32 are not fitted: the exact path is "
            "far too slow for fits, and `twoscale.fit` requires float64.\n\n"
            + table(
                ["material", "variant", "type", "rmse_log", "Δ vs cubic", "fit time (warm)"],
                fit_rows,
            )
            + "\n"
        )
    return text


def _harmonics(lobe_harmonic, sizes: Sizes) -> str:
    """Time and error of the zonal-harmonic lobe against the exact convolution, per band limit."""
    import jax.numpy as jnp

    from twoscale import convolution

    rng = np.random.default_rng(0)
    n = max(200, sizes.ref_cells // 20)
    ct = jnp.asarray(rng.uniform(0.2, 1.0, n))
    u = jnp.asarray(rng.uniform(0.05, 5.0, n))
    beta, p, c = 0.1, 1.5, 2.2
    ref = np.asarray(convolution.lobe(ct, beta, p, c, u, path="exact"))
    rows = []
    for l_max in (25, 50, 100, 200):
        f = jax.jit(lambda a, b, lm=l_max: lobe_harmonic(a, beta, p, c, b, l_max=lm))
        t = common.timed(lambda f=f: f(ct, u), sizes.repeats)
        mx, md = _errors(np.asarray(t["out"]), ref)
        rows.append(
            [
                l_max,
                fmt_time(t["median"] / n * N_GRID * 3),
                fmt_time(t["compile"]),
                fmt(mx),
                fmt(md),
            ]
        )
    return (
        f'\n## Harmonic band limit\n\n`lobe_harmonic` against `convolution.lobe(path="exact")` '
        f"on {n} random (θ_h, u) at β = 0.1, p = 1.5, c = 2.2; time scaled to 1,458,000 × 3 lobes.\n\n"
        + table(["l_max", "time / full grid", "compile", "max rel. err", "median rel. err"], rows)
        + "\n"
    )


# ------------------------------------------------------------------------------------- variants
def variants(sizes: Sizes) -> str:
    import jax.numpy as jnp

    import twoscale
    from twoscale.fit.synthetic import synthetic

    wi, wo = _grid(sizes.grid_stride)
    scale = N_GRID / wi.shape[0]
    full = twoscale.TwoScaleParams.plastic(
        beta=0.1, p=1.5, eta=1.5, rho_d=(0.4, 0.2, 0.1), sigma_s=0.01, b=1.5, c=2.2, e=0.3, m=4.0
    )
    cases = (
        ("specular only", dict(material="plastic", diffuse=False, diffraction=False)),
        ("specular + diffuse", dict(material="plastic", diffraction=False)),
        ("+ diffraction", dict(material="plastic")),
        ("+ apparatus factor", dict(material="plastic", apparatus=True)),
        (
            "+ its knee (MERL protocol)",
            dict(material="plastic", apparatus=True, apparatus_knee=True),
        ),
    )
    rows = []
    for label, kw in cases:
        cfg = twoscale.ModelConfig(**kw)
        params = full.for_config(cfg) if hasattr(full, "for_config") else full
        t = _eval_time(params, wi, wo, cfg, sizes.repeats)
        tg = _grid_time(params, cfg, sizes.repeats)
        a, b = jnp.asarray(wi[:8]), jnp.asarray(wo[:8])
        n_ops = _count_eqns(
            jax.make_jaxpr(lambda pp, x, y, cfg=cfg: twoscale.brdf(pp, x, y, cfg))(
                params, a, b
            ).jaxpr
        )
        fit_t = "—"
        last = label == cases[-1][0]
        if sizes.trade_fits and (sizes.variant_fits == "all" or last):
            data = synthetic(params, cfg, noise=0.01, seed=2)
            from twoscale.fit.schedule import Stage

            sched = (
                [Stage(n_cells=1024, keep=1, max_steps=3)]
                if sizes.preview_schedule == "tiny"
                else sizes.preview_schedule
            )
            times = []
            for _ in range(2 if sizes.variant_fits == "all" else 1):
                t0 = time.perf_counter()
                twoscale.fit(data, config=cfg, material="plastic", schedule=sched)
                times.append(time.perf_counter() - t0)
            fit_t = (
                f"{fmt_time(times[-1])} (first {fmt_time(times[0])})"
                if len(times) > 1
                else f"first run {fmt_time(times[0])}"
            )
        rows.append(
            [
                label,
                ", ".join(cfg.param_names),
                n_ops,
                fmt_time(t["median"] * scale),
                fmt_time(tg["median"]),
                fmt_time(t["compile"]),
                fit_t,
            ]
        )
    return (
        "## Only what a scene requires\n\nPlastic material; each row switches one more lobe on "
        "(`ModelConfig(diffuse=, diffraction=, apparatus=, apparatus_knee=)`). Switched-off lobes "
        "are not traced at all (static configuration): the jaxpr op count and the time show what "
        "each lobe costs. "
        f"Fit: `{sizes.preview_schedule}` schedule on a synthetic material of that variant (warm; first run in brackets).\n\n"
        + table(
            [
                "variant",
                "parameters",
                "jaxpr ops (`brdf`)",
                "eval / full grid (`brdf`)",
                "grid path (`brdf_grid`)",
                "compile (`brdf`)",
                "fit (preview)",
            ],
            rows,
        )
        + "\n"
    )


def _count_eqns(jaxpr) -> int:
    n = 0
    for e in jaxpr.eqns:
        n += 1
        for v in e.params.values():
            sub = getattr(v, "jaxpr", None)
            if sub is not None:
                n += _count_eqns(getattr(sub, "jaxpr", sub))
    return n


# ------------------------------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m benchmarks.run", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--quick", action="store_true", help="small sizes (development, smoke test)")
    ap.add_argument("--smoke", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument(
        "--out", type=Path, default=None, help="results folder (default benchmarks/results)"
    )
    ap.add_argument("--only", default="speed,trade,variants")
    ap.add_argument(
        "--device", action="store_true", help="also run the speed table on an accelerator, labelled"
    )
    args = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    sizes = SMOKE if args.smoke else QUICK if args.quick else Sizes()
    quick = args.quick or args.smoke
    only = set(args.only.split(","))
    mach = common.machine()
    platform_ = jax.devices()[0].platform
    print(f"platform: {platform_} ({mach['device']}); load {common.loadavg()}", flush=True)
    sections = {
        "speed": ("speed.md", "twoscale benchmarks: speed", lambda: speed(sizes)),
        "trade": (
            "trade.md",
            "twoscale benchmarks: speed / accuracy trade",
            lambda: (trade(sizes), []),
        ),
        "variants": (
            "variants.md",
            "twoscale benchmarks: model variants",
            lambda: (variants(sizes), []),
        ),
    }
    verdicts = []
    for key, (fname, title, fn) in sections.items():
        if key not in only:
            continue
        load0 = common.loadavg()
        t0 = time.perf_counter()
        body, v = fn()
        verdicts += v
        text = (
            common.header(
                title,
                mach,
                load0,
                common.loadavg(),
                quick,
                [f"Section wall time {time.perf_counter() - t0:.0f} s."],
            )
            + "\n"
            + body
        )
        path = common.write(fname, text, args.out)
        print(text, flush=True)
        print(f"wrote {path}", flush=True)
    if args.device:
        if platform_ == "gpu":
            load0 = common.loadavg()
            body, _ = speed(sizes, label=f" on {mach['device']}")
            text = (
                common.header(
                    f"twoscale benchmarks: speed on {mach['device']}",
                    mach,
                    load0,
                    common.loadavg(),
                    quick,
                )
                + "\n"
                + body
            )
            common.write(f"speed_{platform_}.md", text, args.out)
            print(text)
        else:
            print(
                f"--device: default device is {platform_!r}, not a GPU; the CPU speed table stands."
            )
    if verdicts:
        print("targets: " + "; ".join(verdicts))
    return 0


if __name__ == "__main__":
    sys.exit(main())

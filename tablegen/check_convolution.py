"""Accuracy of the convolution table against the exact quadrature.

``python -m tablegen.check_convolution [--n N] [--seed S]`` prints, for ``N`` random parameter sets
over the whole domain (β ∈ [1e-3, 1], p ∈ [0.2, 5], c ∈ [1.01, 5], u ∈ [0, 1000], log-uniform
in β, p, c − 1 and uniform in asinh u), the relative error of ``lobe(path="tables")`` on a
θ_h grid (0, geometric from 1e-4 to π/2, uniform; jittered away from the generator's nodes),
counted where the exact lobe exceeds 1e-3 of its peak over that grid, by region.
:func:`accuracy_rows` feeds ``python -m tablegen.report``.

``python -m tablegen.check_convolution --fits PATH ...`` checks the table where fits live
instead: for every two-scale fit record (a ``params.json`` of ``python -m twoscale.fit``, or a
folder searched for them, e.g. a campaign's ``--records``), the fit's (β, p, c) with
``u = (b/λ) cos θ_d`` at the θ_d of :data:`FIT_THETA_D_DEG` and each of its wavelengths, and
the largest error over θ_h as above (:func:`fit_errors`).
"""

from __future__ import annotations

import argparse
import math

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from twoscale.convolution import lobe  # noqa: E402
from twoscale.spectral import RGB_WAVELENGTHS  # noqa: E402

DOMAIN = "β∈[1e-3,1], p∈[0.2,5], c∈[1.01,5], u∈[0,1000]"


def random_sets(n, seed=0):
    """``n`` random ``(β, p, c, u)`` over the whole domain (NumPy arrays)."""
    rng = np.random.default_rng(seed)
    beta = np.exp(rng.uniform(math.log(1e-3), 0.0, n))
    p = np.exp(rng.uniform(math.log(0.2), math.log(5.0), n))
    c = 1.0 + np.exp(rng.uniform(math.log(0.01), math.log(4.0), n))
    u = np.sinh(rng.uniform(0.0, math.asinh(1000.0), n))
    return beta, p, c, u


def theta_grid(n_geom=50, n_lin=30, seed=1):
    """θ_h samples (jittered so that they differ from the generator's)."""
    rng = np.random.default_rng(seed)
    geo = np.geomspace(1e-4, 0.5 * np.pi, n_geom) * rng.uniform(0.9, 1.0, n_geom)
    lin = np.linspace(0.0, 0.5 * np.pi, n_lin)[1:] - rng.uniform(0, 0.02, n_lin - 1)
    return np.unique(np.concatenate([[0.0], geo, lin, [0.5 * np.pi]]))


def errors(n=200, seed=0, level=1e-3, exact_nodes=81, chunk=64):
    """Per-set max relative error where the lobe exceeds ``level`` × peak; also the inputs
    (``n`` sets of :func:`random_sets`; :func:`errors_at`)."""
    return errors_at(*random_sets(n, seed), level=level, exact_nodes=exact_nodes, chunk=chunk)


def errors_at(beta, p, c, u, level=1e-3, exact_nodes=81, chunk=64):
    """:func:`errors` at given parameter sets (1-D arrays of equal length)."""
    n = beta.size
    th = theta_grid()
    ct = np.cos(th)[None, :]
    exact, table = [], []
    for k in range(0, n, chunk):
        sl = slice(k, k + chunk)
        args = (beta[sl, None], p[sl, None], c[sl, None], u[sl, None])
        exact.append(
            np.asarray(lobe(ct, *args, path="exact", n_theta=exact_nodes, n_phi=exact_nodes))
        )
        table.append(np.asarray(lobe(ct, *args, path="tables")))
    exact, table = np.concatenate(exact), np.concatenate(table)
    mask = exact > level * exact.max(axis=1, keepdims=True)
    rel = np.abs(table / exact - 1.0)
    per_set = np.where(mask, rel, 0.0).max(axis=1)
    peak_at_normal = exact[:, 0] >= exact.max(axis=1) * (1 - 1e-12)
    return {
        "beta": beta,
        "p": p,
        "c": c,
        "u": u,
        "theta": th,
        "exact": exact,
        "table": table,
        "rel": rel,
        "mask": mask,
        "per_set": per_set,
        "peak_at_normal": peak_at_normal,
        "finite": bool(np.all(np.isfinite(table))),
    }


#: θ_d (degrees) at which :func:`fit_errors` takes a fit's ``u = (b/λ) cos θ_d``: from the
#: normal to MERL's most grazing bins, where u is smallest.
FIT_THETA_D_DEG = (0.0, 30.0, 60.0, 80.0, 89.0)


def _fit_records(paths):
    """``(name, params, wavelengths)`` of the two-scale fits with a diffraction lobe among
    ``paths`` (JSON files, or folders searched recursively for ``*.json``), each fit once."""
    import json
    from pathlib import Path

    files = []
    for p in map(Path, paths):
        files += sorted(p.rglob("*.json")) if p.is_dir() else [p]
    out, seen = [], set()
    for f in files:
        try:
            d = json.loads(f.read_text())
        except (OSError, ValueError):
            continue
        if not isinstance(d, dict) or d.get("model") != "two-scale":
            continue
        params, config = d.get("params") or {}, d.get("config") or {}
        if params.get("b") is None or not config.get("diffraction", True):
            continue
        name = (d.get("data") or {}).get("name") or str(f)
        key = (name, json.dumps(params, sort_keys=True))
        if key in seen:  # the same fit twice (a campaign keeps the CLI's copy beside its own)
            continue
        seen.add(key)
        out.append((name, params, tuple(config.get("wavelengths") or RGB_WAVELENGTHS)))
    return out


def fit_errors(paths, level=1e-3, exact_nodes=81):
    """Rows ``(name, max error, β, p, c, b)``, worst first: per fit record (:func:`_fit_records`)
    the largest relative error of the table over θ_h where the lobe exceeds ``level`` × its peak,
    over ``u = (b/λ) cos θ_d`` at :data:`FIT_THETA_D_DEG` and each of the fit's wavelengths."""
    fits = _fit_records(paths)
    sets, owner = [], []  # one (β, p, c, u) per fit, wavelength and θ_d; the fit it belongs to
    for i, (_name, pr, wavelengths) in enumerate(fits):
        for w in wavelengths:
            for a in FIT_THETA_D_DEG:
                sets.append((pr["beta"], pr["p"], pr["c"], pr["b"] / w * math.cos(math.radians(a))))
                owner.append(i)
    if not sets:
        return []
    e = errors_at(*np.asarray(sets, dtype=np.float64).T, level=level, exact_nodes=exact_nodes)
    worst = np.zeros(len(fits))
    np.maximum.at(worst, np.asarray(owner), e["per_set"])
    rows = [
        (name, float(err), float(pr["beta"]), float(pr["p"]), float(pr["c"]), float(pr["b"]))
        for (name, pr, _wl), err in zip(fits, worst, strict=True)
    ]
    return sorted(rows, key=lambda r: -r[1])


def regions(e):
    """Named boolean selections of parameter sets."""
    n = e["beta"].size
    return {
        "whole domain": np.ones(n, bool),
        "authors' box (β≤0.35, c≤3.02, u≤100)": (e["beta"] <= 0.35)
        & (e["c"] <= 3.02)
        & (e["u"] <= 100),
        "lobe peak at θ_h = 0": e["peak_at_normal"],
        "lobe peak off normal (grazing)": ~e["peak_at_normal"],
        "small β (β ≤ 0.01)": e["beta"] <= 0.01,
        "β ≤ 0.1": e["beta"] <= 0.1,
        "large β (β ≥ 0.3)": e["beta"] >= 0.3,
        "large u (u ≥ 100)": e["u"] >= 100,
        "small u (u ≤ 1)": e["u"] <= 1,
        "large p (p ≥ 2)": e["p"] >= 2,
        "small p (p ≤ 0.5)": e["p"] <= 0.5,
        "c ≤ 1.1": e["c"] <= 1.1,
    }


def region_stats(e):
    """Rows ``(region, n_sets, max, median, frac of points > 1e-2, frac of sets > 1e-2)``."""
    rows = []
    for name, sel in regions(e).items():
        pts = e["rel"][sel][e["mask"][sel]]
        if pts.size == 0:
            continue
        rows.append(
            (
                name,
                int(sel.sum()),
                float(pts.max()),
                float(np.median(pts)),
                float(np.mean(pts > 1e-2)),
                float(np.mean(e["per_set"][sel] > 1e-2)),
            )
        )
    return rows


def accuracy_rows(n_points: int = 2000, seed: int = 0) -> list[dict]:
    """Rows for ``tablegen/ACCURACY.md``; ``n_points`` random parameter sets (×~80 θ_h each)."""
    from twoscale import convolution
    from twoscale.tables import DATA_DIR, load_table

    table = load_table(convolution.TABLE_NAME)
    meta = {
        "build_seconds": table.meta.get("build_seconds"),
        "file_bytes": (DATA_DIR / f"{convolution.TABLE_NAME}.npz").stat().st_size,
    }
    e = errors(n_points, seed)
    out = []
    for name, n_sets, mx, med, frac_pts, frac_sets in region_stats(e):
        out.append(
            {
                "table": "convolution",
                "quantity": "(S*D)(θ_h) tables vs exact",
                "domain": f"{name}; {DOMAIN}" if name == "whole domain" else name,
                "n_points": int(e["mask"][regions(e)[name]].sum()),
                "max_rel_err": mx,
                "median_rel_err": med,
                "note": f"{n_sets} sets, where lobe > 1e-3 peak; "
                f"points > 1e-2: {frac_pts:.2%}, sets > 1e-2: {frac_sets:.1%}",
                **meta,
            }
        )
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=400, help="random parameter sets")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--worst", type=int, default=8, help="print the worst sets")
    ap.add_argument(
        "--fits",
        nargs="+",
        metavar="PATH",
        help="check where these fits live instead (params.json files or folders of them)",
    )
    args = ap.parse_args(argv)
    if args.fits:
        rows = fit_errors(args.fits)
        if not rows:
            ap.error("no two-scale fit with a diffraction lobe found in --fits")
        err = np.array([r[1] for r in rows])
        print(
            f"fits {len(rows)}: above 1e-2 {int((err > 1e-2).sum())}, above 3e-2 "
            f"{int((err > 3e-2).sum())}, median {np.median(err):.3g}, max {err.max():.3g}"
        )
        for name, e, beta, p, c, b in rows[: args.worst]:
            print(f"  {name:28s} {e:.3g}  β={beta:.4g} p={p:.3g} c={c:.3g} b={b:.3g}")
        return
    e = errors(args.n, args.seed)
    print(f"finite: {e['finite']}")
    head = (
        f"{'region':40s} {'sets':>5s} {'max':>9s} {'median':>9s} {'pts>1e-2':>9s} {'sets>1e-2':>9s}"
    )
    print(head)
    for name, n, mx, med, fp, fs in region_stats(e):
        print(f"{name:40s} {n:5d} {mx:9.3g} {med:9.3g} {fp:9.2%} {fs:9.1%}")
    print("worst sets:")
    for i in np.argsort(e["per_set"])[::-1][: args.worst]:
        j = np.argmax(np.where(e["mask"][i], e["rel"][i], 0.0))
        print(
            f"  {e['per_set'][i]:.3g}  β={e['beta'][i]:.4g} p={e['p'][i]:.3g} c={e['c'][i]:.3g} "
            f"u={e['u'][i]:.4g}  at θ_h={e['theta'][j]:.4g}, "
            f"lobe/peak={e['exact'][i, j] / e['exact'][i].max():.2g}"
        )


if __name__ == "__main__":
    main()

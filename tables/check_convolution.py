"""Accuracy of the compact convolution table against the exact quadrature.

``python -m tables.check_convolution`` prints :func:`accuracy_rows`: for random parameter sets
over the whole domain (β ∈ [1e-3, 1], p ∈ [0.2, 5], c ∈ [1.01, 5], u ∈ [0, 1000], log-uniform
in β, p, c − 1 and uniform in asinh u), the relative error of ``lobe(path="tables")`` on a θ_h
grid (0, geometric from 1e-4 to π/2, uniform), counted where the exact lobe exceeds 1e-3 of its
peak over that grid. Rows: the whole domain and sub-regions.
"""

from __future__ import annotations

import math

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from twoscale.convolution import lobe  # noqa: E402


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
    return np.unique(np.concatenate([[0.0], geo, lin]))


def errors(n=200, seed=0, level=1e-3, exact_nodes=81):
    """Per-set max relative error where the lobe exceeds ``level`` × peak; also the inputs."""
    beta, p, c, u = random_sets(n, seed)
    th = theta_grid()
    ct = np.cos(th)[None, :]
    args = (beta[:, None], p[:, None], c[:, None], u[:, None])
    exact = np.asarray(lobe(ct, *args, path="exact", n_theta=exact_nodes, n_phi=exact_nodes))
    table = np.asarray(lobe(ct, *args, path="tables"))
    mask = exact > level * exact.max(axis=1, keepdims=True)
    rel = np.abs(table / exact - 1.0)
    per_set = np.where(mask, rel, 0.0).max(axis=1)
    peak_at_normal = exact[:, 0] >= exact.max(axis=1) * (1 - 1e-12)
    return {
        "beta": beta,
        "p": p,
        "c": c,
        "u": u,
        "rel": rel,
        "mask": mask,
        "per_set": per_set,
        "peak_at_normal": peak_at_normal,
    }


def accuracy_rows(n=200, seed=0):
    """Rows ``(region, n_sets, max, median, fraction of points above 1e-2)`` of relative error."""
    e = errors(n, seed)
    regions = {
        "whole domain": np.ones(n, bool),
        "lobe peak at θ_h = 0": e["peak_at_normal"],
        "authors' box (β ≤ 0.35, c ≤ 3.02, u ≤ 100)": (e["beta"] <= 0.35)
        & (e["c"] <= 3.02)
        & (e["u"] <= 100),
        "β ≤ 0.1": e["beta"] <= 0.1,
        "p ≥ 0.5": e["p"] >= 0.5,
    }
    rows = []
    for name, sel in regions.items():
        pts = e["rel"][sel][e["mask"][sel]]
        rows.append(
            (
                name,
                int(sel.sum()),
                float(pts.max()),
                float(np.median(pts)),
                float(np.mean(pts > 1e-2)),
            )
        )
    return rows


def main():
    print(f"{'region':48s} {'sets':>5s} {'max':>10s} {'median':>10s} {'>1e-2':>8s}")
    for name, n, mx, med, frac in accuracy_rows():
        print(f"{name:48s} {n:5d} {mx:10.3g} {med:10.3g} {frac:8.3%}")


if __name__ == "__main__":
    main()

"""Build ``twoscale/data/smith_lambda.npz``: the table of the Smith Λ(a; p) of the EPD.

Run from the repository root: ``python -m tablegen.build_smith`` (deterministic, float64; a few
seconds on one core). What is stored and why is documented in :mod:`twoscale.shadowing`:

    T(log p, x) = log[Λ(a; p) / (a m(p))] + a^{−2p},     m(p) = Γ(3/(2p))/(π Γ(1/p)),

on a uniform grid in ``log p`` (p ∈ [0.1, 10]) and in the normalised coordinate ``x ∈ [0, 1]``
(:func:`twoscale.shadowing.table_x`: ``x = 0`` at ``a^{−2p} = 200``, ``x = 1`` at
``a · E[R] = 1e7``), each axis extended by one node beyond each end. Λ comes from the exact path
(trapezoidal quadrature, ~1e-11 relative). The grid sizes are the smallest round numbers whose
measured maximum relative error in Λ and G1 (``python -m tablegen.check_smith``) stays well under
1e-4 over the whole domain.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import jax
import numpy as np

from twoscale.tables import DATA_DIR, Axis, save_table

VERSION = 1

N_P = 81  # nodes inside log p ∈ [log 0.1, log 10]; PAD_P more each side
N_X = 201  # nodes inside ξ ∈ [XI_LO, XI_HI]; one more each side
PAD_P = 3  # the p axis is the accuracy-limiting one: its edges get more room


def _padded_axis(
    name: str, lo: float, hi: float, n_inside: int, coordinate: str, pad: int = 1
) -> Axis:
    """Uniform axis with ``n_inside`` nodes on [lo, hi] plus ``pad`` nodes beyond each end."""
    step = (hi - lo) / (n_inside - 1)
    return Axis(name, lo - pad * step, hi + pad * step, n_inside + 2 * pad, coordinate)


def axes(n_p: int = N_P, n_x: int = N_X, pad_p: int = PAD_P) -> tuple[Axis, Axis]:
    from twoscale.shadowing import P_MAX, P_MIN, XI_HI, XI_LO

    return (
        _padded_axis("log_p", math.log(P_MIN), math.log(P_MAX), n_p, "log p", pad_p),
        _padded_axis(
            "xi", XI_LO, XI_HI, n_x, "η − (s(p) − 1) softplus(2(1/2 − η))/2, η = log(a E[R])"
        ),
    )


def log_a_of_xi(xi: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Invert :func:`twoscale.shadowing.table_xi` (increasing in log a) by bisection, float64."""
    from twoscale.shadowing import table_frame, table_xi

    frame = {k: np.asarray(v) for k, v in table_frame(p).items()}
    lo = np.full(np.shape(xi), -400.0)
    hi = np.full(np.shape(xi), 400.0)
    for _ in range(90):
        mid = 0.5 * (lo + hi)
        below = np.asarray(table_xi(mid, frame)) < xi
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    return 0.5 * (lo + hi)


def t_grid(ax: tuple[Axis, Axis]) -> np.ndarray:
    """``T`` on the grid (float64), shape ``(n_p, n_x)``, with the exact path."""
    from twoscale.shadowing import _lambda_exact, table_quantity

    log_p, xi = np.meshgrid(ax[0].nodes(), ax[1].nodes(), indexing="ij")
    p = np.exp(log_p)
    log_a = log_a_of_xi(xi, p)
    lam_fn = jax.jit(_lambda_exact)
    flat_a, flat_p = np.exp(log_a).ravel(), p.ravel()
    chunk = 4096  # bounded memory: chunk × QUAD_NODES per call
    lam = np.concatenate(
        [
            np.asarray(lam_fn(flat_a[i : i + chunk], flat_p[i : i + chunk]))
            for i in range(0, flat_a.size, chunk)
        ]
    ).reshape(p.shape)
    if not np.all((lam > 0) & np.isfinite(lam)):
        raise RuntimeError("Λ underflowed or is not finite on the Smith grid")
    return np.asarray(table_quantity(lam, log_a, p))


def build(path: Path | None = None, *, n_p: int = N_P, n_x: int = N_X, pad_p: int = PAD_P) -> Path:
    """Compute and write the table; returns its path."""
    jax.config.update("jax_enable_x64", True)
    from twoscale import shadowing

    t0 = time.perf_counter()
    ax = axes(n_p, n_x, pad_p)
    values = t_grid(ax)
    seconds = time.perf_counter() - t0
    path = Path(path) if path is not None else DATA_DIR / f"{shadowing.TABLE_NAME}.npz"
    save_table(
        path,
        values,
        ax,
        name=shadowing.TABLE_NAME,
        version=VERSION,
        generator={
            "module": "tablegen.build_smith",
            "quantity": "log(Lambda / (a m(p))) + a^(-2p), m = Gamma(3/(2p))/(pi Gamma(1/p))",
            "exact_path": f"trapezoid in log(v - v0), {shadowing.QUAD_NODES} nodes",
            "domain": {
                "p": [shadowing.P_MIN, shadowing.P_MAX],
                "a^(-2p) at x=0": shadowing.V_MAX,
                "a E[R] at x=1": shadowing.A_TILDE_MAX,
            },
            "padding": "one node beyond each end of every axis",
        },
        build_seconds=round(seconds, 3),
    )
    return path


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="output .npz (default: package data)")
    ap.add_argument("--n-p", type=int, default=N_P)
    ap.add_argument("--n-x", type=int, default=N_X)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    path = build(args.out, n_p=args.n_p, n_x=args.n_x)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.3f} MB) in {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()

"""Build ``twoscale/data/renormalisation.npz``: the table of the renormalisation ratio R(s; B, c).

Run from the repository root: ``python -m tablegen.build_renorm`` (deterministic; about a second
on one core). What is stored and why is documented in :mod:`twoscale.psd`:

    q̃(log10 B, log10(c−1), x) = (1 + B⁻²) · log[R(s; B, c) / R(0; B, c)],
    x = asinh(B(1−s))/asinh(B),

computed with the exact path (48-node Gauss-Legendre quadrature of the ψ form, ~1e-14 relative)
in float64. Each axis extends one grid step beyond the physical domain (s ∈ [0, 1],
B ∈ [1e-2, 1e4], c ∈ [1.01, 10]) so that the domain's edges are interior to the spline. Beyond
s = 1 (x < 0) the table holds the analytic continuation of the same integral (R is analytic
across s = 1); beyond s = 0 (x > 1) it holds R(|s|) (R is even in s).
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

# Physical domain (docs/model.md §3.5 / the task) and grid sizes (chosen by tablegen/check_renorm.py:
# the smallest grid whose measured maximum relative error in R stays well under 1e-4).
LOG10_B = (-2.0, 4.0)
LOG10_C1 = (-2.0, math.log10(9.0))  # c − 1 ∈ [0.01, 9]
N_B = 61  # nodes inside LOG10_B (step 0.1); one more each side
N_C = 31  # nodes inside LOG10_C1; one more each side
N_X = 97  # nodes inside x ∈ [0, 1]; one more each side


def _padded_axis(name: str, lo: float, hi: float, n_inside: int, coordinate: str) -> Axis:
    """Uniform axis with ``n_inside`` nodes on [lo, hi] plus one node beyond each end."""
    step = (hi - lo) / (n_inside - 1)
    return Axis(name, lo - step, hi + step, n_inside + 2, coordinate)


def axes(n_b: int = N_B, n_c: int = N_C, n_x: int = N_X) -> tuple[Axis, Axis, Axis]:
    return (
        _padded_axis("log10_B", *LOG10_B, n_b, "log10(b/λ)"),
        _padded_axis("log10_c_minus_1", *LOG10_C1, n_c, "log10(c − 1)"),
        _padded_axis("x", 0.0, 1.0, n_x, "asinh(B(1 − sinθ))/asinh(B)"),
    )


def q_tilde_grid(ax: tuple[Axis, Axis, Axis]) -> np.ndarray:
    """``q̃`` on the grid (float64), shape ``(n_B, n_c, n_x)``."""
    from twoscale.psd import _scaled_exact, _scaled_normal

    lb, lc, x = np.meshgrid(*(a.nodes() for a in ax), indexing="ij")
    B = 10.0**lb
    c = 1.0 + 10.0**lc
    s = 1.0 - np.sinh(x * np.arcsinh(B)) / B
    s = np.abs(s)  # x > 1: the even extension R(−s) = R(s); x < 0: s > 1, analytic continuation
    scaled = jax.jit(_scaled_exact)
    flat = [v.ravel() for v in (s, B, c)]
    chunk = 16384  # bounded memory: chunk × 48 quadrature nodes per call
    rho = np.concatenate(
        [np.asarray(scaled(*(v[i : i + chunk] for v in flat))) for i in range(0, s.size, chunk)]
    ).reshape(s.shape)
    rho0 = np.asarray(jax.jit(_scaled_normal)(B, c))
    if not np.all(rho > 0):
        raise RuntimeError("non-positive R in the renormalisation grid")
    return (1.0 + B**-2) * np.log(rho / rho0)


def build(path: Path | None = None, *, n_b: int = N_B, n_c: int = N_C, n_x: int = N_X) -> Path:
    """Compute and write the table; returns its path."""
    jax.config.update("jax_enable_x64", True)
    t0 = time.perf_counter()
    ax = axes(n_b, n_c, n_x)
    values = q_tilde_grid(ax)
    seconds = time.perf_counter() - t0
    path = Path(path) if path is not None else DATA_DIR / "renormalisation.npz"
    save_table(
        path,
        values,
        ax,
        name="renormalisation",
        version=VERSION,
        generator={
            "module": "tablegen.build_renorm",
            "quantity": "(1 + B^-2) * log(R(s;B,c) / R(0;B,c))",
            "quadrature": "Gauss-Legendre in v, psi = psi_c sinh v (twoscale.psd._scaled_exact)",
            "domain": {"log10_B": LOG10_B, "log10_c_minus_1": LOG10_C1, "s": [0.0, 1.0]},
            "padding": "one node beyond each end of every axis",
        },
        build_seconds=round(seconds, 3),
    )
    return path


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=None, help="output .npz (default: package data)")
    p.add_argument("--n-b", type=int, default=N_B)
    p.add_argument("--n-c", type=int, default=N_C)
    p.add_argument("--n-x", type=int, default=N_X)
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    path = build(args.out, n_b=args.n_b, n_c=args.n_c, n_x=args.n_x)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB) in {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()

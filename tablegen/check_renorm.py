"""Accuracy of the renormalisation R(s; B, c): exact path vs SciPy, table path vs exact path.

Run from the repository root: ``python -m tablegen.check_renorm`` prints one row per check.
:func:`accuracy_rows` returns the same rows (used by the tests and the report).

The SciPy reference integrates docs/model.md §3.5 as written (radial form around the specular point,
arccos bracket), independently of the ψ form used by :mod:`twoscale.psd`, with the substitution
``r = 1 − s + s(1 − cos t)`` that removes the square-root kinks of the bracket at ``r = 1 ± s``
and break points at multiples of the PSD width ``1/B``.
"""

from __future__ import annotations

import argparse
import math
import warnings

import numpy as np
from scipy import integrate

PATHS = ("exact", "tables")
DOMAIN = {"s": (0.0, 1.0), "log10_B": (-2.0, 4.0), "log10_c_minus_1": (-2.0, math.log10(9.0))}


def reference_quad(s: float, B: float, c: float, *, epsrel: float = 1e-13) -> float:
    """R(s; B, c) by ``scipy.integrate.quad`` of docs/model.md §3.5 (float64, ~1e-12 relative)::

    R = 1 − (1 + B²(1−s)²)^{−(c−1)/2}
      + ∫_{1−s}^{1+s} [(π − arccos((1 − r² − s²)/(2rs)))/π] (c−1) B² r (1 + B²r²)^{−(c+1)/2} dr
    """
    s, B, c = float(s), float(B), float(c)
    a = 0.5 * (c - 1.0)
    lo, hi = 1.0 - s, 1.0 + s
    head = -math.expm1(-a * math.log1p((B * lo) ** 2))
    if s == 0.0:
        return head
    half = s  # r = lo + half (1 − cos t), t ∈ [0, π]

    def f(t):
        r = lo + half * (1.0 - math.cos(t))
        arg = min(1.0, max(-1.0, (1.0 - r * r - s * s) / (2.0 * r * s)))
        bracket = (math.pi - math.acos(arg)) / math.pi
        g = (c - 1.0) * B * B * r * math.exp(-(a + 1.0) * math.log1p((B * r) ** 2))
        return bracket * g * half * math.sin(t)

    points = []
    for k in (1.0, 3.0, 10.0, 30.0, 100.0, 1000.0):
        r = k / B
        if lo < r < hi:
            points.append(math.acos(1.0 - (r - lo) / half))
    with warnings.catch_warnings():
        # epsrel near machine precision: QUADPACK reports round-off it cannot beat. The result is
        # still within ~1e-12 of mpmath (30 digits) on the points we measured.
        warnings.simplefilter("ignore", integrate.IntegrationWarning)
        val, _ = integrate.quad(
            f, 0.0, math.pi, points=sorted(points) or None, epsabs=0.0, epsrel=epsrel, limit=2000
        )
    return head + val


def random_points(n: int, seed: int, *, near_one: float = 0.3) -> np.ndarray:
    """(s, B, c) rows: log-uniform B and c − 1 over the domain; s uniform, or 1 − 10^U(−8, 0)."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(*DOMAIN["s"], n)
    edge = rng.uniform(size=n) < near_one
    s[edge] = 1.0 - 10.0 ** rng.uniform(-8.0, 0.0, edge.sum())
    B = 10.0 ** rng.uniform(*DOMAIN["log10_B"], n)
    c = 1.0 + 10.0 ** rng.uniform(*DOMAIN["log10_c_minus_1"], n)
    return np.stack([s, B, c], axis=1)


def edge_points() -> np.ndarray:
    """The corners and edges of the domain, all combinations."""
    s = [0.0, 1e-6, 0.5, 1.0 - 1e-6, 1.0]
    B = [1e-2, 1.0, 1e3, 1e4]
    c = [1.01, 2.0, 5.0, 10.0]
    return np.array([(a, b, d) for a in s for b in B for d in c])


_DOMAIN_TEXT = "s∈[0,1], B∈[1e-2,1e4] log-unif, c−1∈[1e-2,9] log-unif, plus edges"


def _row(name: str, pts: np.ndarray, got: np.ndarray, want: np.ndarray, domain: str = "") -> dict:
    """One report row (the keys ``tablegen/report.py`` reads, plus the p99 and the worst point)."""
    err = np.abs(got / want - 1.0)
    k = int(np.argmax(err))
    worst = tuple(float(v) for v in pts[k])
    p99 = float(np.quantile(err, 0.99))
    return {
        "table": "renormalisation",
        "check": name,
        "quantity": name,
        "domain": domain or _DOMAIN_TEXT,
        "n": len(pts),
        "n_points": len(pts),
        "max_rel_err": float(err.max()),
        "median_rel_err": float(np.median(err)),
        "p99_rel_err": p99,
        "worst_at(s,B,c)": worst,
        "note": f"p99 {p99:.2e}; worst at (s, B, c) = ({worst[0]:.4g}, {worst[1]:.4g}, {worst[2]:.4g})",
    }


def accuracy_rows(
    n_random: int = 20000,
    n_scipy: int = 200,
    n_outside: int = 2000,
    seed: int = 0,
    *,
    n_points: int | None = None,
) -> list[dict]:
    """Measured relative errors (float64). Requires ``jax_enable_x64``; enables it.

    ``n_points`` (the argument ``tablegen/report.py`` passes) sets ``n_random`` and, scaled down,
    ``n_scipy`` and ``n_outside``.
    """
    if n_points is not None:
        n_random, n_scipy, n_outside = n_points, max(10, n_points // 10), max(100, n_points // 2)
    import jax

    jax.config.update("jax_enable_x64", True)
    from twoscale.psd import diffraction_ratio, renormalisation

    R = {p: jax.jit(lambda s, B, c, p=p: renormalisation(s, B, c, path=p)) for p in PATHS}
    D = {p: jax.jit(lambda s, B, c, p=p: diffraction_ratio(s, B, c, path=p)) for p in PATHS}

    def run(f, pts):
        return np.asarray(f(pts[:, 0], pts[:, 1], pts[:, 2]))

    rows = []
    pts = np.concatenate([random_points(n_scipy, seed + 1), edge_points()])
    ref = np.array([reference_quad(*p) for p in pts])
    rows.append(_row("R exact vs scipy quad", pts, run(R["exact"], pts), ref))

    pts = np.concatenate([random_points(n_random, seed), edge_points()])
    ex = run(R["exact"], pts)
    rows.append(_row("R tables vs exact (domain)", pts, run(R["tables"], pts), ex))
    dex = run(D["exact"], pts)
    rows.append(_row("(c-1)B²/R tables vs exact (domain)", pts, run(D["tables"], pts), dex))

    rng = np.random.default_rng(seed + 2)
    for name, lo, hi in (("B in [1e-4, 1e-2]", -4.0, -2.0), ("B in [1e4, 1e6]", 4.0, 6.0)):
        p = random_points(n_outside, seed + 3)
        p[:, 1] = 10.0 ** rng.uniform(lo, hi, len(p))
        got, want = run(R["tables"], p), run(R["exact"], p)
        dom = f"outside the table: {name} (asymptotes), s, c as above"
        rows.append(_row(f"R tables vs exact, outside table: {name}", p, got, want, dom))
    from twoscale import psd
    from twoscale.tables import DATA_DIR, load_table

    meta = load_table(psd.TABLE_NAME).meta
    for row in rows:
        if "tables" in row["quantity"]:
            row["build_seconds"] = meta.get("build_seconds")
            row["file_bytes"] = (DATA_DIR / "renormalisation.npz").stat().st_size
    return rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=20000, help="random points for tables vs exact")
    p.add_argument("--n-scipy", type=int, default=200, help="random points for exact vs scipy")
    args = p.parse_args(argv)
    for row in accuracy_rows(args.n, args.n_scipy):
        print(
            f"{row['check']:<48} n={row['n']:<6} max={row['max_rel_err']:.2e} "
            f"p99={row['p99_rel_err']:.2e} worst at {row['worst_at(s,B,c)']}"
        )


if __name__ == "__main__":
    main()

"""Accuracy of the Smith Λ(a; p): exact path vs SciPy and Beckmann, table path vs exact path.

Run from the repository root: ``python -m tablegen.check_smith`` prints one row per check;
:func:`accuracy_rows` returns the same rows (used by ``tablegen/report.py`` and the tests).

Relative error in Λ is counted where the exact ``Λ > 1e-12`` (below that Λ is exponentially small,
``G1 = 1`` to float64 and only its absolute size matters); the relative error in ``G1 = 1/(1+Λ)``
is counted everywhere.

The SciPy reference integrates the polar single integral (docs/model.md §3.3, derived in
:mod:`twoscale.shadowing`) in ρ, independently of the Gamma-variable form the exact path uses::

    Λ = (2 c_p/μ) ∫_μ^∞ exp(−ρ^{2p}) ρ (√(ρ² − μ²) − μ arccos(μ/ρ)) dρ,   μ = 1/a,  c_p = p/(πΓ(1/p)),

with ``ρ = μ e^t`` and break points at the edge of the slope distribution (``ρ^{2p} ≈ 1``).
"""

from __future__ import annotations

import argparse
import math
import warnings

import numpy as np
from scipy import integrate, special

LOG10_A = (-15.0, 8.0)  # a range of the random points (the table covers all a ≥ 0)
P_RANGE = (0.1, 10.0)


def reference_quad(a: float, p: float, *, epsrel: float = 1e-12) -> float:
    """Λ(a; p) by ``scipy.integrate.quad`` of the polar single integral (float64, ~1e-11)."""
    a, p = float(a), float(p)
    if a <= 0.0:
        return 0.0
    mu = 1.0 / a
    log_mu = math.log(mu)
    log_cp = math.log(p) - math.log(math.pi) - special.gammaln(1.0 / p)

    # ρ = μ e^t; Λ = 2 c_p μ² ∫_0^∞ exp(−ρ^{2p}) e^{2t} (√(e^{2t} − 1) − arccos(e^{−t})) dt.
    def log_g(t):
        s = math.sqrt(math.expm1(2.0 * t))
        # √(e^{2t} − 1) − arccos(e^{−t}) = s − arctan(s); series for small s (cancellation).
        bracket = s**3 / 3.0 - s**5 / 5.0 + s**7 / 7.0 if s < 1e-2 else s - math.atan(s)
        if bracket <= 0.0:  # t so small that s³ underflows
            return -math.inf
        return math.log(bracket) - math.exp(2.0 * p * (log_mu + t)) + 2.0 * t

    # The mass sits near ρ^{2p} ≈ 1/p and within a few widths 1/(2p) of it in t, or, when that
    # point lies below ρ = μ, near t = 0. QUADPACK's tolerance is absolute: the integrand is
    # normalised by its largest value on a probe grid.
    width = 1.0 / (2.0 * p)
    t_edge = max(0.0, -log_mu - math.log(p) * width)
    t_end = max(t_edge, -log_mu) + 45.0 * width + 5.0
    probe = np.concatenate([np.geomspace(1e-9, t_end, 300), np.linspace(0.0, t_end, 301)[1:]])
    shift = max(log_g(t) for t in probe)
    steps = (-8, -4, -2, -1, 0, 1, 2, 4, 8, 16)
    points = sorted({t_edge + k * width for k in steps if 0.0 < t_edge + k * width < t_end})

    def g(t):
        return math.exp(log_g(t) - shift) if t > 0 else 0.0

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", integrate.IntegrationWarning)
        val, _ = integrate.quad(
            g, 0.0, t_end, points=points or None, epsabs=0.0, epsrel=epsrel, limit=4000
        )
    return val * math.exp(math.log(2.0) + log_cp + 2.0 * log_mu + shift)


def beckmann_lambda(a) -> np.ndarray:
    """Closed form at p = 1: ``Λ = (erf μ − 1)/2 + e^{−μ²}/(2μ√π)``, ``μ = 1/a`` (a > 0)."""
    mu = 1.0 / np.asarray(a, dtype=np.float64)
    return -0.5 * special.erfc(mu) + np.exp(-mu * mu) / (2.0 * mu * math.sqrt(math.pi))


def random_points(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``(a, p)``: log-uniform a in 10^LOG10_A and p in P_RANGE."""
    rng = np.random.default_rng(seed)
    a = 10.0 ** rng.uniform(*LOG10_A, n)
    p = np.exp(rng.uniform(math.log(P_RANGE[0]), math.log(P_RANGE[1]), n))
    return a, p


def _stats(err: np.ndarray) -> tuple[float, float]:
    return (float(err.max()), float(np.median(err))) if err.size else (float("nan"),) * 2


def _row(quantity, domain, err, note="", meta=None):
    mx, med = _stats(np.asarray(err))
    row = {
        "table": "smith_lambda",
        "quantity": quantity,
        "domain": domain,
        "n_points": int(np.size(err)),
        "max_rel_err": mx,
        "median_rel_err": med,
        "note": note,
    }
    if meta is not None:
        row["build_seconds"] = meta.get("build_seconds")
        row["file_bytes"] = meta.get("file_bytes")
    return row


def accuracy_rows(n_points: int = 2000, seed: int = 0, n_scipy: int = 60) -> list[dict]:
    """Measured relative errors (float64). Enables ``jax_enable_x64``."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from twoscale import shadowing
    from twoscale.tables import DATA_DIR, load_table

    table = load_table(shadowing.TABLE_NAME)
    meta = {
        "build_seconds": table.meta.get("build_seconds"),
        "file_bytes": (DATA_DIR / f"{shadowing.TABLE_NAME}.npz").stat().st_size,
    }
    exact = jax.jit(lambda a, p: shadowing.smith_lambda_a(a, p, path="exact"))
    tables = jax.jit(lambda a, p: shadowing.smith_lambda_a(a, p, path="tables"))
    rows = []

    # Exact path vs the independent SciPy quadrature (moderate a, where quad is reliable).
    rng = np.random.default_rng(seed + 1)
    a = 10.0 ** rng.uniform(-3.0, 7.0, n_scipy)
    p = np.exp(rng.uniform(math.log(P_RANGE[0]), math.log(P_RANGE[1]), n_scipy))
    ref = np.array([reference_quad(x, y) for x, y in zip(a, p, strict=True)])
    keep = ref > 1e-12
    ex = np.asarray(exact(a[keep], p[keep]))
    rows.append(
        _row("Λ exact vs scipy quad", "a∈[1e-3,1e7], p∈[0.1,10]", np.abs(ex / ref[keep] - 1.0))
    )

    # Both paths vs the Beckmann closed form.
    a = np.geomspace(0.05, 1e7, 400)
    ref = beckmann_lambda(a)
    keep = ref > 1e-12
    for path, fn in (("exact", exact), ("tables", tables)):
        got = np.asarray(fn(a, np.ones_like(a)))
        rows.append(
            _row(
                f"Λ {path} vs Beckmann closed form",
                "p=1, a∈[0.05,1e7]",
                np.abs(got / ref - 1.0)[keep],
            )
        )

    # Table vs exact over the whole domain and the grazing-to-normal range of the brief.
    a, p = random_points(n_points, seed)
    ex = np.asarray(exact(a, p))
    tb = np.asarray(tables(a, p))
    keep = ex > 1e-12
    lam_err = np.abs(tb / np.where(keep, ex, 1.0) - 1.0)
    g1_err = np.abs((1.0 + ex) / (1.0 + tb) - 1.0)
    dom = "a∈[1e-15,1e8] log-unif, p∈[0.1,10] log-unif"
    rows.append(_row("Λ tables vs exact", dom, lam_err[keep], "where Λ > 1e-12", meta))
    rows.append(_row("G1 tables vs exact", dom, g1_err, "all points", meta))
    band = (a >= 1e-3) & (a <= 1e7)
    rows.append(
        _row(
            "Λ tables vs exact",
            "a∈[1e-3,1e7], p∈[0.1,10]",
            lam_err[keep & band],
            "where Λ > 1e-12",
            meta,
        )
    )
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20000, help="random points for tables vs exact")
    ap.add_argument("--n-scipy", type=int, default=60, help="random points for exact vs scipy")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    for row in accuracy_rows(args.n, args.seed, args.n_scipy):
        print(
            f"{row['quantity']:<34} {row['domain']:<44} n={row['n_points']:<6} "
            f"max={row['max_rel_err']:.2e} median={row['median_rel_err']:.2e} {row['note']}"
        )


if __name__ == "__main__":
    main()

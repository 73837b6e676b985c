"""Materials none of the fits have seen: mixtures of two Neural-BRDF stand-ins, through the CLI.

    python -m campaigns.mixtures [--n 12] [--seed 0] [--out campaigns/MIXTURES.md]
        [--work DIR] [--npz PATH]

The fitting issue measures the default CLI on stand-ins that are not among the 60 in
``shared/data``. This script makes such materials from the 60 without choosing them: ``--n``
pairs of distinct materials drawn with ``--seed``, each mixed as ``w A + (1 − w) B`` with ``w``
drawn uniformly in [0.3, 0.7] (the BRDF of a surface whose pixels are a fraction ``w`` of material
A and the rest of B: the mixture of two reflectance functions is one, its lobes are not any single
stand-in's), valid where both are valid. Each mixture is fitted twice through the command line,
as a user would: ``python -m twoscale.fit FILE`` (the default) and ``--baseline ggx`` (GGX +
Lambert under the same protocol). The report gives both log RMSEs (all valid cells), the
improvement, the linear RMSEs, the chosen type, convergence, warnings, exit codes and times
(end to end, warm compilation cache unless the first run fills it), and a summary computed from
the rows.

The mixtures are written under ``--work`` (a temporary folder by default), never into the
repository. Skips with a message when the Neural-BRDF weights are absent.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from campaigns import nbrdf
from campaigns.cli import run_cli

#: The mixing weight of the first material is drawn uniformly in this range.
WEIGHT_RANGE = (0.3, 0.7)


def draw_pairs(names, n: int, seed: int = 0) -> list[tuple[str, str, float]]:
    """``n`` pairs ``(a, b, w)`` of distinct materials (no pair twice, in either order) and the
    weight of ``a``, drawn with ``seed``. Raises ``ValueError`` when ``names`` has too few pairs."""
    names = sorted(names)
    n_pairs = len(names) * (len(names) - 1) // 2
    if n > n_pairs:
        raise ValueError(f"{n} pairs asked from {len(names)} materials ({n_pairs} pairs)")
    rng = np.random.default_rng(seed)
    seen, out = set(), []
    while len(out) < n:
        i, j = rng.choice(len(names), size=2, replace=False)
        key = (min(i, j), max(i, j))
        if key in seen:
            continue
        seen.add(key)
        w = float(rng.uniform(*WEIGHT_RANGE))
        out.append((names[i], names[j], round(w, 3)))
    return out


def mix(a, b, w: float, name: str | None = None):
    """``w a + (1 − w) b`` of two :class:`twoscale.merl.MerlData` on the same grid, valid where
    both are (other cells 0, written as invalid)."""
    from twoscale import merl

    if not 0.0 <= w <= 1.0:
        raise ValueError(f"mixing weight {w} outside [0, 1]")
    va, vb = np.asarray(a.values), np.asarray(b.values)
    if va.shape != vb.shape:
        raise ValueError(f"grids differ: {va.shape} and {vb.shape}")
    valid = np.asarray(a.valid) & np.asarray(b.valid)
    values = np.where(valid[..., None], w * va + (1.0 - w) * vb, 0.0)
    return merl.MerlData(values=values, valid=valid, name=name)


@dataclass
class Outcome:
    name: str
    exit_full: int
    exit_ggx: int
    log_full: float = float("nan")
    log_ggx: float = float("nan")
    lin_full: float = float("nan")
    lin_ggx: float = float("nan")
    material: str = ""
    converged: bool = False
    n_warnings: int = 0
    time_full: float = float("nan")
    time_ggx: float = float("nan")

    @property
    def improvement(self) -> float:
        """Relative improvement of the log RMSE over GGX + Lambert (positive: better)."""
        return 1.0 - self.log_full / self.log_ggx


def _run_cli(path: Path, out: Path, extra: list[str]):
    """``(exit code, wall time, FitResult or None)`` of one CLI run writing into ``out``."""
    run = run_cli(path, out, extra)
    if run.returncode != 0:
        print(f"  exit {run.returncode}: {run.stderr.strip()[-300:]}", file=sys.stderr)
    return run.returncode, run.wall, run.result


def fit_pair(path: Path, work: Path) -> Outcome:
    """The default CLI and ``--baseline ggx`` on one file (outputs under ``work/<name>/``)."""
    name = path.stem
    rc_f, t_f, full = _run_cli(path, work / name / "full", [])
    rc_g, t_g, ggx = _run_cli(path, work / name / "ggx", ["--baseline", "ggx"])
    row = Outcome(name, rc_f, rc_g, time_full=t_f, time_ggx=t_g)
    if full is not None:
        row.log_full, row.lin_full = full.rmse_log, full.rmse_linear
        row.material, row.converged = full.material, full.converged
        row.n_warnings = len(full.warnings)
    if ggx is not None:
        row.log_ggx, row.lin_ggx = ggx.rmse_log, ggx.rmse_linear
    return row


def report(rows: list[Outcome], pairs, args) -> str:
    """The Markdown report: one row per mixture and a summary computed from the rows."""
    lines = [
        "# Mixtures of two stand-ins through the default CLI",
        "",
        f"Generated by `python -m campaigns.mixtures --n {args.n} --seed {args.seed}` "
        f"({time.strftime('%Y-%m-%d')}). Each material is `w A + (1 − w) B` of two Neural-BRDF "
        "stand-ins drawn at random (see the script's docstring), fitted by `python -m "
        "twoscale.fit FILE` (default settings) and by `--baseline ggx`. Log and linear RMSE on all "
        "valid cells (the CLI's own figures); improvement = 1 − two-scale / GGX on the log RMSE; "
        "times end to end, one run at a time.",
        "",
        "| material (w of the first) | two-scale log | GGX + Lambert log | improvement | "
        "two-scale linear | GGX linear | type | converged | warnings | exit (full, GGX) | "
        "time (full, GGX) |",
        "| --- | ---: | ---: | ---: | ---: | ---: | --- | :---: | ---: | --- | --- |",
    ]
    for row, (a, b, w) in zip(rows, pairs, strict=True):
        lines.append(
            f"| {a} + {b} ({w:.2f}) | {row.log_full:.4f} | {row.log_ggx:.4f} | "
            f"{100 * row.improvement:.1f} % | {row.lin_full:.3g} | {row.lin_ggx:.3g} | "
            f"{row.material} | {'yes' if row.converged else 'no'} | {row.n_warnings} | "
            f"{row.exit_full}, {row.exit_ggx} | {row.time_full:.0f} s, {row.time_ggx:.0f} s |"
        )
    ok = [r for r in rows if r.exit_full == 0 and r.exit_ggx == 0]
    below = [r for r in ok if r.log_full < r.log_ggx]
    not_below = [r.name for r in ok if r.log_full >= r.log_ggx]
    lin_bad = [r.name for r in ok if r.lin_full > 2.0 * r.lin_ggx]
    times = [r.time_full for r in rows if r.exit_full == 0]
    lines += [
        "",
        "## Summary",
        "",
        f"- Default CLI exit 0 on {sum(r.exit_full == 0 for r in rows)} of {len(rows)}; "
        f"converged on {sum(r.converged for r in rows)}.",
        f"- Log RMSE below GGX + Lambert's on {len(below)} of {len(ok)}"
        + (f" (not on: {', '.join(not_below)})" if not_below else "")
        + (
            f"; improvement median {100 * statistics.median(r.improvement for r in ok):.1f} %, "
            f"range {100 * min(r.improvement for r in ok):.1f} % to "
            f"{100 * max(r.improvement for r in ok):.1f} %."
            if ok
            else "."
        ),
        f"- Linear RMSE above 2× GGX + Lambert's on {len(lin_bad)}"
        + (f": {', '.join(lin_bad)}." if lin_bad else "."),
    ]
    if times:
        lines.append(
            f"- Default CLI end to end: median {statistics.median(times):.0f} s, "
            f"max {max(times):.0f} s."
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=12, help="number of mixtures (default 12)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the pairs and weights")
    ap.add_argument("--out", default="campaigns/MIXTURES.md", help="Markdown report to write")
    ap.add_argument("--work", help="folder for the mixtures and fits (default: a temporary one)")
    ap.add_argument("--npz", help="Neural-BRDF weights (default: shared/data/merl_nbrdf)")
    args = ap.parse_args(argv)
    npz = Path(args.npz) if args.npz else nbrdf.default_npz()
    if not npz.exists():
        print(f"Neural-BRDF weights not found at {npz}: nothing to mix", file=sys.stderr)
        return 0
    from twoscale import merl

    weights = nbrdf.load_weights(npz)
    pairs = draw_pairs(weights, args.n, args.seed)
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="twoscale-mix-"))
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for a, b, w in pairs:
        name = f"mix-{a}-{b}"
        path = work / f"{name}.binary"
        if not path.exists():
            da, db = nbrdf.render(weights[a], a), nbrdf.render(weights[b], b)
            merl.write(path, mix(da, db, w, name))
        row = fit_pair(path, work)
        print(
            f"{name} (w={w}): two-scale {row.log_full:.4f} ({row.material}), GGX "
            f"{row.log_ggx:.4f}, exit {row.exit_full}/{row.exit_ggx}, {row.time_full:.0f} s",
            flush=True,
        )
        rows.append(row)
        Path(args.out).write_text(report(rows, pairs[: len(rows)], args), encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

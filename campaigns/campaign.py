"""Fitting campaign: every MERL ``.binary`` of a folder plus the 60 Neural-BRDF stand-ins.

    python -m campaigns.campaign [--out campaigns/RESULTS.md] [--folder DIR] [--preview] [--limit N]
        [--materials NAME ...] [--records DIR [--resume]] [--gallery DIR | --no-gallery]
        [--no-apparatus] [--apparatus-angles theta_d|theta_io]

For each material it fits, with the same driver, metric and schedule:

1. the full two-scale model (material type chosen by the better fit: conductor or plastic);
2. the specular lobe alone (EPD + diffuse, diffraction off), same material type;
3. the Cook-Torrance + Lambert baselines (GGX and Beckmann, :mod:`twoscale.baselines`);

every one with MERL's apparatus factor ``L(θ_d)²`` on the specular term (the MERL protocol's;
``--no-apparatus`` turns it off for all of them; ``--apparatus-angles theta_io`` makes it the
paper's ``L(θ_i) L(θ_o)`` for all). It writes a Markdown report: log and linear RMSE on all valid cells
and on the cells with ``θ_i, θ_o ≤ 80°``, the material type chosen against the one expected from
the material's name (:func:`expected_type`), convergence and times, and a summary computed from
these rows. The report is rewritten after every material, so a long campaign can be watched.

``--records DIR`` keeps every fit's ``params.json`` (``DIR/<material>/<model>.json``, with a
``"campaign"`` entry holding the report's row); ``--resume`` reuses those made with the same
settings, so an interrupted campaign continues where it stopped. The gallery (``--gallery DIR``,
:mod:`campaigns.gallery`) holds one small picture per material and an index, ``GALLERY.md``.

The Neural-BRDF materials are rendered to a temporary folder (never into the repository): they are
MLP approximations of the MERL data, not the measurements.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from twoscale.fit.material_type import MERL_APPARATUS_ANGLES
from twoscale.fit.residuals import DEFAULT_METRIC, METRICS
from twoscale.fit.solver import STALL_RTOL

MODELS = ("full", "specular", "ggx", "beckmann")
LABELS = {
    "full": "two-scale",
    "specular": "EPD + diffuse",
    "ggx": "GGX + Lambert",
    "beckmann": "Beckmann + Lambert",
}
BASELINES = ("ggx", "beckmann")
#: The second RMSE of the report: valid cells with θ_i, θ_o at or below this angle (degrees).
THETA_CUT = 80.0
#: Ratio of linear RMSEs (two-scale / best baseline) above which the summary names a material.
LINEAR_RATIO = 2.0

# --------------------------------------------------------------------------------------------
# Expected material type, from the material's name
# --------------------------------------------------------------------------------------------

#: Words that make a material neither clearly a metal nor a dielectric: paints (metallic flakes
#: in a dielectric binder, even "gold-metallic-paint"), alumina (a ceramic, not aluminium) and
#: hematite (an iron oxide, a semiconductor with a metallic sheen).
NEUTRAL_WORDS = ("paint", "alumina", "hematite")
#: Dielectrics the "plastic" type stands for: plastics, phenolics, acrylics, rubbers, fabrics,
#: latex, nylon, polymers (poly…, pvc, vinyl, delrin, teflon) and the white diffuse basketball.
PLASTIC_WORDS = (
    "plastic",
    "phenolic",
    "acrylic",
    "rubber",
    "neoprene",
    "fabric",
    "felt",
    "latex",
    "nylon",
    "pvc",
    "vinyl",
    "poly",
    "delrin",
    "teflon",
    "bball",
)
#: Metals (and alloys, carbides) the "conductor" type stands for.
METAL_WORDS = (
    "steel",
    "ss440",
    "silver",
    "gold",
    "brass",
    "copper",
    "nickel",
    "chrome",
    "alumin",
    "bronze",
    "tungsten",
    "titanium",
    "iron",
    "zinc",
    "platinum",
    "metal",
)
TYPES = ("conductor", "plastic", "either")


def expected_type(name: str) -> str:
    """The material type a good fit should choose for a material, from its name.

    The name is split into words at ``-``, ``_`` and spaces; a keyword matches a word that starts
    with it (``paint`` matches ``paint2``, ``alumin`` matches ``aluminium``). Rules, in order:
    a word of :data:`NEUTRAL_WORDS` gives ``"either"``; then one of :data:`PLASTIC_WORDS` gives
    ``"plastic"``; then one of :data:`METAL_WORDS` gives ``"conductor"``; anything else (woods,
    stones, ceramics, unknown names) is ``"either"``.

    >>> [expected_type(n) for n in ("chrome-steel", "gold-metallic-paint", "red-fabric2", "pvc")]
    ['conductor', 'either', 'plastic', 'plastic']
    """
    words = [w for w in name.lower().replace("_", "-").replace(" ", "-").split("-") if w]
    for keywords, kind in (
        (NEUTRAL_WORDS, "either"),
        (PLASTIC_WORDS, "plastic"),
        (METAL_WORDS, "conductor"),
    ):
        if any(w.startswith(k) for w in words for k in keywords):
            return kind
    return "either"


# --------------------------------------------------------------------------------------------
# One material
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Row:
    """One material of the report: per model (keys of :data:`MODELS`) its errors, convergence,
    time and warnings.

    Attributes:
        material: the type chosen by the full model; ``expected`` the one from the name
            (:func:`expected_type` when left empty).
        rmse_log, rmse_lin: RMSE on all valid cells; ``rmse_log_80``, ``rmse_lin_80`` on the valid
            cells with ``θ_i, θ_o ≤`` :data:`THETA_CUT` (``n_cells_80`` of them); ``rmse_slog``
            the scaled log metric's on all valid cells (docs/model.md §8); ``rmse_fit`` the
            fitted metric's on the fitted cells (what each fit minimised).
        resumed: models whose result was reused from a record (``--resume``).
        cli_exit: with ``--cli``, the exit status of ``python -m twoscale.fit`` on the file (the
            full model's time is then the CLI's end to end: read, fit, errors, pictures).
    """

    name: str
    source: str
    material: str = ""
    expected: str = ""
    rmse_log: dict = dataclasses.field(default_factory=dict)
    rmse_lin: dict = dataclasses.field(default_factory=dict)
    rmse_log_80: dict = dataclasses.field(default_factory=dict)
    rmse_slog: dict = dataclasses.field(default_factory=dict)
    rmse_lin_80: dict = dataclasses.field(default_factory=dict)
    rmse_fit: dict = dataclasses.field(default_factory=dict)
    n_cells_80: int = 0
    converged: dict = dataclasses.field(default_factory=dict)
    seconds: dict = dataclasses.field(default_factory=dict)
    warnings: dict = dataclasses.field(default_factory=dict)
    resumed: list = dataclasses.field(default_factory=list)
    error: str = ""
    cli_exit: int | None = None  # exit status of the CLI run of the full model (``--cli``)

    def __post_init__(self):
        if not self.expected:
            self.expected = expected_type(self.name)

    @property
    def complete(self) -> bool:
        """No error and a log RMSE for every model."""
        return not self.error and all(k in self.rmse_log for k in MODELS)

    @property
    def type_match(self) -> bool | None:
        """Chosen type = expected type; ``None`` where either type is acceptable (or no fit)."""
        if self.expected == "either" or not self.material:
            return None
        return self.material == self.expected


#: The apparatus factor's forms as the report writes them.
FALL_OFF_FORMS = {
    "theta_io": "`L(θ_i) L(θ_o)` (`--apparatus-angles theta_io`)",
    "theta_d": "`L(θ_d)²`",
}


def _baseline_config(
    dist: str, apparatus: bool = True, apparatus_angles: str = MERL_APPARATUS_ANGLES
):
    """``CookTorranceConfig(dist, apparatus=..., apparatus_angles=...)``; a clear error where
    the field is missing."""
    from twoscale.baselines import CookTorranceConfig

    if not apparatus:
        return CookTorranceConfig(dist)
    if "apparatus" not in {f.name for f in dataclasses.fields(CookTorranceConfig)}:
        raise RuntimeError(
            "this twoscale's CookTorranceConfig has no apparatus field: run with --no-apparatus"
        )
    return CookTorranceConfig(
        dist, apparatus=True, apparatus_knee=True, apparatus_angles=apparatus_angles
    )


def _cell_rmse(pred: np.ndarray, cells) -> dict:
    """RMSE over cells and channels of the cosine-weighted log and linear metrics (as the fit:
    :func:`twoscale.fit.evaluation.rmse`)."""
    from twoscale.fit.evaluation import rmse

    e = rmse(pred, cells)
    return {"log": e["rmse_log"], "linear": e["rmse_linear"], "n_cells": len(cells)}


def rmse_below(res, cells) -> dict:
    """``{"log", "linear", "n_cells"}`` of a result on ``cells`` (the valid cells with
    ``θ_i, θ_o ≤`` :data:`THETA_CUT`): the result's own ``rmse_80`` where it has one, else
    computed from its parameters."""
    got = getattr(res, "rmse_80", None)
    if got:
        return dict(got)
    from twoscale.fit.adapters import adapter_for, config_from_dict
    from twoscale.fit.evaluation import predict_cells

    adapter = adapter_for(config_from_dict(res.config))
    return _cell_rmse(np.asarray(predict_cells(adapter, res.params, cells)), cells)


def _angles_of(settings: dict) -> str:
    """The apparatus factor's angles of a campaign's settings (a record without them was made
    with the paper's, ``"theta_io"``)."""
    return settings.get("apparatus_angles") or "theta_io"


def _settings_key(settings: dict) -> dict:
    """The settings a record must share to be reused by ``--resume``."""
    key = {k: settings.get(k) for k in ("schedule", "metric", "apparatus", "max_theta")}
    key["apparatus_angles"] = _angles_of(settings)
    return key


def _record_entry(row: Row, key: str, settings: dict) -> dict:
    def num(x):
        return None if x is None or not math.isfinite(x) else float(x)

    return {
        "source": row.source,
        "settings": _settings_key(settings),
        "seconds": num(row.seconds.get(key)),
        "rmse_80": {
            "log": num(row.rmse_log_80.get(key)),
            "linear": num(row.rmse_lin_80.get(key)),
            "n_cells": row.n_cells_80,
        },
        "warnings": list(row.warnings.get(key, [])),
    }


def _save_record(path: Path, res, entry: dict) -> None:
    """``res``'s ``params.json`` with the campaign's row entry (``load_result`` ignores it)."""
    from twoscale.fit.record import write_text_atomic

    d = res.to_dict()
    d["campaign"] = entry
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps(d, indent=2, allow_nan=False) + "\n")


def _load_record(path: Path, settings: dict, source: str):
    """``(FitResult, campaign entry)`` of a record made with the same settings, else ``None``."""
    from twoscale.fit.record import result_from_dict

    try:
        d = json.loads(path.read_text(encoding="utf-8"))
        entry = d["campaign"]
        if entry["settings"] != _settings_key(settings) or entry.get("source") != source:
            return None
        return result_from_dict(d), entry
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _num(x) -> float:
    return math.nan if x is None else float(x)


def fit_material(
    path,
    *,
    metric: str,
    schedule: str,
    apparatus: bool = True,
    apparatus_angles: str = MERL_APPARATUS_ANGLES,
    source: str = "",
    log=print,
    records: Path | None = None,
    resume: bool = False,
    max_theta_deg: float | None = None,
    cli: bool = False,
):
    """Fit the four models to one file.

    With ``cli``, the full model is fitted as a user would: ``python -m twoscale.fit`` in a
    subprocess with the default options (the same schedule, metric, angle cut and apparatus
    switch), its ``params.json`` read back, its exit status and end-to-end time recorded.

    Returns ``(row, results, data)``: the :class:`Row`, ``{model key: FitResult}`` and the
    :class:`twoscale.merl.MerlData`. With ``records``, every result is saved as
    ``records/<material>/<key>.json``; with ``resume`` too, a record made with the same settings
    (schedule, metric, apparatus, angle cut, source) is reused instead of fitting again.
    """
    from twoscale import merl
    from twoscale.fit import fit, merl_protocol
    from twoscale.fit.cells import select_cells

    data = merl.read(path)
    row = Row(name=data.name, source=source)
    settings = {
        "schedule": schedule,
        "metric": metric,
        "apparatus": apparatus,
        "apparatus_angles": apparatus_angles,
        "max_theta": max_theta_deg,
    }
    cells_80 = select_cells(data, max_theta_deg=THETA_CUT).fit
    row.n_cells_80 = len(cells_80)
    results = {}

    def run(key, config, material=None, fresnel=None):
        record = None if records is None else records / data.name / f"{key}.json"
        old = _load_record(record, settings, source) if resume and record is not None else None
        if old is not None and material not in (None, "auto", old[0].material):
            old = None  # EPD + diffuse of another type than the full model's
        if old is not None and fresnel is None and key == "specular":
            form = getattr(config, "fresnel", "exact")
            if getattr(old[0].model_config, "fresnel", "exact") != form:
                old = None  # EPD + diffuse with another Fresnel form than the full model's
        if old is not None:
            res, entry = old
            row.seconds[key] = _num(entry.get("seconds"))
            got = entry.get("rmse_80") or {}
            rmse_80 = {"log": _num(got.get("log")), "linear": _num(got.get("linear"))}
            row.warnings[key] = list(entry.get("warnings", []))
            row.resumed.append(key)
            if cli and key == "full" and (records / data.name / "cli" / "params.json").is_file():
                row.cli_exit = 0  # the CLI writes its output only when it exits 0
        else:
            t = time.perf_counter()
            kw = {} if material is None else {"material": material}
            if fresnel is not None:
                kw["fresnel"] = fresnel
            if cli and key == "full":
                res = _fit_with_cli(path, records, data.name, row, settings, log)
            else:
                res = fit(
                    data,
                    config=config,
                    metric=metric,
                    schedule=schedule,
                    max_theta_deg=max_theta_deg,
                    **kw,
                )
            row.seconds[key] = time.perf_counter() - t
            rmse_80 = rmse_below(res, cells_80)
            row.warnings[key] = [str(w) for w in getattr(res, "warnings", None) or []]
        row.rmse_log[key] = res.rmse_log
        row.rmse_lin[key] = res.rmse_linear
        row.rmse_slog[key] = math.nan if res.rmse_log_scaled is None else res.rmse_log_scaled
        row.rmse_fit[key] = res.rmse_fit
        row.rmse_log_80[key] = rmse_80["log"]
        row.rmse_lin_80[key] = rmse_80["linear"]
        row.converged[key] = res.converged
        results[key] = res
        log(
            f"  {data.name} {LABELS[key]}: log RMSE {res.rmse_log:.4g} "
            f"(≤ {THETA_CUT:g}°: {rmse_80['log']:.4g}), linear {res.rmse_linear:.4g} "
            f"({row.seconds[key]:.0f} s{'' if res.converged else ', not converged'}"
            f"{', from the record' if key in row.resumed else ''})"
        )
        if record is not None and key not in row.resumed:
            _save_record(record, res, _record_entry(row, key, settings))
        return res

    protocol = {"apparatus": apparatus, "apparatus_angles": apparatus_angles}
    full = run("full", merl_protocol(**protocol), "auto", fresnel="auto")
    row.material = full.material
    # The special case: the full fit's configuration (protocol, material type, Fresnel form) with
    # the diffraction lobe off.
    special = merl_protocol(**protocol, diffraction=False)
    if isinstance(full.model_config, type(special)):
        special = dataclasses.replace(full.model_config, diffraction=False)
    run("specular", special, full.material)
    for key in BASELINES:
        run(key, _baseline_config(key, apparatus, apparatus_angles))
    return row, results, data


def _fit_with_cli(path, records, name: str, row: Row, settings: dict, log):
    """Run ``python -m twoscale.fit`` on ``path`` (see :func:`fit_material`); returns the result."""
    import shutil
    import tempfile

    from campaigns.cli import run_cli

    keep = records is not None
    out_parent = Path(records) / name if keep else Path(tempfile.mkdtemp(prefix="twoscale-cli-"))
    extra = ["--metric", settings["metric"]]
    if settings["schedule"] == "preview":
        extra.append("--preview")
    if not settings["apparatus"]:
        extra.append("--no-apparatus")
    extra += ["--apparatus-angles", _angles_of(settings)]
    if settings["max_theta"] is not None:
        extra += ["--max-theta", str(settings["max_theta"])]
    run = run_cli(path, out_parent / "cli", extra)
    row.cli_exit = run.returncode
    for line in run.stderr.splitlines():
        log(f"    cli: {line}")
    if run.returncode != 0:
        raise RuntimeError(f"the CLI exited {run.returncode}: {run.stderr.strip()[-300:]}")
    if not keep:
        shutil.rmtree(out_parent, ignore_errors=True)
    return run.result


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------


def _fmt(x, digits: int = 4) -> str:
    return "—" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _names(items) -> str:
    return ", ".join(items) if items else "none"


def _median(x) -> float:
    return float(np.median(x)) if len(x) else math.nan


def summary_sentences(rows: list[Row]) -> list[str]:
    """Statements computed from the rows: wins and losses of the two-scale model, type accuracy,
    convergence and time, each exception named."""
    ok = [r for r in rows if r.complete]
    failed = [r.name for r in rows if not r.complete]
    if not ok:
        return ["No material was fitted with all four models."]
    n = len(ok)
    lines = [
        f"- Materials fitted with all four models: {n} of {len(rows)}"
        + (f" (failed or incomplete: {_names(failed)})." if failed else ".")
    ]

    def compare(values, where: str, name: str = "Log RMSE") -> str:
        have = [r for r in ok if all(math.isfinite(values(r).get(k, math.nan)) for k in MODELS)]
        if not have:
            return f"- {name}, {where}: not available."
        full = np.array([values(r)["full"] for r in have])
        ggx = np.array([values(r)["ggx"] for r in have])
        best = np.array([min(values(r)[k] for k in BASELINES) for r in have])
        below_ggx = full < ggx
        below_best = full < best
        rel = (ggx - full) / ggx * 100
        not_ggx = [r.name for r, b in zip(have, below_ggx, strict=True) if not b]
        not_best = [r.name for r, b in zip(have, below_best, strict=True) if not b]
        return (
            f"- {name}, {where}: the two-scale model is below GGX + Lambert on "
            f"{int(below_ggx.sum())} of {len(have)} materials (not on: {_names(not_ggx)}) and "
            f"below the better baseline on {int(below_best.sum())} of {len(have)} (not on: "
            f"{_names(not_best)}). Relative improvement over GGX + Lambert: median "
            f"{np.median(rel):.1f} %, range {rel.min():.1f} % to {rel.max():.1f} %."
        )

    lines.append(compare(lambda r: r.rmse_log, "all valid cells"))
    lines.append(compare(lambda r: r.rmse_log_80, f"cells with θ_i, θ_o ≤ {THETA_CUT:g}°"))
    lines.append(compare(lambda r: r.rmse_slog, "all valid cells", "Scaled log RMSE"))

    def vs_special(r):
        return r.rmse_log["full"] / r.rmse_log["specular"] - 1

    def fmt(r):
        text = (
            f"{r.name} ({r.rmse_log['full']:.5g} vs {r.rmse_log['specular']:.5g}, "
            f"{100 * vs_special(r):+.2g} %"
        )
        fitted = [r.rmse_fit.get(k) for k in ("full", "specular")]
        if None not in fitted and all(math.isfinite(v) for v in fitted):
            # The fits minimise the fitted metric, not the plain log RMSE of this table.
            side = "lower" if fitted[0] < fitted[1] else "not lower"
            text += f"; on the fitted metric {fitted[0]:.6g} vs {fitted[1]:.6g}, {side}"
        return text + ")"

    # The fits stop when a round of solver steps lowers the RMS by less than STALL_RTOL: two
    # fits of the same minimum agree to about that, so smaller differences are reported apart.
    worse = [fmt(r) for r in ok if vs_special(r) > STALL_RTOL]
    level = [fmt(r) for r in ok if 0 < vs_special(r) <= STALL_RTOL]
    lines.append(
        "- Two-scale log RMSE above its own special case EPD + diffuse (all valid cells) by more "
        f"than the fits' convergence tolerance ({STALL_RTOL:g} relative): "
        + (f"on {len(worse)} material(s): {', '.join(worse)}." if worse else "on no material.")
        + (
            f" Above it by less than that (the same minimum; the diffraction lobe brings "
            f"nothing): {', '.join(level)}."
            if level
            else ""
        )
    )
    fitted = [r for r in ok if all(k in r.rmse_fit for k in ("full", "specular"))]
    if fitted:
        above = [
            f"{r.name} ({r.rmse_fit['full']:.6g} vs {r.rmse_fit['specular']:.6g})"
            for r in fitted
            if r.rmse_fit["full"] > r.rmse_fit["specular"] * (1 + STALL_RTOL)
        ]
        lines.append(
            "- On the metric the fits minimise (RMSE over the fitted cells), the two-scale model "
            f"is above its special case by more than that tolerance on {len(above)} of "
            f"{len(fitted)} materials" + (f": {', '.join(above)}." if above else ".")
        )

    ratios = []
    for r in ok:
        best = min(r.rmse_lin[k] for k in BASELINES)
        if r.rmse_lin["full"] > LINEAR_RATIO * best:
            ratios.append(f"{r.name} ({r.rmse_lin['full'] / best:.1f}×)")
    lines.append(
        f"- Two-scale linear RMSE more than {LINEAR_RATIO:g}× the better baseline's (all valid "
        "cells): " + (f"on {len(ratios)}: {', '.join(ratios)}." if ratios else "on no material.")
    )

    typed = [r for r in ok if r.type_match is not None]
    wrong = [f"{r.name} ({r.material}, expected {r.expected})" for r in typed if not r.type_match]
    either = [r.name for r in ok if r.type_match is None]
    if typed:
        lines.append(
            f"- Material type: {len(typed) - len(wrong)} of {len(typed)} materials with an "
            f"unambiguous expected type chosen correctly ({100 * (1 - len(wrong) / len(typed)):.0f} "
            f"%); wrong: {_names(wrong)}. {len(either)} material(s) accept either type."
        )
    else:
        lines.append(f"- Material type: no material with an unambiguous expected type ({n}).")

    n_conv = sum(bool(r.converged.get(k)) for r in ok for k in MODELS)
    not_conv = [
        f"{LABELS[k]}: {_names([r.name for r in ok if not r.converged.get(k)])}" for k in MODELS
    ]
    lines.append(
        f"- Convergence: {n_conv} of {4 * n} fits converged; not converged — "
        + "; ".join(not_conv)
        + "."
    )

    cli_runs = [r for r in rows if r.cli_exit is not None]
    if cli_runs:
        bad = [f"{r.name} (exit {r.cli_exit})" for r in cli_runs if r.cli_exit != 0]
        lines.append(
            f"- Default CLI (`python -m twoscale.fit FILE`): {len(cli_runs) - len(bad)} of "
            f"{len(cli_runs)} runs exited 0" + (f"; not: {_names(bad)}." if bad else ".")
        )
    times = [(r.seconds.get("full", math.nan), r.name) for r in ok]
    times = [(t, name) for t, name in times if math.isfinite(t)]
    if times:
        t_max, name_max = max(times)
        total = sum(t for r in ok for t in r.seconds.values() if math.isfinite(t))
        what = (
            "end to end through the CLI (read, fit, errors, pictures)"
            if any(r.cli_exit is not None for r in ok)
            else "of the two-scale fit"
        )
        lines.append(
            f"- Time {what}: median {_median([t for t, _ in times]):.0f} s, "
            f"max {t_max:.0f} s ({name_max}); all fits of these materials: {total:.0f} s."
        )
    parts = []
    for key in MODELS:  # per model: a campaign may rerun one model and reuse the others
        names = [r.name for r in ok if key in r.resumed]
        if names:
            which = f"all {len(ok)}" if len(names) == len(ok) else _names(names)
            parts.append(f"{LABELS[key]} on {which}")
    if parts:
        lines.append(
            f"- Reused from records (`--resume`, times from the original runs): {'; '.join(parts)}; "
            "every other fit was run anew."
        )
    if any(r.source == "Neural-BRDF" for r in ok):
        lines.append(
            "- Neural-BRDF rows are fits to MLP approximations of the MERL measurements "
            "(`campaigns/nbrdf.py`), not to the measurements."
        )
    return lines


def _metric_table(rows: list[Row], values, *, with_type: bool = False) -> list[str]:
    """One Markdown table of a metric (``values(row) -> {key: float}``), best of a row in bold,
    † after a fit that did not converge."""
    head = "| material | "
    rule = "| --- | "
    if with_type:
        head += "source | type | expected | match | "
        rule += "--- | --- | --- | :---: | "
    lines = [
        head + " | ".join(LABELS[k] for k in MODELS) + " |",
        rule + " | ".join("---:" for _ in MODELS) + " |",
    ]
    for r in rows:
        prefix = f"| {r.name} | "
        if with_type:
            match = {True: "yes", False: "**no**", None: "—"}[r.type_match]
            prefix += f"{r.source} | {r.material or '—'} | {r.expected} | {match} | "
        if r.error:
            lines.append(prefix + " | ".join("—" for _ in MODELS) + f" failed: {r.error} |")
            continue
        vals = values(r)
        finite = [vals[k] for k in MODELS if math.isfinite(vals.get(k, math.nan))]
        best = min(finite) if finite else None
        cells = []
        for k in MODELS:
            v = vals.get(k, math.nan)
            s = _fmt(v)
            if best is not None and v == best:
                s = f"**{s}**"
            if k in r.converged and not r.converged[k]:
                s += "†"
            cells.append(s)
        lines.append(prefix + " | ".join(cells) + " |")
    return lines


def _time_table(rows: list[Row]) -> list[str]:
    lines = [
        "| material | " + " | ".join(LABELS[k] for k in MODELS) + " | total |",
        "| --- | " + " | ".join("---:" for _ in MODELS) + " | ---: |",
    ]
    for r in rows:
        if r.error and not r.seconds:
            continue
        secs = [r.seconds.get(k, math.nan) for k in MODELS]
        total = sum(s for s in secs if math.isfinite(s))
        lines.append(
            f"| {r.name}{' (records)' if r.resumed else ''} | "
            + " | ".join(_fmt(s, 0) for s in secs)
            + f" | {total:.0f} |"
        )
    return lines


def _warning_lines(rows: list[Row]) -> list[str]:
    out = []
    for r in rows:
        for k in MODELS:
            for w in r.warnings.get(k, []):
                out.append(f"- {r.name}, {LABELS[k]}: {w}")
    return out


def write_report(path, rows: list[Row], settings: dict) -> Path:
    """Write the Markdown report of the campaign (tables, summary, settings, empty notes)."""
    from twoscale.fit.record import package_versions, write_text_atomic

    cut = f"θ_i, θ_o ≤ {THETA_CUT:g}°"
    apparatus = settings.get("apparatus", True)
    lines = [
        "# Fitting campaign: two-scale model vs EPD + diffuse vs Cook-Torrance baselines",
        "",
        f"Generated by `python -m campaigns.campaign` ({settings['schedule']} schedule, fitted metric "
        f"`{settings['metric']}`, MERL's apparatus factor "
        + (
            "on for every model, as " + FALL_OFF_FORMS[_angles_of(settings)]
            if apparatus
            else "off (`--no-apparatus`)"
        )
        + "). RMSE over cells and channels of the cosine-weighted log metric "
        "`log(1 + ρ_model cos θ_i) − log(1 + ρ_meas cos θ_i)` and linear metric "
        f"`(ρ_model − ρ_meas) cos θ_i`, on all valid cells and on the valid cells with {cut}, "
        "and of the scaled log metric (`log(1 + ρ cos θ_i / s_c)`, `s_c` each channel's median "
        "measured `ρ cos θ_i`: relative error on dark cells too) on all valid cells. "
        "Lower is better; the best of each row is in bold; † marks a fit whose solver stopped at "
        "its step limit (result kept). *type*: the material type the two-scale model chose "
        "(conductor or plastic); *expected*: the type expected from the material's name "
        "(`expected_type` in `campaigns/campaign.py`; either = no expectation).",
        "",
        "## Log RMSE, all valid cells",
        "",
        *_metric_table(rows, lambda r: r.rmse_log, with_type=True),
        "",
        f"## Log RMSE, {cut}",
        "",
        *_metric_table(rows, lambda r: r.rmse_log_80),
        "",
        "## Scaled log RMSE, all valid cells",
        "",
        *_metric_table(rows, lambda r: r.rmse_slog),
        "",
        "## Linear RMSE, all valid cells",
        "",
        *_metric_table(rows, lambda r: r.rmse_lin),
        "",
        f"## Linear RMSE, {cut}",
        "",
        *_metric_table(rows, lambda r: r.rmse_lin_80),
        "",
        "## Time (s)",
        "",
        *_time_table(rows),
        "",
        "## Summary",
        "",
        "Computed from the rows above (a material counts when all four models were fitted).",
        "",
        *summary_sentences(rows),
    ]
    warnings = _warning_lines(rows)
    if warnings:
        lines += ["", "## Fit warnings", "", *warnings]
    v = package_versions()
    max_theta = settings.get("max_theta")
    lines += [
        "",
        "## Settings",
        "",
        f"- schedule: {settings['schedule']}; metric: {settings['metric']}; apparatus factor: "
        f"{'on' if apparatus else 'off'}; fitted cells: "
        + (f"θ_i, θ_o ≤ {max_theta:g}°" if max_theta else "all valid")
        + f"; materials: {len(rows)}",
        f"- machine: {platform.machine()}, {platform.system()}; Python {v['python']}, "
        f"jax {v['jax']}, optimistix {v['optimistix']}",
        f"- wall time of this run: {settings.get('wall', math.nan):.0f} s",
        "",
        "## Notes",
        "",
        "Notes are added by hand after a run; rerunning the command replaces this file.",
        "",
    ]
    return write_text_atomic(path, "\n".join(lines))


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------


def _materials(
    folder, with_nbrdf: bool, tmp: Path, nbrdf_npz=None, *, names=None, limit=None, log=print
):
    """``[(name, source, path)]``: the folder's ``.binary`` files, then the Neural-BRDF stand-ins
    (only those selected by ``names`` and ``limit`` are rendered, into ``tmp``).

    Raises:
        ValueError: a name in ``names`` that neither source has.
    """
    items: list[tuple[str, str, Path | None]] = []
    if folder:
        items += [(p.stem, "MERL", p) for p in sorted(Path(folder).glob("*.binary"))]
    if with_nbrdf:
        from campaigns.nbrdf import load_weights

        items += [(name, "Neural-BRDF", None) for name in load_weights(nbrdf_npz)]
    if names:
        unknown = sorted(set(names) - {name for name, _, _ in items})
        if unknown:
            raise ValueError(f"unknown material(s): {', '.join(unknown)}")
        items = [it for it in items if it[0] in set(names)]
    if limit is not None:
        items = items[:limit]
    render = [name for name, source, path in items if path is None]
    if render:
        from campaigns.nbrdf import render_all

        log(f"rendering {len(render)} Neural-BRDF stand-in(s) to a temporary folder")
        paths = {p.stem: p for p in render_all(tmp, materials=render, npz_path=nbrdf_npz)}
        items = [(name, source, path or paths[name]) for name, source, path in items]
    return items


def main(argv=None) -> int:
    from twoscale._hugepages import avoid_hugepage_stalls

    avoid_hugepage_stalls()  # as the CLI (twoscale/_hugepages.py)
    from twoscale.config import APPARATUS_ANGLES

    ap = argparse.ArgumentParser(
        prog="python -m campaigns.campaign", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--out", default="campaigns/RESULTS.md", help="Markdown report to write")
    ap.add_argument("--folder", help="folder of MERL .binary files")
    ap.add_argument("--no-nbrdf", action="store_true", help="skip the Neural-BRDF stand-ins")
    ap.add_argument("--nbrdf-npz", help="Neural-BRDF weights (default: shared/data/merl_nbrdf)")
    ap.add_argument("--materials", nargs="+", metavar="NAME", help="fit only these materials")
    ap.add_argument("--limit", type=int, help="fit only the first N materials")
    ap.add_argument("--preview", action="store_true", help="preview schedule (faster)")
    ap.add_argument("--metric", choices=METRICS, default=DEFAULT_METRIC)
    ap.add_argument(
        "--max-theta",
        type=float,
        help="fit only cells with θ_i, θ_o ≤ this angle (degrees); RMSE still on all valid cells",
    )
    ap.add_argument(
        "--no-apparatus",
        action="store_true",
        help="fit every model without MERL's apparatus factor (default: on for every model)",
    )
    ap.add_argument(
        "--apparatus-angles",
        choices=APPARATUS_ANGLES,
        default=MERL_APPARATUS_ANGLES,
        help="the apparatus factor's angles for every model: L(θ_d)² (default, the MERL "
        "protocol's) or L(θ_i) L(θ_o)",
    )
    ap.add_argument(
        "--cli",
        action="store_true",
        help="fit the full model through `python -m twoscale.fit` (exit status, end-to-end time)",
    )
    ap.add_argument("--records", help="folder to keep every fit's params.json")
    ap.add_argument(
        "--resume",
        action="store_true",
        help="reuse the fits in --records made with the same settings (continue a campaign)",
    )
    ap.add_argument(
        "--gallery", default="campaigns/gallery", help="folder of the gallery's pictures"
    )
    ap.add_argument(
        "--gallery-md", help="gallery index to write (default: GALLERY.md beside --gallery)"
    )
    ap.add_argument("--no-gallery", action="store_true", help="draw no gallery")
    args = ap.parse_args(argv)
    if args.resume and not args.records:
        ap.error("--resume needs --records DIR")
    if args.limit is not None and args.limit < 1:
        ap.error("--limit must be at least 1")
    apparatus = not args.no_apparatus
    try:
        _baseline_config("ggx", apparatus)
    except RuntimeError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2

    import jax

    jax.config.update("jax_enable_x64", True)

    def log(msg):
        print(msg, file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    schedule = "preview" if args.preview else "default"
    records = Path(args.records) if args.records else None
    gallery = None if args.no_gallery else Path(args.gallery)
    gallery_md = None
    if gallery is not None:
        gallery_md = Path(args.gallery_md) if args.gallery_md else gallery.parent / "GALLERY.md"
    settings = {
        "schedule": schedule,
        "metric": args.metric,
        "max_theta": args.max_theta,
        "apparatus": apparatus,
        "apparatus_angles": args.apparatus_angles,
    }
    rows: list[Row] = []
    pictures: dict[str, Path] = {}
    with tempfile.TemporaryDirectory(prefix="twoscale-nbrdf-") as tmp:
        try:
            items = _materials(
                args.folder,
                not args.no_nbrdf,
                Path(tmp),
                args.nbrdf_npz,
                names=args.materials,
                limit=args.limit,
                log=log,
            )
        except (OSError, ValueError) as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        if not items:
            print("error: no material to fit (empty folder and --no-nbrdf)", file=sys.stderr)
            return 2
        for i, (name, source, path) in enumerate(items):
            log(f"[{i + 1}/{len(items)}] {name} ({source})")
            try:
                row, results, data = fit_material(
                    path,
                    metric=args.metric,
                    schedule=schedule,
                    apparatus=apparatus,
                    apparatus_angles=args.apparatus_angles,
                    source=source,
                    log=log,
                    records=records,
                    resume=args.resume,
                    max_theta_deg=args.max_theta,
                    cli=args.cli,
                )
            except Exception as err:  # noqa: BLE001 - one failed material must not stop the campaign
                row = Row(name=name, source=source, error=f"{type(err).__name__}: {err}")
                results, data = {}, None
                log(f"  failed: {row.error}")
            rows.append(row)
            if gallery is not None and "full" in results:
                picture = _draw_picture(gallery, row, results, data, log, records)
                if picture is not None:
                    pictures[name] = picture
            # Rewrite the report after every material: a long campaign can be watched.
            write_report(args.out, rows, {**settings, "wall": time.perf_counter() - t0})
            if gallery_md is not None:
                from campaigns.gallery import write_index

                write_index(gallery_md, rows, pictures, LABELS)
    log(f"wrote {args.out}" + (f" and {gallery_md}" if gallery_md else ""))
    log(f"total {time.perf_counter() - t0:.0f} s")
    return 0


def _draw_picture(gallery: Path, row: Row, results: dict, data, log, records=None) -> Path | None:
    """The material's gallery tile (two-scale and GGX + Lambert); kept when all four fits came
    from records and the picture is newer than every one of them (a picture drawn from older
    fits is drawn again). A drawing error is logged, not raised."""
    from campaigns.gallery import draw_tile

    path = gallery / f"{row.name}.png"
    if path.exists() and set(row.resumed) >= set(MODELS) and records is not None:
        made = [p.stat().st_mtime for p in (Path(records) / row.name).glob("*.json")]
        if made and path.stat().st_mtime >= max(made):
            return path
    shown = {LABELS[k]: results[k] for k in ("full", "ggx") if k in results}
    title = f"{row.name}: two-scale ({row.material}) log RMSE {row.rmse_log['full']:.3f}"
    if "ggx" in row.rmse_log:
        title += f"; GGX + Lambert {row.rmse_log['ggx']:.3f}"
    try:
        gallery.mkdir(parents=True, exist_ok=True)
        return draw_tile(data, shown, path, title=title)
    except Exception as err:  # noqa: BLE001 - a picture must not stop the campaign
        log(f"  gallery picture failed: {type(err).__name__}: {err}")
        return None


if __name__ == "__main__":
    sys.exit(main())

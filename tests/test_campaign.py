"""The fitting campaign's bookkeeping (``campaigns/campaign.py``, ``campaigns/gallery.py``) without fitting:
expected material types, the report and its summary, records and ``--resume``, the gallery tile."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from campaigns import campaign, gallery
from campaigns.campaign import MODELS, Row, expected_type

#: The 60 Neural-BRDF materials and the type a good fit should choose (from the campaign's brief).
EXPECTED_60 = {
    **dict.fromkeys(
        (
            "alum-bronze",
            "aluminium",
            "black-oxidized-steel",
            "chrome",
            "chrome-steel",
            "nickel",
            "tungsten-carbide",
            "two-layer-silver",
        ),
        "conductor",
    ),
    **dict.fromkeys(
        (
            "black-fabric",
            "black-phenolic",
            "gray-plastic",
            "green-acrylic",
            "green-fabric",
            "green-latex",
            "green-plastic",
            "light-brown-fabric",
            "maroon-plastic",
            "nylon",
            "pink-fabric2",
            "pink-plastic",
            "polyethylene",
            "polyurethane-foam",
            "pure-rubber",
            "pvc",
            "red-fabric",
            "red-fabric2",
            "red-specular-plastic",
            "specular-black-phenolic",
            "specular-green-phenolic",
            "specular-red-phenolic",
            "specular-violet-phenolic",
            "specular-white-phenolic",
            "specular-yellow-phenolic",
            "violet-rubber",
            "white-diffuse-bball",
            "white-fabric",
            "white-fabric2",
            "yellow-matte-plastic",
            "yellow-plastic",
        ),
        "plastic",
    ),
    **dict.fromkeys(
        (
            "aventurnine",
            "blue-metallic-paint2",
            "cherry-235",
            "color-changing-paint1",
            "dark-blue-paint",
            "dark-red-paint",
            "fruitwood-241",
            "gold-metallic-paint",
            "gold-metallic-paint2",
            "hematite",
            "ipswich-pine-221",
            "natural-209",
            "orange-paint",
            "pearl-paint",
            "pink-jasper",
            "purple-paint",
            "red-metallic-paint",
            "silicon-nitrade",
            "silver-metallic-paint2",
            "silver-paint",
            "white-marble",
        ),
        "either",
    ),
}


def test_expected_type_of_the_60():
    assert len(EXPECTED_60) == 60
    wrong = {n: expected_type(n) for n, t in EXPECTED_60.items() if expected_type(n) != t}
    assert not wrong


@pytest.mark.parametrize(
    "name, kind",
    [
        ("brass", "conductor"),
        ("steel", "conductor"),
        ("ss440", "conductor"),
        ("grease-covered-steel", "conductor"),
        ("two-layer-gold", "conductor"),
        ("Copper_Rough", "conductor"),
        ("titanium", "conductor"),
        ("red-plastic", "plastic"),
        ("blue-fabric", "plastic"),
        ("neoprene-rubber", "plastic"),
        ("pink-felt", "plastic"),
        ("delrin", "plastic"),
        ("teflon", "plastic"),
        ("gold-paint", "either"),
        ("green-metallic-paint", "either"),
        ("alumina-oxide", "either"),
        ("special-walnut-224", "either"),
        ("black-obsidian", "either"),
        ("", "either"),
    ],
)
def test_expected_type_held_out(name, kind):
    assert expected_type(name) == kind


def _row(name, full, spec, ggx, beck, *, material="conductor", lin=None, conv=None, secs=None):
    """A hand-made row: log RMSE per model (the ≤ 80° values 10 % lower), linear RMSE ``lin``."""
    log = dict(zip(MODELS, (full, spec, ggx, beck), strict=True))
    lin = dict(zip(MODELS, lin or (0.1, 0.1, 0.1, 0.1), strict=True))
    return Row(
        name=name,
        source="Neural-BRDF",
        material=material,
        rmse_log=log,
        rmse_lin=lin,
        rmse_log_80={k: 0.9 * v for k, v in log.items()},
        rmse_lin_80={k: 0.9 * v for k, v in lin.items()},
        n_cells_80=1000,
        converged=dict(zip(MODELS, conv or (True,) * 4, strict=True)),
        seconds=dict(zip(MODELS, secs or (30.0, 10.0, 5.0, 5.0), strict=True)),
    )


@pytest.fixture
def rows():
    return [
        # Conductor as expected; the two-scale model wins everywhere.
        _row("nickel", 0.20, 0.25, 0.40, 0.45, secs=(40.0, 10.0, 5.0, 5.0)),
        # Expected plastic, chose conductor; GGX + Lambert wins; full fit not converged.
        _row("gray-plastic", 0.60, 0.61, 0.50, 0.55, conv=(False, True, True, True)),
        # No expectation; full worse than EPD + diffuse; linear 3x the better baseline.
        _row(
            "white-marble",
            0.30,
            0.29,
            0.35,
            0.36,
            material="plastic",
            lin=(0.3, 0.2, 0.1, 0.2),
            secs=(90.0, 10.0, 5.0, 5.0),
        ),
        Row(name="chrome", source="Neural-BRDF", error="FitError: no finite start"),
    ]


def test_row_type_match():
    assert Row("nickel", "x", material="conductor").type_match is True
    assert Row("nylon", "x", material="conductor").type_match is False
    assert Row("hematite", "x", material="conductor").type_match is None
    assert Row("nickel", "x").type_match is None  # not fitted
    assert Row("nickel", "x", expected="plastic").expected == "plastic"


def test_summary_names_every_exception(rows):
    text = "\n".join(campaign.summary_sentences(rows))
    assert "3 of 4 (failed or incomplete: chrome)" in text
    # all valid cells and ≤ 80°: below GGX on 2 of 3, not on gray-plastic
    assert text.count("below GGX + Lambert on 2 of 3 materials (not on: gray-plastic)") == 2
    assert "below the better baseline on 2 of 3 (not on: gray-plastic)" in text
    rel = np.median([(0.40 - 0.20) / 0.40, (0.50 - 0.60) / 0.50, (0.35 - 0.30) / 0.35]) * 100
    assert f"median {rel:.1f} %" in text
    assert (
        "tolerance (0.0001 relative): on 1 material(s): white-marble (0.3 vs 0.29, +3.4 %)." in text
    )
    assert "better baseline's (all valid cells): on 1: white-marble (3.0×)" in text
    assert "1 of 2 materials with an unambiguous expected type chosen correctly (50 %)" in text
    assert "wrong: gray-plastic (conductor, expected plastic)" in text
    assert "1 material(s) accept either type" in text
    assert "11 of 12 fits converged" in text
    assert "two-scale: gray-plastic; EPD + diffuse: none" in text
    assert "median 40 s, max 90 s (white-marble)" in text
    assert "Neural-BRDF rows" in text


def test_summary_names_what_was_reused(rows):
    """``--resume``: the summary says which models came from the records, per model."""
    assert not any("Reused from records" in x for x in campaign.summary_sentences(rows))
    for r in rows[:3]:
        r.resumed = ["ggx", "beckmann"]
    rows[0].resumed.append("specular")
    text = "\n".join(campaign.summary_sentences(rows))
    assert (
        "Reused from records (`--resume`, times from the original runs): EPD + diffuse on "
        "nickel; GGX + Lambert on all 3; Beckmann + Lambert on all 3; every other fit was run "
        "anew." in text
    )


def test_summary_without_exceptions():
    text = "\n".join(campaign.summary_sentences([_row("chrome-steel", 0.1, 0.2, 0.3, 0.4)]))
    assert "below GGX + Lambert on 1 of 1 materials (not on: none)" in text
    assert "tolerance (0.0001 relative): on no material." in text
    # A difference below the solvers' stopping tolerance is listed apart, as the same minimum.
    row = _row("chrome-steel", 0.1, 0.2, 0.3, 0.4)
    row.rmse_log["specular"] = 0.1 * (1 - 2e-6)
    text = "\n".join(campaign.summary_sentences([row]))
    assert "on no material. Above it by less than that" in text and "chrome-steel (0.1 vs" in text
    assert "better baseline's (all valid cells): on no material." in text
    assert "1 of 1 materials with an unambiguous expected type chosen correctly (100 %)" in text
    assert "the metric the fits minimise" not in text  # rows without it: no sentence


def test_summary_special_case_on_the_fitted_metric():
    """Above the special case in plain log RMSE but not on the metric the fits minimise: both
    are said, and the fitted metric's comparison is counted apart."""
    low = _row("fruitwood-241", 0.0434, 0.0433, 0.0383, 0.0399)
    low.rmse_fit = {"full": 0.0900017, "specular": 0.0900031}
    high = _row("white-marble", 0.30, 0.29, 0.35, 0.36)
    high.rmse_fit = {"full": 0.25, "specular": 0.24}
    text = "\n".join(campaign.summary_sentences([low, high]))
    assert "fruitwood-241 (0.0434 vs 0.0433, +0.23 %; on the fitted metric 0.0900017 vs " in text
    assert "0.0900031, lower)" in text
    assert (
        "white-marble (0.3 vs 0.29, +3.4 %; on the fitted metric 0.25 vs 0.24, not lower)" in text
    )
    assert "above its special case by more than that tolerance on 1 of 2 materials: " in text
    assert "white-marble (0.25 vs 0.24)." in text
    assert campaign.summary_sentences([Row("x", "y", error="E")]) == [
        "No material was fitted with all four models."
    ]


def test_report(rows, tmp_path):
    rows[0].warnings["full"] = ["e at its bound"]
    rows[1].rmse_log_80 = {}  # a row without ≤ 80° values (e.g. an old record) still renders
    settings = {"schedule": "preview", "metric": "log", "apparatus": True, "wall": 12.0}
    text = campaign.write_report(tmp_path / "r.md", rows, settings).read_text(encoding="utf-8")
    for heading in (
        "## Log RMSE, all valid cells",
        "## Log RMSE, θ_i, θ_o ≤ 80°",
        "## Linear RMSE, all valid cells",
        "## Linear RMSE, θ_i, θ_o ≤ 80°",
        "## Time (s)",
        "## Summary",
        "## Fit warnings",
        "## Settings",
        "## Notes",
    ):
        assert heading in text
    assert "apparatus factor on for every model" in text
    assert "apparatus factor: on" in text
    assert "| nickel | Neural-BRDF | conductor | conductor | yes | **0.2000** |" in text
    assert "| gray-plastic | Neural-BRDF | conductor | plastic | **no** | 0.6000† |" in text
    assert "| white-marble | Neural-BRDF | plastic | either | — |" in text
    assert "| nickel | **0.1800** | 0.2250 | 0.3600 | 0.4050 |" in text  # ≤ 80°
    assert "| gray-plastic | —† | — | — | — |" in text
    assert "failed: FitError: no finite start" in text
    assert "| nickel | 40 | 10 | 5 | 5 | 60 |" in text
    assert "- nickel, two-scale: e at its bound" in text
    assert text.rstrip().endswith("rerunning the command replaces this file.")
    off = campaign.write_report(tmp_path / "o.md", rows, {**settings, "apparatus": False})
    assert "off (`--no-apparatus`)" in off.read_text(encoding="utf-8")


def test_baseline_config():
    from twoscale.baselines import CookTorranceConfig

    assert campaign._baseline_config("beckmann", False) == CookTorranceConfig("beckmann")
    if "apparatus" in {f.name for f in dataclasses.fields(CookTorranceConfig)}:
        assert campaign._baseline_config("ggx").apparatus is True
    # The MERL protocol's L(θ_d)², as the two-scale model's (merl_protocol).
    assert campaign._baseline_config("ggx").apparatus_angles == "theta_d"
    assert campaign._baseline_config("ggx", True, "theta_io").apparatus_angles == "theta_io"


def test_resume_key_has_the_apparatus_angles():
    """A record made before the switch existed was made with the paper's ``L(θ_i) L(θ_o)``:
    ``--resume`` reuses it for that form and not for ``L(θ_d)²``."""
    old = {"schedule": "default", "metric": "blend", "apparatus": True, "max_theta": None}
    assert campaign._settings_key(old) == campaign._settings_key(
        {**old, "apparatus_angles": "theta_io"}
    )
    assert campaign._settings_key(old) != campaign._settings_key(
        {**old, "apparatus_angles": "theta_d"}
    )


def test_materials_selection(tmp_path):
    for name in ("b", "a", "c"):
        (tmp_path / f"{name}.binary").write_bytes(b"")
    items = campaign._materials(tmp_path, False, tmp_path / "tmp")
    assert [n for n, _, _ in items] == ["a", "b", "c"]
    items = campaign._materials(tmp_path, False, tmp_path / "tmp", names=["c", "a"], limit=1)
    assert [(n, s) for n, s, _ in items] == [("a", "MERL")]
    with pytest.raises(ValueError, match="unknown material.*zz"):
        campaign._materials(tmp_path, False, tmp_path / "tmp", names=["a", "zz"])


def _data(value=0.1, name="x"):
    from twoscale.merl import MerlData

    shape = (90, 90, 180)
    return MerlData(values=np.full(shape + (3,), value), valid=np.ones(shape, bool), name=name)


def _result(rmse_log, material):
    """A :class:`FitResult` with Cook-Torrance parameters (stands in for any model here)."""
    from twoscale.baselines import CookTorranceParams
    from twoscale.fit.record import FitResult

    return FitResult(
        params=CookTorranceParams(0.2, 0.5, 0.3),
        model="cook-torrance-ggx",
        config={"model": "cook-torrance", "distribution": "ggx", "material": material},
        metric="log",
        rmse_linear=2 * rmse_log,
        rmse_log=rmse_log,
        per_channel={},
        rmse_fit=rmse_log,
        n_valid=10,
        n_fit=10,
        converged=True,
        status="",
        steps=3,
        wall_time=1.0,
        std_errors={},
        covariance={},
        settings={},
        versions={},
        data={},
    )


def test_records_and_resume(tmp_path, monkeypatch):
    """Fit (faked) with records, then resume: every model comes back from its record."""
    from twoscale import merl

    calls = []

    def fake_fit(data, *, config, material=None, **kwargs):
        calls.append(material)
        res = _result(0.1 + 0.01 * len(calls), "plastic")
        res.rmse_80 = {"log": 0.05, "linear": 0.07, "n_cells": 5}
        res.warnings = ["a warning"]
        return res

    monkeypatch.setattr(merl, "read", lambda path: _data(name="nylon"))
    monkeypatch.setattr("twoscale.fit.fit", fake_fit)
    kw = dict(metric="log", schedule="preview", source="MERL", log=lambda _m: None)
    rec = tmp_path / "rec"
    row, results, _ = campaign.fit_material("nylon.binary", records=rec, **kw)
    assert calls == ["auto", "plastic", None, None]
    assert sorted(p.name for p in (rec / "nylon").iterdir()) == sorted(f"{k}.json" for k in MODELS)
    assert row.material == "plastic" and row.type_match is True
    assert row.rmse_log_80["ggx"] == 0.05 and row.warnings["full"] == ["a warning"]
    assert set(results) == set(MODELS)

    def no_fit(*args, **kwargs):
        raise AssertionError("resume must not fit again")

    monkeypatch.setattr("twoscale.fit.fit", no_fit)
    again, _, _ = campaign.fit_material("nylon.binary", records=rec, resume=True, **kw)
    assert again.resumed == list(MODELS)
    for field in ("rmse_log", "rmse_lin", "rmse_log_80", "rmse_lin_80", "converged", "warnings"):
        assert getattr(again, field) == getattr(row, field), field
    assert again.seconds == pytest.approx(row.seconds)
    # Other settings (here the apparatus factor): the records are not reused.
    monkeypatch.setattr("twoscale.fit.fit", fake_fit)
    calls.clear()
    other, _, _ = campaign.fit_material(
        "nylon.binary", records=rec, resume=True, apparatus=False, **kw
    )
    assert other.resumed == [] and len(calls) == 4


def test_rmse_below_computes_from_params():
    """Without ``rmse_80`` on the result, the metrics come from the parameters: 0 on cells made
    by the model itself, the metric's definition on cells 10 % off."""
    from twoscale.baselines import CookTorranceConfig
    from twoscale.fit.adapters import adapter_for
    from twoscale.fit.cells import Cells

    res = _result(0.1, "baseline")
    adapter = adapter_for(CookTorranceConfig("ggx"))
    rng = np.random.default_rng(0)
    wi = np.column_stack([rng.uniform(-0.5, 0.5, (50, 2)), np.ones(50)])
    wo = np.column_stack([rng.uniform(-0.5, 0.5, (50, 2)), np.ones(50)])
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    pred = np.asarray(adapter.evaluate(res.params, wi, wo))
    exact = campaign.rmse_below(res, Cells(wi, wo, pred, np.arange(50)))
    assert exact["log"] < 1e-12 and exact["linear"] < 1e-12 and exact["n_cells"] == 50
    off = campaign.rmse_below(res, Cells(wi, wo, 1.1 * pred, np.arange(50)))
    cos = wi[:, 2:3]
    want = np.sqrt(np.mean((np.log1p(pred * cos) - np.log1p(1.1 * pred * cos)) ** 2))
    assert off["log"] == pytest.approx(want, rel=1e-10)
    assert off["linear"] == pytest.approx(np.sqrt(np.mean((0.1 * pred * cos) ** 2)), rel=1e-10)


def test_gallery_tile_and_index(tmp_path, rows):
    from twoscale.plots import plot_gallery_tile

    data = _data(0.1)

    def flat(wi, wo):
        return np.full(np.shape(wi)[:-1] + (3,), 0.1)

    def half(wi, wo):
        return 0.5 * flat(wi, wo)

    path = plot_gallery_tile(
        data, {"two-scale": flat, "GGX + Lambert": half}, tmp_path / "x.png", title="x"
    )
    raw = path.read_bytes()
    assert raw[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(raw) < 60_000
    only = plot_gallery_tile(data, {}, tmp_path / "none.png")  # the measured sphere alone
    assert only.stat().st_size > 0

    index = gallery.write_index(
        tmp_path / "GALLERY.md", rows, {"nickel": path}, {"full": "two-scale", "ggx": "GGX"}
    )
    text = index.read_text(encoding="utf-8")
    assert "![nickel](x.png)" in text
    assert "two-scale 0.2000 / 0.1800; GGX 0.4000 / 0.3600" in text
    assert "type conductor (expected conductor)" in text
    assert "Failed: FitError: no finite start" in text
    assert math.isfinite(rows[0].rmse_log["full"])


def test_help(capsys):
    with pytest.raises(SystemExit) as exc:
        campaign.main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for flag in ("--materials", "--resume", "--no-apparatus", "--gallery", "--no-gallery"):
        assert flag in out


def test_mixture_pairs_and_mixing():
    """``campaigns.mixtures``: the pairs are distinct, reproducible from the seed, weights in
    range; a mixture is the weighted sum where both are valid and invalid elsewhere; the report's
    summary counts what the rows say."""
    import argparse

    from campaigns import mixtures
    from twoscale import merl

    names = [f"m{i}" for i in range(6)]
    pairs = mixtures.draw_pairs(names, 15, seed=3)  # every one of the 15 pairs, once
    assert len({frozenset(p[:2]) for p in pairs}) == 15
    assert all(a != b and 0.3 <= w <= 0.7 for a, b, w in pairs)
    assert pairs == mixtures.draw_pairs(names, 15, seed=3)
    assert mixtures.draw_pairs(names, 4, seed=3) != mixtures.draw_pairs(names, 4, seed=4)
    with pytest.raises(ValueError, match="pairs"):
        mixtures.draw_pairs(names, 16)

    rng = np.random.default_rng(0)
    shape = merl.SHAPE
    va, vb = rng.random(shape + (3,)), rng.random(shape + (3,))
    ok_a, ok_b = rng.random(shape) > 0.2, rng.random(shape) > 0.2
    m = mixtures.mix(
        merl.MerlData(values=va, valid=ok_a), merl.MerlData(values=vb, valid=ok_b), 0.4
    )
    both = ok_a & ok_b
    np.testing.assert_array_equal(m.valid, both)
    np.testing.assert_allclose(m.values[both], 0.4 * va[both] + 0.6 * vb[both])
    assert np.all(m.values[~both] == 0.0)
    with pytest.raises(ValueError, match="weight"):
        mixtures.mix(merl.MerlData(values=va, valid=ok_a), merl.MerlData(values=vb, valid=ok_b), 2)

    rows = [
        mixtures.Outcome("x", 0, 0, 0.1, 0.2, 1.0, 1.5, "plastic", True, 0, 20.0, 5.0),
        mixtures.Outcome("y", 0, 0, 0.3, 0.2, 4.0, 1.5, "conductor", True, 1, 30.0, 5.0),
    ]
    text = mixtures.report(
        rows, [("a", "b", 0.5), ("c", "d", 0.4)], argparse.Namespace(n=2, seed=0)
    )
    assert "below GGX + Lambert's on 1 of 2 (not on: y)" in text
    assert "Linear RMSE above 2× GGX + Lambert's on 1: y." in text
    assert "median 0.0 %" in text  # improvements 50 % and −50 %


def test_run_cli_reports_a_refused_file(tmp_path):
    """``campaigns.cli.run_cli`` (both campaigns' CLI runs): a file the CLI refuses comes back
    with its exit status, its message and no result."""
    from campaigns.cli import run_cli

    bad = tmp_path / "short.binary"
    bad.write_bytes(b"\x00" * 12)
    run = run_cli(bad, tmp_path / "out", ["--no-plots"])
    assert run.returncode == 2, run.stderr
    assert run.result is None and run.wall > 0
    assert "not a valid MERL .binary file" in run.stderr, run.stderr

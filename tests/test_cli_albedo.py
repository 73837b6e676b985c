"""``python -m twoscale.fit`` writes the fitted material's directional-albedo table into
``params.json`` (``"albedo_table"``), and :func:`twoscale.fit.load_result` keeps it.

The fit itself is replaced by a stand-in that returns a two-scale record of the ``--example``
material (a real two-scale fit takes a minute); everything after it (the table, the record, the
files) is the CLI's own code.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

import twoscale
from tests.helpers import two_scale_record
from twoscale import merl
from twoscale.fit import load_result
from twoscale.fit.__main__ import main
from twoscale.fit.record import ALBEDO_ROWS, FitResult, result_from_dict
from twoscale.fit.synthetic import EXAMPLE

#: Fitted-record configuration of the stand-in (the MERL protocol: apparatus factor on).
CONFIG = twoscale.ModelConfig(material="conductor", apparatus=True, diffuse_fresnel=False)
PARAMS = twoscale.TwoScaleParams.conductor(**EXAMPLE)
#: Largest difference allowed between the stored table and ``twoscale.albedo_table`` (default
#: quadrature): the CLI's quadrature (n_phi = 16) measured 1.2e-6 here, at most 1.8e-5 on seven
#: test materials.
TOL = 1e-4


def _record(params=PARAMS, config=CONFIG) -> FitResult:
    return two_scale_record(params, config)


@pytest.fixture(scope="module")
def cli_out(tmp_path_factory):
    """Run the CLI once (stand-in fit, no pictures) on a small constant MERL file."""
    import twoscale.fit.driver as driver

    d = tmp_path_factory.mktemp("cli-albedo")
    path = d / "grey.binary"
    merl.write(path, np.full(merl.SHAPE + (3,), 0.05), np.ones(merl.SHAPE, bool))
    calls = []

    def stand_in(data, **kwargs):
        calls.append(kwargs)
        return _record()

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(driver, "fit", stand_in)
        rc = main([str(path), "--out", str(d / "out"), "--no-plots", "--quiet"])
        rc_off = main([str(path), "--out", str(d / "off"), "--no-plots", "--quiet", "--no-albedo"])
    assert len(calls) == 2
    return {"rc": rc, "rc_off": rc_off, "out": d / "out", "off": d / "off"}


def test_table_written_with_its_layout(cli_out):
    assert cli_out["rc"] == 0
    raw = json.loads((cli_out["out"] / "params.json").read_text())
    tab = raw["albedo_table"]
    assert tab["n"] == ALBEDO_ROWS == 256
    assert tab["cos_theta_i"] == "(i+1)/n"
    assert tab["apparatus"] is False
    assert tab["channels"] == ["R", "G", "B"]
    values = np.asarray(tab["values"], dtype=np.float64)
    assert values.shape == (256, 3)
    assert np.all(np.isfinite(values))
    assert values.min() >= 0.0 and values.max() <= 1.05, (values.min(), values.max())
    # Row order: the gold-like conductor is coloured at normal incidence (the last row) and
    # whitens towards grazing incidence (row 0), where its Fresnel reflectance tends to 1.
    spread = np.ptp(values, axis=1)
    assert spread[-1] > 0.4 and spread[0] < 0.5 * spread[-1], spread[[0, -1]]


def test_table_matches_twoscale_albedo_table(cli_out):
    """The stored table is twoscale.albedo_table of the fitted parameters with the apparatus
    factor off (the material), to ``TOL``. (With the factor on, the record's e = 0.8 darkens the
    grazing rows by far more than ``TOL``.)"""
    values = load_result(cli_out["out"] / "params.json").albedo_values()
    material = dataclasses.replace(CONFIG, apparatus=False)
    ref = np.asarray(twoscale.albedo_table(PARAMS.for_config(material), 256, material))
    err = np.max(np.abs(values - ref))
    assert err <= TOL, err


def test_round_trip_and_records_without_a_table(cli_out, tmp_path):
    path = cli_out["out"] / "params.json"
    raw = json.loads(path.read_text())
    res = load_result(path)
    assert res.albedo_table == raw["albedo_table"]
    again = result_from_dict(json.loads(res.to_json()))
    assert again.to_dict() == res.to_dict()
    np.testing.assert_array_equal(again.albedo_values(), res.albedo_values())
    # A record without the entry (older records, --no-albedo, baselines) still loads.
    del raw["albedo_table"]
    old = tmp_path / "old.json"
    old.write_text(json.dumps(raw))
    res_old = load_result(old)
    assert res_old.albedo_table is None and res_old.albedo_values() is None
    assert "albedo_table" not in res_old.to_dict()
    assert res_old.params.to_dict() == res.params.to_dict()


def test_no_albedo_flag(cli_out):
    assert cli_out["rc_off"] == 0
    raw = json.loads((cli_out["off"] / "params.json").read_text())
    assert "albedo_table" not in raw
    assert load_result(cli_out["off"] / "params.json").albedo_table is None


def test_table_through_the_pictures_evaluation():
    """The CLI computes the table through the lobe evaluation its pictures compile, with the
    apparatus exponent set to 0 (the factor is then 1 above the horizon): the same table as
    :func:`twoscale.albedo`'s own quadrature at the same nodes, to rounding."""
    from twoscale.fit.adapters import adapter_for
    from twoscale.fit.evaluation import material_evaluator
    from twoscale.fit.record import albedo_table_entry

    assert CONFIG.apparatus and float(PARAMS.e) != 0.0
    for params, config in [
        (PARAMS, CONFIG),
        (
            twoscale.TwoScaleParams.plastic(
                0.05, 0.8, (1.5, 1.5, 1.5), (0.2, 0.3, 0.4), 0.01, 2.0, 1.8, e=0.7
            ),
            dataclasses.replace(CONFIG, material="plastic", diffuse_fresnel=True),
        ),
    ]:
        ref = albedo_table_entry(params, config, n=32)
        got = albedo_table_entry(
            params, config, n=32, evaluate_lobes=material_evaluator(adapter_for(config), params)
        )
        assert got["channels"] == ref["channels"] and got["quadrature"] == ref["quadrature"]
        np.testing.assert_allclose(got["values"], ref["values"], rtol=1e-12, atol=0)
        assert np.all(np.asarray(got["values"]) > 0.01)
        # The lobes apart (what the CLI passes): the table's last row by lobe.
        at_normal = got["lobes_at_normal"]
        assert at_normal["cos_theta_i"] == 1.0
        parts = np.asarray([at_normal[n] for n in ("specular", "diffraction", "diffuse")])
        np.testing.assert_allclose(parts.sum(axis=0), got["values"][-1], rtol=1e-12)
        assert np.all(parts[:2] > 0.0)  # both lobes of these materials carry light
        assert "lobes_at_normal" not in ref


@pytest.mark.parametrize("sigma_s, faint", [(EXAMPLE["sigma_s"], False), (1e-4, True)])
def test_summary_gives_the_light_per_lobe(sigma_s, faint):
    """The summary prints each lobe's albedo at normal incidence and says when the diffraction
    lobe is too faint for its b and c to mean anything (σ_s → 0: a fit of gold-metallic-paint
    printed c = 1.03 ± 6.5 without a word on why)."""
    from twoscale.fit.adapters import adapter_for
    from twoscale.fit.evaluation import material_evaluator
    from twoscale.fit.record import albedo_table_entry

    params = PARAMS.replace(sigma_s=sigma_s)
    rec = _record(params)
    rec.albedo_table = albedo_table_entry(
        params,
        CONFIG,
        n=8,
        evaluate_lobes=material_evaluator(adapter_for(CONFIG), params),
    )
    lines = rec.summary().splitlines()
    light = [ln for ln in lines if "light per lobe at normal incidence" in ln]
    assert len(light) == 1 and "specular [" in light[0] and "diffraction [" in light[0]
    assert "diffuse" not in light[0]  # the conductor has no floor here: no such lobe
    note = [ln for ln in lines if "b and c are not determined" in ln]
    assert len(note) == (1 if faint else 0), lines
    # A record without the split (older records, --no-albedo) prints neither.
    rec.albedo_table = None
    assert not any("light per lobe" in ln for ln in rec.summary().splitlines())

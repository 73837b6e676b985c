"""``campaigns/fall_off_form.py``: refitting the apparatus factor's (e, m) alone, in each form."""

from __future__ import annotations

import numpy as np

from campaigns import fall_off_form
from tests.helpers import two_scale_record
from twoscale import ModelConfig, TwoScaleParams, merl
from twoscale.fit import synthetic


def test_the_form_that_made_the_data_wins_and_recovers_its_exponents(capsys, tmp_path):
    """Data made with the protocol's ``L(θ_i) L(θ_o)`` (a rough plastic, noise-free): its form
    refits e and m and the data to round-off; ``L(θ_d)²``, the same at the mirror direction only,
    fits worse; no factor worse still. The command line reads a record and prints the three."""
    cfg = ModelConfig(material="plastic", diffraction=False, apparatus=True, apparatus_knee=True)
    true = TwoScaleParams.plastic(0.3, 1.0, (1.5, 1.5, 1.5), (0.2, 0.1, 0.05), e=0.8, m=4.0)
    data = synthetic(true, cfg, noise=0.0, seed=1)
    start = true.replace(e=0.5, m=2.0)  # away from the truth: the refit must move e and m
    out = fall_off_form.compare_forms(data, start, cfg, n_cells=20_000)
    assert set(out) == set(fall_off_form.FORMS)
    io, d, none = out["theta_io"], out["theta_d"], out["none"]
    np.testing.assert_allclose([io["e"], io["m"]], [0.8, 4.0], rtol=1e-3)
    assert io["rmse_log"] < 1e-5, io
    assert d["rmse_log"] > 20 * io["rmse_log"] and d["rmse_grazing"] > d["rmse_other"], d
    assert none["rmse_log"] > d["rmse_log"], (none, d)

    path = merl.write(tmp_path / "m.binary", data)
    record = two_scale_record(start, cfg).save(tmp_path / "params.json")
    assert fall_off_form.main([str(path), str(record), "--cells", "20000"]) == 0
    printed = capsys.readouterr().out
    assert all(form in printed for form in fall_off_form.FORMS), printed
    assert "two-scale (plastic)" in printed, printed

"""A fit result a user can use: its model configuration as an object, evaluation in one line,
and a record that names its input file (name, size, SHA-256)."""

import hashlib
import json

import jax.numpy as jnp
import numpy as np
import pytest

import twoscale
from twoscale.baselines import CookTorranceConfig, CookTorranceParams
from twoscale.fit import Stage, fit, load_result, synthetic

CT = CookTorranceConfig("ggx")
CT_TRUE = CookTorranceParams(0.15, [0.9, 0.7, 0.4], [0.02, 0.05, 0.1])
TS = twoscale.ModelConfig(diffraction=False, material="conductor")
TS_TRUE = twoscale.TwoScaleParams.conductor(
    beta=0.2, p=1.2, eta=(0.3, 0.6, 1.2), k=(3.0, 2.5, 2.0)
).for_config(TS)
SHORT = [Stage(4096, 1, 30)]


@pytest.fixture(scope="module")
def ct_file(tmp_path_factory):
    data = synthetic(CT_TRUE, CT, noise=0.0, seed=3)
    path = tmp_path_factory.mktemp("merl") / "ct-material.binary"
    raw = np.where(data.valid[..., None], data.values, -1.0)
    twoscale.merl.write(path, raw, data.valid)
    return path


@pytest.fixture(scope="module")
def ct_fit(ct_file):
    return fit(twoscale.merl.read(ct_file), config=CT, schedule=SHORT)


def test_read_records_size_and_sha256(ct_file):
    data = twoscale.merl.read(ct_file)
    blob = ct_file.read_bytes()
    assert data.size == len(blob) == twoscale.merl.FILE_BYTES
    assert data.sha256 == hashlib.sha256(blob).hexdigest()
    # In-memory data has no file to name.
    assert synthetic(CT_TRUE, CT, seed=3).sha256 is None


def test_params_json_names_its_input(ct_file, ct_fit, tmp_path):
    res = ct_fit
    assert res.rmse_log < 1e-3  # the fit did fit (noise-free data of its own model)
    res.save(tmp_path / "params.json")
    back = load_result(tmp_path / "params.json")
    assert back.data["name"] == "ct-material"
    assert back.data["path"] == str(ct_file)
    assert back.data["size_bytes"] == twoscale.merl.FILE_BYTES
    assert back.data["sha256"] == hashlib.sha256(ct_file.read_bytes()).hexdigest()
    # The loaded baseline evaluates in one line, on the grid and at directions, and agrees with
    # the in-memory result.
    assert isinstance(back.model_config, CookTorranceConfig)
    grid = np.asarray(back.evaluate_merl())
    assert grid.shape == (90, 90, 180, 3)
    np.testing.assert_allclose(grid, np.asarray(res.evaluate_merl()), rtol=1e-12)
    wi, wo = twoscale.merl.grid_directions()
    i = (10, 20, 30)
    np.testing.assert_allclose(
        np.asarray(back.evaluate(wi[i], wo[i])), grid[i], rtol=1e-12, atol=1e-15
    )


def test_two_scale_result_evaluates_in_one_line(ct_fit, tmp_path):
    # A two-scale record: the baseline fit's record with the model, configuration and
    # parameters of a two-scale material (what the fitter writes; no second fit needed).
    from twoscale.fit.adapters import adapter_for

    record = ct_fit.to_dict()
    adapter = adapter_for(TS)
    record.update(model="two-scale", config=adapter.config_to_dict())
    record["params"] = adapter.params_to_dict(TS_TRUE)
    path = tmp_path / "params.json"
    path.write_text(json.dumps(record))
    back = load_result(path)
    assert back.model_config == TS
    wi = jnp.array([[0.3, 0.0, 0.954], [0.0, 0.6, 0.8]])
    wo = jnp.array([[-0.3, 0.0, 0.954], [0.5, -0.2, 0.843]])
    np.testing.assert_allclose(
        np.asarray(back.evaluate(wi, wo)),
        np.asarray(twoscale.brdf(TS_TRUE, wi, wo, TS)),
        rtol=1e-12,
    )
    grid = np.asarray(back.evaluate_merl())
    np.testing.assert_allclose(grid, np.asarray(twoscale.brdf_merl(TS_TRUE, TS)), rtol=1e-12)
    assert np.all(np.isfinite(grid)) and grid.max() > 0

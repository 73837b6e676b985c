"""Smoke test of the benchmarks (tiny sizes, no timing assertions) and the NumPy reference model."""

import numpy as np
import pytest

import twoscale
from benchmarks import numpy_model, run


def _dirs(rng, n):
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_numpy_model_agrees_with_brdf():
    rng = np.random.default_rng(0)
    wi, wo = run._grid(997)  # MERL directions (some below the horizon) ...
    wi = np.concatenate([wi, _dirs(rng, 500)])  # ... and random ones
    wo = np.concatenate([wo, _dirs(rng, 500)])
    for params in (
        run._params(),
        twoscale.TwoScaleParams.conductor(
            beta=0.02, p=0.6, eta=(1.2, 0.9, 0.4), k=(6.0, 4.0, 2.5), sigma_s=0.05, b=8.0, c=1.3
        ),
    ):
        ref = np.asarray(twoscale.brdf(params, wi, wo))
        new = numpy_model.brdf(params.to_dict(), wi, wo)
        assert np.array_equal(ref == 0, new == 0)
        ok = ref > 0
        np.testing.assert_allclose(new[ok], ref[ok], rtol=1e-6)
    x = numpy_model.pack(params.to_dict())
    assert x.shape == (11,)
    np.testing.assert_array_equal(numpy_model.pack(numpy_model.unpack(x)), x)


@pytest.mark.slow
def test_benchmark_scripts_run_on_tiny_sizes(tmp_path):
    """The runner end to end on tiny sizes (20 s on 2 cores: the slow set; the numbers it
    measures come from code checked by default: test_numpy_model_agrees_with_brdf and the
    model's own tests)."""
    assert run.main(["--smoke", "--only", "variants", "--out", str(tmp_path)]) == 0
    text = (tmp_path / "variants.md").read_text()
    assert "specular only" in text and "Load average" in text
    # Trade pieces on a tiny grid: errors of the variants against the exact path.
    body = run._errors(np.array([1.0, 2.0]), np.array([1.0, 2.5]))
    assert body == (0.2, 0.1)
    rows = [[0, 1.0, 0, 0, 0.1], [0, 2.0, 0, 0, 0.05], [0, 3.0, 0, 0, 0.2]]
    assert run._pareto(rows, 1, 4) == [True, True, False]


def test_ggx_reference_peak_value():
    """The speed table's peer: at normal incidence and mirror reflection, D = 1/(πα²), G = 1 and
    F = F0, so the value is F0/(4πα²) + ρ_d/π; below the horizon it is 0."""
    from benchmarks import reference

    n = np.array([[0.0, 0.0, 1.0], [0.0, 0.6, -0.8]])
    args = reference.ggx_inputs(n, np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]), np.float64)
    out = np.asarray(reference.ggx_lambert(*args))
    a, f0, rho = reference.ALPHA, np.array(reference.F0), np.array(reference.RHO_D)
    np.testing.assert_allclose(out[0], f0 / (4 * np.pi * a * a) + rho / np.pi, rtol=1e-12)
    np.testing.assert_array_equal(out[1], 0.0)


def test_fit_worker_refuses_a_spectral_protocol(capsys):
    """The MERL protocol is RGB: ``--wavelengths`` with it is an error, not a silent RGB fit."""
    from benchmarks import fit_worker

    with pytest.raises(SystemExit) as exc:
        fit_worker.main(["--config", "protocol", "--wavelengths", "8"])
    assert exc.value.code == 2
    assert "--wavelengths needs --config conductor or auto" in capsys.readouterr().err

"""Parameter recovery of the two-scale model from synthetic MERL tables made by the model itself.

Synthetic tables (``twoscale.fit.synthetic``) sample the model at the MERL bins' lower edges with
the realistic mask (below-horizon cells plus random dropout: ≈ 24 % invalid). From the default
starts, noise-free data must give back the parameters within 2 %, and 1 % multiplicative noise
must give them back within a few reported standard errors, with the residual at the noise level.

The default run fits one noisy plastic with the preview schedule (the full-data refinement stage
is the same solver on more cells: ``tests/test_fit.py`` and ``test_cli.py`` run it); the ``slow``
cases add its noise-free fit, the conductor's preview fits and more parameter sets with the
default schedule.
"""

from __future__ import annotations

import numpy as np
import pytest

from twoscale import ModelConfig, TwoScaleParams
from twoscale.fit import fit, synthetic
from twoscale.fit.synthetic import EXAMPLE

# The default fit follows the MERL protocol (apparatus factor on): the default cases are made with
# MERL's grazing fall-off (exponent e; the conductor's also with a knee exponent m ≠ 2, fitted as
# the protocol does); the slow sets without it, fitted with the bare model.
CONDUCTOR = TwoScaleParams.conductor(**{**EXAMPLE, "e": 0.7, "m": 4.0})  # the --example metal
PLASTIC = TwoScaleParams.plastic(
    beta=0.08,
    p=0.8,
    eta=(1.5, 1.5, 1.5),
    rho_d=(0.3, 0.15, 0.05),
    sigma_s=0.008,
    b=2.0,
    c=1.8,
    e=0.9,
)
SLOW_SETS = [
    (
        "conductor",
        TwoScaleParams.conductor(0.05, 2.5, (1.2, 0.9, 0.6), (6.0, 5.0, 4.0), 0.02, 0.8, 2.8),
    ),
    pytest.param(
        "conductor",
        TwoScaleParams.conductor(0.3, 0.7, (2.0, 1.8, 1.5), (3.0, 3.2, 3.5), 0.005, 4.0, 1.4),
        marks=pytest.mark.xfail(
            reason="measured: noise-free recovery passes, but with 1 % noise the fit lands in "
            "another basin (σ_s 0.0228 vs 0.005 µm, 150 standard errors away): a narrow "
            "diffraction lobe (b = 4 µm) under a rough specular lobe is nearly degenerate",
            strict=False,
        ),
    ),
    pytest.param(
        "plastic",
        TwoScaleParams.plastic(0.2, 1.2, (1.4, 1.4, 1.4), (0.6, 0.5, 0.4), 0.01, 1.0, 2.5),
        marks=pytest.mark.xfail(
            reason="NOT FIXED (since 2026-12-02): the noisy fit ends at c = 1.07 against 2.5, "
            "11 standard errors away (σ_s 0.029 ± 0.024, b 1.9 ± 0.2). Measured 2026-12-04: "
            "its scaled log RMS on every fitted cell is 0.0052878 against 0.0052876 at the "
            "true parameters, 3e-5 relative, below the stall rule's 1e-4: with a weak "
            "diffraction lobe (A_spec(0) ≈ 0.95) the (σ_s, b, c) valley is that flat, and the "
            "linearised standard errors do not describe it",
            strict=False,
        ),
    ),
]


def _relative_errors(est: TwoScaleParams, true: TwoScaleParams) -> dict:
    out = {}
    for name, value in true.fields().items():
        t = np.atleast_1d(np.asarray(value, float))
        e = np.atleast_1d(np.asarray(getattr(est, name), float))
        out[name] = np.abs(e - t) / np.abs(t)
    return out


def _config(material: str, true: TwoScaleParams) -> ModelConfig:
    return ModelConfig(
        material=material, apparatus=true.e is not None, apparatus_knee=true.m is not None
    )


def _check_noise_free(material: str, true: TwoScaleParams, schedule: str) -> None:
    cfg = _config(material, true)
    data = synthetic(true, cfg, noise=0.0, seed=3)
    res = fit(data, config=cfg, schedule=schedule)
    assert res.converged, res.status
    rel = _relative_errors(res.params, true)
    worst = {k: float(v.max()) for k, v in rel.items()}
    assert all(v <= 0.02 for v in worst.values()), worst
    assert res.rmse_log < 1e-4, res.rmse_log


def _check_noisy(material: str, true: TwoScaleParams, schedule: str) -> None:
    cfg = _config(material, true)
    data = synthetic(true, cfg, noise=0.01, seed=4)
    res = fit(data, config=cfg, schedule=schedule)
    assert res.converged, res.status
    # 1 % multiplicative noise on ρ gives log residuals ≈ 0.01 ρ cos/(1 + ρ cos) < 0.01.
    assert 1e-4 < res.rmse_log < 0.01, res.rmse_log
    for name, value in true.fields().items():
        est = np.asarray(getattr(res.params, name), float)
        se = np.asarray(res.std_errors[name], float)
        assert np.all(se > 0), (name, se)
        assert np.all(np.abs(est - np.asarray(value)) <= 5.0 * se + 1e-12), (name, est, value, se)


# Each material's first fit in a module compiles its solver (≈ 20 s on 2 cores): the default run
# fits the plastic with noise (its full-model fit is run nowhere else by default), the slow run its
# noise-free fit (the same code, ≈ 15 s more) and the conductor's, whose fits the default run
# covers in tests/test_fit.py (the full model started from its special case:
# test_preview_of_a_bare_metal_fits_one_type; the apparatus factor's e:
# test_merl_protocol_default_is_apparatus; the type choice: test_type_choice_on_synthetic_materials)
# and, in the slow set, by notebooks/fitting.ipynb.
@pytest.mark.slow
def test_recovery_noise_free():
    _check_noise_free("plastic", PLASTIC, "preview")


def test_recovery_noisy_within_standard_errors():
    _check_noisy("plastic", PLASTIC, "preview")


@pytest.mark.slow
def test_recovery_conductor_preview():
    """The conductor's noise-free and noisy recoveries (preview schedule); the same fitter code as
    the plastic's test_recovery_noise_free / test_recovery_noisy_within_standard_errors, and the
    conductor's full-model fits run by default in test_fit.py."""
    _check_noise_free("conductor", CONDUCTOR, "preview")
    _check_noisy("conductor", CONDUCTOR, "preview")


@pytest.mark.slow
@pytest.mark.parametrize(("material", "true"), SLOW_SETS)
def test_recovery_more_sets_default_schedule(material, true):
    _check_noise_free(material, true, "default")
    _check_noisy(material, true, "default")

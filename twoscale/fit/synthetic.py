"""Synthetic MERL tables made by a model with known parameters (tests, ``--example``)."""

from __future__ import annotations

import numpy as np

from twoscale.fit.adapters import adapter_for
from twoscale.fit.cells import Cells

#: Parameters of the ``--example`` material: a rough gold-like conductor with a diffraction halo,
#: measured through MERL's apparatus (``e``: the grazing fall-off of the specular lobe).
EXAMPLE = dict(
    beta=0.12,
    p=1.4,
    eta=(0.25, 0.55, 1.35),
    k=(3.4, 2.4, 1.8),
    sigma_s=0.012,
    b=1.5,
    c=2.2,
    e=0.8,
)

#: Fraction of above-horizon cells dropped at random by :func:`synthetic` (with the cells below
#: the horizon this gives ≈ 24 % invalid cells, as in the MERL files: 75.8 % valid).
DROPOUT = 0.005


def synthetic(
    params,
    config,
    *,
    noise: float = 0.0,
    invalid: bool = True,
    dropout: float = DROPOUT,
    seed: int = 0,
    name: str = "synthetic",
):
    """A :class:`twoscale.merl.MerlData` sampled from a model at the lower-edge bin directions.

    Args:
        params: model parameters (``TwoScaleParams`` or a baseline's).
        config: the model configuration (``ModelConfig`` or ``CookTorranceConfig``).
        noise: relative standard deviation of multiplicative Gaussian noise (0.01 = 1 %).
        invalid: mark the cells below the horizon invalid, plus a random ``dropout`` fraction
            of the others (a realistic MERL mask, ≈ 24 % invalid). Otherwise only the cells
            below the horizon are invalid.
        seed: seed of the noise and of the dropout.
    """
    from twoscale import merl
    from twoscale.fit.evaluation import predict_cells

    shape = merl.SHAPE
    blank = merl.MerlData(
        values=np.zeros(shape + (3,)), valid=np.ones(shape, bool), path=None, name=name
    )
    wi, wo = blank.directions("lower")
    wi = np.asarray(wi).reshape(-1, 3)
    wo = np.asarray(wo).reshape(-1, 3)
    above = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    idx = np.flatnonzero(above)
    cells = Cells(wi[idx], wo[idx], np.zeros((idx.size, 3)), idx)
    adapter = adapter_for(config)
    pred = predict_cells(adapter, params, cells)
    rng = np.random.default_rng(seed)
    if noise:
        pred = pred * (1.0 + noise * rng.standard_normal(pred.shape))
    values = np.zeros((above.size, 3))
    values[idx] = np.maximum(pred, 0.0)
    valid = above.copy()
    if invalid and dropout > 0:
        valid[idx[rng.random(idx.size) < dropout]] = False
    values[~valid] = 0.0
    return merl.MerlData(
        values=values.reshape(shape + (3,)), valid=valid.reshape(shape), path=None, name=name
    )

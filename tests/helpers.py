"""Shared test helpers: float64 finite differences, NaN checks, stand-in fit records."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def fd_grad(f, x, h=None):
    """Central finite-difference derivative of scalar f at scalar x (float64), step ~ eps^(1/3)·scale."""
    x = float(x)
    h = h if h is not None else 6e-6 * max(abs(x), 1e-3)
    return (float(f(x + h)) - float(f(x - h))) / (2 * h)


def assert_finite_tree(tree, what=""):
    """Every leaf of ``tree`` is finite."""
    for leaf in jax.tree_util.tree_leaves(tree):
        arr = np.asarray(leaf)
        assert np.all(np.isfinite(arr)), f"non-finite {what}: {arr}"


def grads_all(f, *args):
    """Gradients of sum(f(*args)) w.r.t. every positional argument."""
    return jax.grad(lambda *a: jnp.sum(f(*a)), argnums=tuple(range(len(args))))(*args)


def two_scale_record(params, config, **fields):
    """A :class:`~twoscale.fit.record.FitResult` of a two-scale fit that was never run: ``params``
    under ``config`` with zero errors (``fields`` override any other field)."""
    from twoscale.fit.adapters import config_to_dict
    from twoscale.fit.record import FitResult

    record = dict(
        params=params,
        model="two-scale",
        config={"model": "two-scale", **config_to_dict(config)},
        metric="log",
        rmse_linear=0.0,
        rmse_log=0.0,
        per_channel={},
        rmse_fit=0.0,
        n_valid=1,
        n_fit=1,
        converged=True,
        status="stand-in fit",
        steps=0,
        wall_time=0.0,
        std_errors={},
        covariance={},
        settings={},
        versions={},
        data={},
    )
    return FitResult(**(record | fields))

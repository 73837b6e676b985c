"""Shared test helpers: float64 finite differences and NaN checks."""

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

"""Small numerical guards shared by the kernels.

Every guard here exists so that values *and* gradients stay finite over the documented domain.
The pattern is the JAX FAQ's "double where": the unsafe branch is fed a harmless input where it
would be evaluated outside its domain, so that its (discarded) gradient is finite too.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np


def tiny(dtype) -> float:
    """Smallest positive normal number of ``dtype`` (a floor that keeps logs and divisions finite)."""
    return float(jnp.finfo(dtype).tiny)


def eps(dtype) -> float:
    """Machine epsilon of ``dtype``."""
    return float(jnp.finfo(dtype).eps)


def float_dtype(*xs, default=jnp.float32):
    """Result floating dtype of the inputs: the one dtype rule of the kernels.

    A floating array among the inputs sets it (weak Python scalars do not promote float32).
    Without one (Python numbers, integer arrays) it is ``default``: float32 for the model, or
    ``float``, JAX's default float (float64 under ``jax_enable_x64``), where a component kernel
    documents that Python numbers follow JAX's default (:mod:`twoscale.shadowing`,
    :mod:`twoscale.psd`).
    """
    return jnp.dtype(jnp.result_type(*xs, default))


def safe_sqrt(x):
    """``sqrt(max(x, 0))`` whose gradient is 0 (not inf/NaN) where ``x <= 0``."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def safe_log(x):
    """``log(x)`` for ``x > 0``; returns ``log(tiny)`` (finite) where ``x <= 0``, with zero gradient."""
    floor = tiny(jnp.result_type(x))
    pos = x > floor
    return jnp.where(pos, jnp.log(jnp.where(pos, x, 1.0)), jnp.log(floor))


def safe_pow(x, p):
    """``x**p`` for ``x >= 0`` and ``p > 0``, with finite gradients at ``x = 0``.

    ``x**p = exp(p log x)``: at ``x = 0`` the gradient in ``p`` is ``x**p log x = 0·(−inf)``,
    which autodiff turns into NaN (docs/model.md §6 trap 1). The double where keeps it at 0.
    """
    pos = x > 0
    xs = jnp.where(pos, x, 1.0)
    return jnp.where(pos, jnp.exp(p * jnp.log(xs)), 0.0)


@functools.cache
def gauss_legendre(n: int, a: float = 0.0, b: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre nodes and weights on ``[a, b]`` (NumPy float64, cached)."""
    x, w = np.polynomial.legendre.leggauss(n)
    x = 0.5 * (b - a) * x + 0.5 * (b + a)
    w = 0.5 * (b - a) * w
    x.setflags(write=False)
    w.setflags(write=False)
    return x, w

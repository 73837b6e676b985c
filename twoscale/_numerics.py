"""Small numerical guards shared by the kernels.

Every guard here exists so that values *and* gradients stay finite over the documented domain.
The pattern is the JAX FAQ's "double where": the unsafe branch is fed a harmless input where it
would be evaluated outside its domain, so that its (discarded) gradient is finite too.
"""

from __future__ import annotations

import functools
import math

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


_LOG2 = math.log(2.0)


def asinh_nonneg(x):
    """``asinh x`` as ``log1p(x + x²/(1 + √(1 + x²)))`` for ``x ≥ 0`` (``−asinh(−x)`` below 0).

    Accurate to a few ulp for every ``x ≥ 0`` (no cancellation: every term is positive) and
    cheaper than ``jnp.arcsinh``, which evaluates two logarithms; ``x²`` overflows beyond
    ``√max`` (1e154 in float64), where the quotient tends to ``x`` and the result stays finite.
    """
    ax = jnp.where(x < 0.0, -x, x)  # not abs: its derivative at 0 would be 0, not 1
    big = ax > 1e150 if jnp.result_type(x) == jnp.float64 else ax > 1e18
    safe = jnp.where(big, 1.0, ax)
    small = jnp.log1p(safe + safe * safe / (1.0 + jnp.sqrt(1.0 + safe * safe)))
    val = jnp.where(big, jnp.log(jnp.where(big, ax, 1.0)) + _LOG2, small)
    return jnp.where(x < 0.0, -val, val)


@functools.cache
def gauss_legendre(n: int, a: float = 0.0, b: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre nodes and weights on ``[a, b]`` (NumPy float64, cached)."""
    x, w = np.polynomial.legendre.leggauss(n)
    x = 0.5 * (b - a) * x + 0.5 * (b + a)
    w = 0.5 * (b - a) * w
    x.setflags(write=False)
    w.setflags(write=False)
    return x, w

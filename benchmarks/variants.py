"""Model variants the trade study compares that are not ``ModelConfig`` switches.

:func:`table_variant` rebuilds every spline the model uses (Smith Λ, renormalisation R, the
convolution components) with another interpolation order (``1``: multilinear, the authors'
choice; ``3``: the library's C² cubic B-spline) and/or from every ``stride``-th node of each table
axis (:meth:`twoscale.tables.Table.subsample`). It is a study hook for this package only: it
swaps ``Table.spline`` while active, clears the modules' spline caches and JAX's trace caches
(the spline coefficients are trace-time constants of the jitted model), and restores everything
on exit.
"""

from __future__ import annotations

import contextlib
import importlib

import jax

from twoscale import tables

__all__ = ["table_variant", "harmonics_available"]


def _clear_caches() -> None:
    from twoscale import psd, shadowing

    for fn in (getattr(shadowing, "_spline", None), getattr(psd, "_spline_cached", None)):
        if fn is not None and hasattr(fn, "cache_clear"):
            fn.cache_clear()
    jax.clear_caches()


@contextlib.contextmanager
def table_variant(order: int = 3, stride: int = 1):
    """Make the model's tables interpolate with ``order`` on a ``stride``-subsampled grid."""
    if order == 3 and stride == 1:
        yield
        return
    original = tables.Table.spline

    def spline(self, dtype=jax.numpy.float64, order_=None):
        table = self.subsample(stride) if stride > 1 else self
        return original(table, dtype, order=order if order_ is None else order_)

    tables.Table.spline = spline
    _clear_caches()
    try:
        yield
    finally:
        tables.Table.spline = original
        _clear_caches()


def harmonics_available():
    """``twoscale.harmonics.lobe_harmonic`` if that module exists, else ``None``."""
    try:
        mod = importlib.import_module("twoscale.harmonics")
    except ImportError:
        return None
    return getattr(mod, "lobe_harmonic", None)

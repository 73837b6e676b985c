"""Model variants the trade study compares that are not ``ModelConfig`` switches.

:func:`table_variant` makes the model's table splines (Smith Λ, renormalisation R, the convolved
lobe ``g``) interpolate with another order (``1``: multilinear, the authors' choice; ``3``: the
library's C² cubic B-spline) and/or from every ``stride``-th node of each table axis
(:meth:`twoscale.tables.Table.subsample`). It is the table service's supported study hook,
:func:`twoscale.tables.interpolation`: the service keys its splines on these settings and JAX's
trace caches are cleared on entry and exit (the coefficients are trace-time constants of the
jitted model); the convolution's angle map and ``log k`` stay cubic on the full grid.
"""

from __future__ import annotations

import contextlib
import importlib

from twoscale import tables

__all__ = ["table_variant", "harmonics_available"]


@contextlib.contextmanager
def table_variant(order: int = 3, stride: int = 1):
    """Make the model's tables interpolate with ``order`` on a ``stride``-subsampled grid."""
    with tables.interpolation(order, stride):
        yield


def harmonics_available():
    """``twoscale.harmonics.lobe_harmonic`` if that module exists, else ``None``."""
    try:
        mod = importlib.import_module("twoscale.harmonics")
    except ImportError:
        return None
    return getattr(mod, "lobe_harmonic", None)

"""Fitting BRDF models to MERL measurements (docs/model.md §8).

``fit(data, ...)`` runs the multi-start, coarse-to-fine Levenberg-Marquardt fit and returns a
:class:`FitResult`; ``python -m twoscale.fit material.binary`` is the command-line front end.
"""

import sys

from twoscale.fit.cells import select_cells as select_cells
from twoscale.fit.driver import FitError as FitError
from twoscale.fit.driver import fit as fit
from twoscale.fit.evaluation import predict_cells as predict_cells
from twoscale.fit.material_type import merl_protocol as merl_protocol
from twoscale.fit.record import FitResult as FitResult
from twoscale.fit.record import load_result as load_result
from twoscale.fit.schedule import DEFAULT_SCHEDULE as DEFAULT_SCHEDULE
from twoscale.fit.schedule import PREVIEW_SCHEDULE as PREVIEW_SCHEDULE
from twoscale.fit.schedule import Stage as Stage
from twoscale.fit.synthetic import EXAMPLE as EXAMPLE
from twoscale.fit.synthetic import synthetic as synthetic


class _CallableModule(type(sys.modules[__name__])):
    """``twoscale.fit`` is a package *and* the fitting function: calling it calls :func:`fit`."""

    def __call__(self, data, *args, **kwargs):
        return fit(data, *args, **kwargs)

    __call__.__doc__ = fit.__doc__


sys.modules[__name__].__class__ = _CallableModule

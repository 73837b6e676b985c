"""NumPy's transparent-huge-page advice, switched off for the fit's CLI and the tests.

On Linux NumPy marks every allocation of 4 MiB or more with ``madvise(MADV_HUGEPAGE)``. Where
the kernel's ``/sys/kernel/mm/transparent_hugepage/defrag`` is ``madvise`` or
``defer+madvise`` (the default of many distributions), a page fault in such memory may stall
while the kernel compacts memory to find a huge page, instead of falling back to small pages
(numpy/numpy#31590 describes it). A fit allocates many arrays of the MERL grid's size (35 MB)
on the host: reading the file, selecting and pairing the cells, the pictures. Measured on the
2-core machine (``defrag`` = ``madvise``): selecting the cells of a MERL file 1.2-1.8 s with the
advice, 0.2 s without; ``python -m twoscale.fit silver-paint.binary`` with a warm compilation
cache 38.2-38.4 s → 31.0-31.3 s, the same fit.

NumPy reads its switch, the environment variable ``NUMPY_MADVISE_HUGEPAGE``, when it is
imported; :func:`avoid_hugepage_stalls` sets the same switch afterwards, and leaves it alone
when the user has set that variable (``NUMPY_MADVISE_HUGEPAGE=1`` keeps NumPy's advice).
"""

from __future__ import annotations

import os

ENV_VAR = "NUMPY_MADVISE_HUGEPAGE"


def _setter():
    """NumPy's private setter of the advice (``numpy._core`` from 2.0, ``numpy.core`` before),
    or None."""
    import numpy as np

    for module in ("_core", "core"):
        ma = getattr(getattr(np, module, None), "multiarray", None)
        fn = getattr(ma, "_set_madvise_hugepage", None)
        if fn is not None:
            return fn
    return None


def avoid_hugepage_stalls(environ=None) -> bool:
    """Stop NumPy from advising huge pages for this process unless ``NUMPY_MADVISE_HUGEPAGE``
    is set. Returns whether the advice was switched off by this call."""
    env = os.environ if environ is None else environ
    if ENV_VAR in env:
        return False
    setter = _setter()
    if setter is None:
        return False
    setter(False)
    return True

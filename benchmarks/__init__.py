"""Speed / accuracy benchmarks of ``twoscale`` (``python -m benchmarks.run [--quick]``).

Modules: :mod:`benchmarks.numpy_model` (an independent NumPy evaluation of the default model on
the library's tables, for the SciPy comparison), :mod:`benchmarks.common` (timing, machine
description, Markdown tables), :mod:`benchmarks.variants` (table order / resolution overrides),
:mod:`benchmarks.fit_worker` (one fit in a subprocess, for its peak memory), and
:mod:`benchmarks.run` (the command). Results: ``benchmarks/results/*.md``.
"""

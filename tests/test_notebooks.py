"""The notebooks in ``notebooks/``: committed without outputs, and they run headless with figures.

Each notebook is executed with nbclient in a fresh ``python3`` kernel of the interpreter running the
tests (a kernel spec written for ``sys.executable`` into a temporary ``JUPYTER_PATH``, so that a
``python3`` kernel registered elsewhere cannot run another environment), in a temporary working
directory; two notebooks run at once (one kernel each). A run passes when every cell executes without an error, no Python warning is printed,
at least one ``image/png`` output is produced, and the kernel reports ``sys.executable`` to be
this interpreter. The tests skip, naming the reason, when nbclient or ipykernel is missing
(``pip install -e .[test]`` installs both); ``rendering.ipynb`` is skipped (not executed) when
Mitsuba 3 or its LLVM backend cannot be loaded.
"""

from __future__ import annotations

import asyncio
import functools
import json
import os
import re
import sys
import time
from pathlib import Path

import pytest

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))
EXPECTED = ("quickstart", "fitting", "speed_accuracy", "stability", "rendering")
#: Notebooks that render with Mitsuba 3 (executed only where it and libLLVM load).
NEEDS_MITSUBA = ("rendering",)
#: Executed in the slow set only (``-m slow``; CI runs it): every notebook. The fast set checks
#: that each is committed clean, that every code cell parses, and that every ``twoscale.…`` name
#: it uses exists (:func:`test_cells_parse_and_names_exist`); the library code they call is tested
#: directly: evaluation, lobes, gradients, spectra and albedo (tests/test_model.py,
#: tests/test_spectral.py), the extremes (tests/test_model.py, tests/test_convolution.py), fitting
#: (tests/test_fit.py, tests/test_recovery.py, tests/test_cli.py), speed and accuracy
#: (tests/test_table_service.py, tests/test_convolution.py, tests/test_benchmarks.py) and rendering
#: (tests/test_mitsuba.py, tests/test_render_cli.py). Executed, they took 33-77 s each on 2 cores,
#: the quickstart and stability ones together 77 s: an eighth of the fast set.
SLOW_NOTEBOOKS = EXPECTED
#: Seconds allowed per cell: each notebook takes well under a minute in all on 2 cores; the margin
#: absorbs a loaded CI machine (the longest cell, the fit, is ≈ 20 s on an idle one).
CELL_TIMEOUT = 300
X64_LINE = 'jax.config.update("jax_enable_x64", True)'
#: A Python warning as ``warnings.showwarning`` prints it (``file:line: CategoryWarning: text``).
WARNING_LINE = re.compile(r":\d+: \w*Warning: ")
#: Notebooks executed at once (two cores: each kernel mostly compiles on one).
PARALLEL = 2
#: The cell appended to each executed copy: the kernel's interpreter.
EXECUTABLE_PROBE = "import sys\nprint('sys.executable =', sys.executable)"


@functools.cache
def _no_mitsuba() -> str | None:
    """Why Mitsuba 3 cannot render here (None when it can)."""
    from twoscale.render import RenderUnavailable, check_available

    try:
        check_available()
    except RenderUnavailable as err:
        return str(err)
    return None


def _skip_reason(path: Path) -> str | None:
    if path.stem in NEEDS_MITSUBA and _no_mitsuba():
        return f"{path.name} needs Mitsuba 3 and libLLVM: {_no_mitsuba()}"
    return None


def _ids(paths):
    return [p.stem for p in paths]


def _run_params(paths):
    """``test_notebook_runs``'s parameters: the notebooks of :data:`SLOW_NOTEBOOKS` marked slow."""
    return [
        pytest.param(p, id=p.stem, marks=[pytest.mark.slow] if p.stem in SLOW_NOTEBOOKS else [])
        for p in paths
    ]


def _load_json(path: Path) -> dict:
    with path.open(encoding="utf-8") as f:
        return json.load(f)


def _source(cell: dict) -> str:
    src = cell.get("source", "")
    return "".join(src) if isinstance(src, list) else src


# ------------------------------------------------------------------------- committed notebooks
def test_expected_notebooks_exist():
    assert set(EXPECTED) <= {p.stem for p in NOTEBOOKS}, f"notebooks in {NOTEBOOK_DIR}: {NOTEBOOKS}"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=_ids(NOTEBOOKS))
def test_cells_parse_and_names_exist(path):
    """Every code cell is valid Python, and every dotted name under ``twoscale`` that a cell
    spells out (``twoscale.fit.synthetic``, ``twoscale.geometry.spherical``, ...) exists: the
    fast set's guard against a renamed API, without executing the notebook."""
    import importlib

    nb = _load_json(path)
    used = set()
    for i, cell in enumerate(c for c in nb["cells"] if c["cell_type"] == "code"):
        src = _source(cell)
        compile(src, f"{path.name}[{i}]", "exec")  # raises SyntaxError naming the cell
        used |= set(re.findall(r"\btwoscale(?:\.[A-Za-z_]\w*)+", src))
    assert used, f"{path.name} uses no twoscale name"
    for name in sorted(used):
        parts = name.split(".")
        obj = importlib.import_module(parts[0])
        for k, part in enumerate(parts[1:], start=1):
            if hasattr(obj, part):
                obj = getattr(obj, part)
            else:  # a submodule not imported by its package
                obj = importlib.import_module(".".join(parts[: k + 1]))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=_ids(NOTEBOOKS))
def test_committed_without_outputs(path):
    """nbformat 4, no outputs, no execution counts; float64 switched on in the first code cell."""
    nb = _load_json(path)
    assert nb["nbformat"] == 4
    assert nb["metadata"].get("kernelspec", {}).get("name") == "python3"
    code = [c for c in nb["cells"] if c["cell_type"] == "code"]
    assert code, f"{path.name} has no code cell"
    for i, cell in enumerate(code):
        assert cell.get("outputs") == [], f"{path.name}: code cell {i} has outputs (clear them)"
        assert cell.get("execution_count") is None, f"{path.name}: code cell {i} has a count"
    assert X64_LINE in _source(code[0]), f"{path.name}: the first code cell must call {X64_LINE}"


# ------------------------------------------------------------------------- executed notebooks
@pytest.fixture(scope="module")
def kernel_name(tmp_path_factory):
    """``"python3"``, from a kernel spec for ``sys.executable`` put first on ``JUPYTER_PATH``."""
    pytest.importorskip("nbformat", reason="nbformat is not installed (pip install -e .[test])")
    pytest.importorskip("nbclient", reason="nbclient is not installed (pip install -e .[test])")
    pytest.importorskip(
        "ipykernel", reason="no Jupyter kernel: ipykernel is not installed (pip install -e .[test])"
    )
    from ipykernel.kernelspec import write_kernel_spec

    root = tmp_path_factory.mktemp("jupyter")
    write_kernel_spec(root / "kernels" / "python3")  # argv[0] = sys.executable
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("JUPYTER_PATH", str(root))  # searched before the user and environment dirs
        mp.setenv("JUPYTER_PLATFORM_DIRS", "1")  # jupyter_core's path-migration warning, off
        from jupyter_client.kernelspec import KernelSpecManager, NoSuchKernel

        try:
            spec = KernelSpecManager().get_kernel_spec("python3")
        except NoSuchKernel:  # pragma: no cover - only with a broken Jupyter installation
            pytest.skip("no Jupyter kernel named python3 is available")
        assert Path(spec.resource_dir) == root / "kernels" / "python3", spec.resource_dir
        assert os.path.samefile(spec.argv[0], sys.executable), spec.argv
        yield "python3"


async def _execute(path: Path, kernel: str, cwd: Path):
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read(path, as_version=4)
    nb.cells.append(nbformat.v4.new_code_cell(EXECUTABLE_PROBE))
    client = NotebookClient(
        nb,
        kernel_name=kernel,
        timeout=CELL_TIMEOUT,
        allow_errors=False,  # the first failing cell raises CellExecutionError with its traceback
        resources={"metadata": {"path": str(cwd)}},  # the kernel's working directory
    )
    t0 = time.perf_counter()
    await client.async_execute()
    return nb, time.perf_counter() - t0


@pytest.fixture(scope="module")
def executed(kernel_name, tmp_path_factory, request):
    """Every notebook whose ``test_notebook_runs`` is selected in this run (``-m``, ``-k``),
    executed ``PARALLEL`` kernels at a time: ``{stem: (nb, seconds)}``, or the exception its
    execution raised (re-raised by its own test).

    Each kernel compiles on one core most of the time, so two at once take about half the wall
    time of one after the other on two cores; every notebook still runs in its own fresh kernel
    and temporary working directory, and each is checked by its own test below.
    """

    async def run_all():
        gate = asyncio.Semaphore(PARALLEL)

        async def one(path):
            async with gate:
                return await _execute(path, kernel_name, tmp_path_factory.mktemp(path.stem))

        selected = {
            item.callspec.params["path"]
            for item in request.session.items
            if item.originalname == "test_notebook_runs" and hasattr(item, "callspec")
        }
        runnable = [p for p in NOTEBOOKS if p in selected and not _skip_reason(p)]
        return runnable, await asyncio.gather(*(one(p) for p in runnable), return_exceptions=True)

    runnable, results = asyncio.run(run_all())
    return dict(zip(_ids(runnable), results, strict=True))


def _outputs(nb):
    for cell in nb.cells:
        if cell.cell_type == "code":
            yield from cell.outputs


@pytest.mark.parametrize("path", _run_params(NOTEBOOKS))
def test_notebook_runs(path, request, record_property):
    if reason := _skip_reason(path):
        pytest.skip(reason)
    result = request.getfixturevalue("executed")[path.stem]
    if isinstance(result, BaseException):
        raise result
    nb, seconds = result
    record_property("seconds", round(seconds, 1))
    outputs = list(_outputs(nb))

    errors = [o for o in outputs if o.output_type == "error"]
    assert not errors, f"{path.name}: {[(e.ename, e.evalue) for e in errors]}"
    stderr = "".join(o.text for o in outputs if o.output_type == "stream" and o.name == "stderr")
    warned = [line for line in stderr.splitlines() if WARNING_LINE.search(line)]
    assert not warned, f"{path.name} printed warnings: {warned}"

    pngs = [o for o in outputs if "image/png" in o.get("data", {})]
    assert pngs, f"{path.name} produced no figure (no image/png output)"

    probe = "".join(o.get("text", "") for o in nb.cells[-1].outputs if o.output_type == "stream")
    executable = probe.strip().removeprefix("sys.executable =").strip()
    assert os.path.samefile(executable, sys.executable), (executable, sys.executable)
    # The working directory is the temporary one (nothing is written into the repository).
    assert not list(NOTEBOOK_DIR.glob("*.png")) and not list(NOTEBOOK_DIR.glob("*.binary"))

"""Test configuration: float64 everywhere in tests (never at library import)."""

import os
import shutil
import tempfile
import uuid
from pathlib import Path

# Before JAX's import: large constants (the convolution table) passed to compiled code as
# arguments, as in the CLI (twoscale._xla.HOIST_ENV; JAX reads it when it is imported), with the
# CLI's rules: a value the user set wins, TWOSCALE_HOIST_CONSTANTS=0 keeps JAX's default. The
# names are spelled out: importing twoscale._xla would import JAX first.
if os.environ.get("TWOSCALE_HOIST_CONSTANTS", "1") != "0":
    os.environ.setdefault("JAX_USE_SIMPLIFIED_JAXPR_CONSTANTS", "true")

import pytest

from twoscale._hugepages import avoid_hugepage_stalls
from twoscale._xla import prefer_fast_compile

# Before JAX starts: the suite compiles far more than it runs, as the CLI does (twoscale._xla:
# the fast set 427 -> 370 s on 2 cores, measured; .ci/run also runs it with
# XLA's default emitters, TWOSCALE_FAST_COMPILE=0).
prefer_fast_compile()
# No huge-page advice for NumPy's large arrays, as in the CLI (twoscale._hugepages).
avoid_hugepage_stalls()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
# The CLI's persistent compilation cache stays off in tests (never written into the user's cache
# folder); the test of the cache switches it on for its own subprocesses.
os.environ["TWOSCALE_COMPILE_CACHE"] = "0"

#: Seconds of compilation from which a compiled function is kept in the run's compilation cache.
SUITE_CACHE_MIN_COMPILE_S = 0.2


def pytest_configure(config):
    """One persistent compilation cache for the whole test run, in a new temporary folder.

    The suite compiles the same functions many times: in both xdist workers, again in each module
    after :func:`_release_compiled_code`, and in the CLI's subprocesses. JAX's persistent cache
    (keyed by the compiled program and its options, so never a wrong hit) lets every compilation
    after the first load the executable instead: the fast set's CPU time 15.1 -> 13.1 min, its
    wall time 482 -> 424 s on the 2-core machine (measured one after the other, 2026-12-06).
    The folder is made for this run (named by xdist's run id, which the workers share), so
    nothing from an earlier run or the user's cache is read, and removed when the run ends.
    ``TWOSCALE_TEST_COMPILE_CACHE=0`` switches it off. It is off with large constants embedded
    in compiled code (JAX's default, ``.ci/run``'s third run of the fast set): every entry then
    carries the convolution table, and the folder grew to 2.4 GB in that run (measured).
    """
    hoisted = os.environ.get("JAX_USE_SIMPLIFIED_JAXPR_CONSTANTS", "").lower() in ("1", "true")
    if os.environ.get("TWOSCALE_TEST_COMPILE_CACHE", "1") == "0" or not hoisted:
        return
    worker = getattr(config, "workerinput", None)
    if worker is not None:
        uid = worker["testrunuid"]
    else:  # the controller (or a run without xdist) names the run; xdist passes it on
        uid = getattr(config.option, "testrunuid", None) or uuid.uuid4().hex
        if hasattr(config.option, "testrunuid"):
            config.option.testrunuid = uid
        config._twoscale_suite_cache = _suite_cache_dir(uid)
    folder = _suite_cache_dir(uid)
    folder.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", SUITE_CACHE_MIN_COMPILE_S)
    # The CLI's subprocesses (its persistent cache off, TWOSCALE_COMPILE_CACHE=0) use it too.
    os.environ["JAX_COMPILATION_CACHE_DIR"] = str(folder)
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = str(SUITE_CACHE_MIN_COMPILE_S)


def _suite_cache_dir(uid: str) -> Path:
    return Path(tempfile.gettempdir()) / f"twoscale-tests-jax-cache-{uid}"


def pytest_unconfigure(config):
    """Remove the run's compilation cache (the controller's, once every worker has ended)."""
    folder = getattr(config, "_twoscale_suite_cache", None)
    if folder is not None:
        shutil.rmtree(folder, ignore_errors=True)


SHARED = Path(os.environ.get("TWOSCALE_SHARED", Path(__file__).resolve().parents[2] / "shared"))
SHARED_DATA = SHARED / "data"


@pytest.fixture
def shared_data():
    """Path to ../shared/data; skips the test cleanly when the folder is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(autouse=True, scope="module")
def _compile_quickly(request):
    """XLA without most of its optimisations for modules that set ``COMPILE_QUICKLY = True``.

    Those modules check values and gradients of many configurations, each evaluated a few times
    at small sizes: their time is compilation, which this halves (tests/test_model.py: 226 s ->
    145 s in one process, the same tests passing). Optimisation passes do not change what is
    computed; modules whose time is spent running compiled code (fits, renders) keep them.
    """
    if not getattr(request.module, "COMPILE_QUICKLY", False):
        yield
        return
    # A flag JAX reads when it compiles (jax._src.compiler), initialised from this variable.
    before = os.environ.get("JAX_DISABLE_MOST_OPTIMIZATIONS", "").lower() in ("1", "true")
    jax.config.update("jax_disable_most_optimizations", True)
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", before)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code():
    """Drop JAX's compiled executables after each test module.

    The suite compiles hundreds of functions (every configuration, shape and solver variant);
    kept for the whole session they grew the process past 7 GB (measured), so each module
    starts from empty caches instead (a few seconds of recompilation in all).
    """
    yield
    jax.clear_caches()


#: The test modules that take longest (worker seconds of the fast set on the 2-core machine,
#: 2026-12-06: test_fit 116, test_model 87, test_grid 72, test_convolution 54, test_mitsuba 50,
#: test_shadowing 48, test_sampling 36, test_cli 31, test_recovery 30, test_schlick 28), run
#: first. ``-n 2 --dist loadfile`` hands the modules to the two workers in collection order, one
#: at a time as a worker becomes free; alphabetical order left long modules for the end, where
#: one worker ran them while the other had nothing left (the wall time ≈ 40 s over half the
#: workers' total). Longest first, the modules left for the end are short.
LONGEST_FIRST = (
    "test_fit",
    "test_model",
    "test_grid",
    "test_convolution",
    "test_mitsuba",
    "test_shadowing",
    "test_sampling",
    "test_cli",
    "test_recovery",
    "test_schlick",
)


def pytest_collection_modifyitems(config, items):
    """Modules of :data:`LONGEST_FIRST` first, in that order; the others after them in
    collection order (a stable sort: the tests of a module keep their order)."""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}

    def key(item):
        module = getattr(item, "module", None)
        name = module.__name__.rsplit(".", 1)[-1] if module is not None else ""
        return rank.get(name, len(rank))

    items.sort(key=key)

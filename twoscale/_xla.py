"""XLA settings for programs that compile many large functions once (the fit's CLI, the tests).

XLA's CPU backend emits fused loops with its MLIR "fusion emitters" by default. The older LLVM
emitters (``--xla_cpu_use_fusion_emitters=false``) compile the fit's functions about a third
faster at nearly the same speed of the compiled code. Measured on the 2-core machine
(``python -m twoscale.fit`` on stand-ins of MERL materials):

- the full model's compiled solve: 5.1-5.4 s to compile with the fusion emitters, 3.4-3.6 s
  without; one pass of its normal equations over all 1.1 M cells 662 ms against 658 ms;
- the whole CLI with an empty compilation cache: pvc 54.5 → 43.5 s, silver-paint 61-64 → 53 s
  (the same fits to 1e-15); with a warm cache pvc 26.4-26.7 → 27.3-27.5 s;
- but some kernels run slower without them (the convolution table's accuracy checks in the
  tests: 5.2 → 30.7 s, 6× slower), so the library itself leaves XLA's default alone: only the
  CLI and the test suite, which compile far more than they run, ask for it.

The flag must be in ``XLA_FLAGS`` before JAX starts its CPU backend (the first computation), and
XLA aborts the process on a flag it does not know, so it is only added when the installed jaxlib
names it, and never over a setting of the user's.
"""

from __future__ import annotations

import mmap
import os
import sys
from pathlib import Path

FAST_COMPILE_FLAG = "--xla_cpu_use_fusion_emitters=false"

#: Switch: ``TWOSCALE_FAST_COMPILE=0`` keeps XLA's default emitters.
ENV_SWITCH = "TWOSCALE_FAST_COMPILE"


def _jaxlib_knows(flag_name: str) -> bool:
    """Whether a shared library of the installed jaxlib contains the flag's name."""
    try:
        import importlib.util

        spec = importlib.util.find_spec("jaxlib")
        if spec is None or not spec.submodule_search_locations:
            return False
        needle = flag_name.encode()
        for folder in spec.submodule_search_locations:
            libs = sorted(Path(folder).glob("*.so"), key=lambda p: p.stat().st_size, reverse=True)
            for lib in libs:
                if lib.stat().st_size < 10_000_000:
                    break
                with open(lib, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
                    if m.find(needle) >= 0:
                        return True
    except (OSError, ValueError):
        return False
    return False


def prefer_fast_compile(environ=None) -> bool:
    """Add :data:`FAST_COMPILE_FLAG` to ``XLA_FLAGS`` (see the module doc) unless the user set
    that flag, ``TWOSCALE_FAST_COMPILE=0``, or jaxlib does not know it. Returns whether the flag
    is now in ``XLA_FLAGS``. Call it before JAX's first computation: later it changes nothing."""
    env = os.environ if environ is None else environ
    flags = env.get("XLA_FLAGS", "")
    name = FAST_COMPILE_FLAG.split("=")[0].lstrip("-")
    if name in flags:
        return FAST_COMPILE_FLAG in flags.split()
    if env.get(ENV_SWITCH, "1") == "0" or not _jaxlib_knows(name):
        return False
    env["XLA_FLAGS"] = f"{flags} {FAST_COMPILE_FLAG}".strip()
    return True


#: JAX's option (an environment variable, read when JAX is imported) that passes a function's
#: large closed-over constants to its compiled code as arguments instead of embedding them in it
#: (above ``jax_embedded_constants_max_bytes``, 32 bytes by default;
#: https://docs.jax.dev/en/latest/internals/constants.html). JAX calls the option transitional:
#: it selects the behaviour that is to become the default. Set after JAX's import (with
#: ``jax.config.update``) it changes the flag's value but not the behaviour (JAX 0.10.2).
HOIST_ENV = "JAX_USE_SIMPLIFIED_JAXPR_CONSTANTS"

#: Switch: ``TWOSCALE_HOIST_CONSTANTS=0`` keeps JAX's default (constants embedded).
HOIST_SWITCH = "TWOSCALE_HOIST_CONSTANTS"

#: The command lines that set :data:`HOIST_ENV` for themselves (``python -m MODULE``).
CLI_MODULES = ("twoscale.fit",)


def hoist_large_constants(environ=None, modules=None) -> bool:
    """Set :data:`HOIST_ENV` unless the user set it, ``TWOSCALE_HOIST_CONSTANTS=0``, or JAX is
    already imported (``modules``: default ``sys.modules``), when it would change nothing.
    Returns whether large constants are hoisted in this process.

    Why: the convolution table's 5.7 M spline coefficients (23 MB in float32) are closed-over
    constants of every compiled function that evaluates the diffraction lobe. Embedded, they are
    converted, compiled into and stored with each such function: a ``--preview`` fit compiled
    them into five functions and wrote 123 MB to the persistent compilation cache (2.7 MB with
    them hoisted). The option is part of JAX's compilation key, so code compiled either way is
    never mixed up.
    """
    env = os.environ if environ is None else environ
    mods = sys.modules if modules is None else modules
    if env.get(HOIST_SWITCH, "1") == "0":
        return False
    if HOIST_ENV in env:
        return env[HOIST_ENV].strip().lower() in ("1", "true", "yes", "on")
    if "jax" in mods:
        return False
    env[HOIST_ENV] = "true"
    return True


#: The interpreter's options that take the next word as their value (``python -X importtime``).
_OPTIONS_WITH_VALUE = ("-X", "-W", "--check-hash-based-pycs")


def started_as_cli(argv=None) -> bool:
    """Whether this process is ``python [options] -m M ...`` for an ``M`` of :data:`CLI_MODULES`
    (``argv``: default ``sys.orig_argv``, the interpreter's own command line). Only the
    interpreter's options are read: a ``-m`` among a script's or a ``-c`` command's arguments
    (``python script.py -m twoscale.fit``) is the script's."""
    argv = list(getattr(sys, "orig_argv", []) if argv is None else argv)
    i = 1
    while i < len(argv):
        arg = argv[i]
        if arg in _OPTIONS_WITH_VALUE:
            i += 2
            continue
        if not arg.startswith("-") or arg == "-" or arg.startswith("-c"):
            return False  # a script, standard input or a command: the rest is theirs
        if not arg.startswith("--") and arg.endswith("m"):  # -m, or flags ending in it (-Bm)
            return i + 1 < len(argv) and argv[i + 1] in CLI_MODULES
        i += 1
    return False

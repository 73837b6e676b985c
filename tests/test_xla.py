"""The CLI's and the suite's XLA setting (twoscale/_xla.py): added only where it is safe."""

import os
import subprocess
import sys
from pathlib import Path

from twoscale._xla import (
    ENV_SWITCH,
    FAST_COMPILE_FLAG,
    HOIST_ENV,
    HOIST_SWITCH,
    _jaxlib_knows,
    hoist_large_constants,
    prefer_fast_compile,
    started_as_cli,
)

REPO = Path(__file__).resolve().parents[1]


def test_flag_added_to_existing_flags_once():
    if not _jaxlib_knows(FAST_COMPILE_FLAG.split("=")[0].lstrip("-")):
        env = {}
        assert prefer_fast_compile(env) is False and "XLA_FLAGS" not in env
        return
    env = {"XLA_FLAGS": "--xla_dump_to=/tmp/x"}
    assert prefer_fast_compile(env) is True
    assert env["XLA_FLAGS"].split() == ["--xla_dump_to=/tmp/x", FAST_COMPILE_FLAG]
    assert prefer_fast_compile(env) is True  # already there: unchanged
    assert env["XLA_FLAGS"].split() == ["--xla_dump_to=/tmp/x", FAST_COMPILE_FLAG]


def test_user_setting_and_switch_win():
    env = {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true"}
    assert prefer_fast_compile(env) is False
    assert env["XLA_FLAGS"] == "--xla_cpu_use_fusion_emitters=true"
    env = {ENV_SWITCH: "0"}
    assert prefer_fast_compile(env) is False and "XLA_FLAGS" not in env


def test_unknown_flag_is_never_added():
    """XLA aborts on a flag it does not know: only names found in jaxlib are added."""
    assert not _jaxlib_knows("xla_no_such_flag_in_any_jaxlib_0f3c9a")


def test_hoisting_is_set_before_jax_only():
    """The option is an environment variable JAX reads at its import: set only before it, never
    over the user's value or with the switch off."""
    env = {}
    assert hoist_large_constants(env, modules={}) is True and env[HOIST_ENV] == "true"
    env = {}
    assert hoist_large_constants(env, modules={"jax": object()}) is False and env == {}
    env = {HOIST_ENV: "false"}
    assert hoist_large_constants(env, modules={}) is False and env == {HOIST_ENV: "false"}
    env = {HOIST_ENV: "1"}
    assert hoist_large_constants(env, modules={"jax": object()}) is True
    env = {HOIST_SWITCH: "0"}
    assert hoist_large_constants(env, modules={}) is False and HOIST_ENV not in env


def test_started_as_cli():
    assert started_as_cli(["python", "-m", "twoscale.fit", "a.binary"])
    assert started_as_cli(["/usr/bin/python3", "-X", "importtime", "-m", "twoscale.fit"])
    assert not started_as_cli(["python", "-m", "pytest", "twoscale.fit"])
    assert started_as_cli(["python", "-W", "ignore", "-Bm", "twoscale.fit"])
    # A -m among a script's or a command's arguments is theirs, not the interpreter's.
    assert not started_as_cli(["python", "script.py", "-m", "twoscale.fit"])
    assert not started_as_cli(["python", "-c", "pass", "-m", "twoscale.fit"])
    assert not started_as_cli(["python", "-", "-m", "twoscale.fit"])
    assert not started_as_cli(["python", "-m"])
    assert not started_as_cli([])


_PROBE = """
import sys
{argv}
import twoscale
import jax
from twoscale import TwoScaleParams
jax.config.update("jax_enable_x64", True)
print(jax.config.jax_use_simplified_jaxpr_constants)
p = TwoScaleParams.conductor(0.1, 1.0, (0.2, 0.5, 1.4), (3.5, 2.5, 1.9), 0.01, 1.5, 2.2)
w = jax.numpy.array([[0.0, 0.0, 1.0]])
ir = jax.jit(lambda: twoscale.brdf(p, w, w)).lower().compiler_ir("stablehlo")
main = next(op for op in ir.body.operations if op.attributes["sym_name"].value == "main")
print(len(main.regions[0].blocks[0].arguments))
"""


def _probe(argv_line: str) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k not in (HOIST_ENV, HOIST_SWITCH)}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    out = subprocess.run(
        [sys.executable, "-c", _PROBE.format(argv=argv_line)],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_cli_hoists_the_tables_constants_and_the_library_does_not():
    """Run as ``python -m twoscale.fit``, twoscale sets the option before JAX's import, and the
    full model's compiled code (a function of no arguments) takes the tables as arguments;
    imported as a library, it changes nothing: the tables are embedded, no argument."""
    flag, n_args = _probe('sys.orig_argv = [sys.executable, "-m", "twoscale.fit"]')
    assert flag == "True" and int(n_args) >= 1
    flag, n_args = _probe("")
    assert flag == "False" and int(n_args) == 0

"""The CLI's and the suite's XLA setting (twoscale/_xla.py): added only where it is safe."""

from twoscale._xla import ENV_SWITCH, FAST_COMPILE_FLAG, _jaxlib_knows, prefer_fast_compile


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

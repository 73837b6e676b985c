"""``python -m twoscale.fit``: success path, bad inputs, exit codes, warnings, the MERL protocol,
the compilation cache, loading the result back.

Most cases call :func:`twoscale.fit.__main__.main` in-process (the compiled fit is shared between
tests); the bad-input cases also run as real subprocesses to check the exit status and that no
traceback reaches the user.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from twoscale import merl
from twoscale.baselines import CookTorranceConfig, CookTorranceParams
from twoscale.fit import load_result, synthetic
from twoscale.fit.__main__ import EXIT_FIT, EXIT_INPUT, main

REPO = Path(__file__).resolve().parents[1]
CT_TRUE = CookTorranceParams(0.2, [0.8, 0.6, 0.3], [0.05, 0.1, 0.2])


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    good = d / "ct.binary"
    merl.write(good, synthetic(CT_TRUE, CookTorranceConfig("ggx"), noise=0.01, seed=3))
    short = d / "short.binary"
    short.write_bytes(b"\x5a\x00\x00\x00" * 3 + b"\x00" * 100)
    header = d / "header.binary"
    header.write_bytes(np.asarray([90, 90, 90], "<i4").tobytes() + b"\x00" * 64)
    empty = d / "empty.binary"
    merl.write(empty, np.zeros((90, 90, 180, 3)), np.zeros((90, 90, 180), bool))
    black = d / "black.binary"  # every cell valid and 0
    merl.write(black, np.zeros((90, 90, 180, 3)))
    return {
        "good": good,
        "short": short,
        "header": header,
        "empty": empty,
        "black": black,
        "dir": d,
    }


def _run_cli(args, cwd, extra_env=None):
    env = {**os.environ, **(extra_env or {})}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    env.pop("TWOSCALE_DEBUG", None)
    return subprocess.run(
        [sys.executable, "-m", "twoscale.fit", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def _assert_one_line_error(stderr: str, needle: str):
    lines = [ln for ln in stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, stderr
    assert lines[0].startswith("error: ") and needle in lines[0], stderr
    assert "Traceback" not in stderr


def test_success_and_load_back(files, tmp_path, capsys):
    out = tmp_path / "fit-out"
    rc = main([str(files["good"]), "--out", str(out), "--baseline", "ggx", "--preview"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert sorted(p.name for p in out.iterdir()) == [
        "lobes.png",
        "params.json",
        "slices.png",
        "spheres.png",
    ]
    for png in out.glob("*.png"):
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # Ordinary permissions (the temporary folder and files start 0o700 / 0o600).
    umask = os.umask(0)
    os.umask(umask)
    assert out.stat().st_mode & 0o777 == 0o777 & ~umask
    assert (out / "params.json").stat().st_mode & 0o777 == 0o666 & ~umask
    assert "RMSE" in captured.out and "stage 1/2" in captured.err
    res = load_result(out / "params.json")
    assert res.converged and res.model == "cook-torrance-ggx"
    np.testing.assert_allclose(res.params.alpha, 0.2, rtol=1e-3)
    raw = json.loads((out / "params.json").read_text())
    assert raw["settings"]["starts"] == "few"  # --preview: fewer starts, no last stage
    assert len(raw["settings"]["schedule"]) == 2
    assert CookTorranceParams.from_dict(raw["params"]).to_dict() == res.params.to_dict()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left
    # A second run into the existing folder replaces the files.
    rc = main(
        [
            str(files["good"]),
            "--out",
            str(out),
            "--baseline",
            "ggx",
            "--preview",
            "--no-plots",
            "--quiet",
        ]
    )
    assert rc == 0
    assert (out / "params.json").is_file()


@pytest.mark.parametrize(
    "case, needle",
    [
        ("missing", "no such file"),
        ("short", "not a valid MERL"),
        ("header", "header dimensions"),
        ("empty", "invalid"),
        ("black", "every valid cell is 0"),
    ],
)
def test_bad_input_in_process(files, tmp_path, capsys, case, needle):
    path = files["dir"] / "missing.binary" if case == "missing" else files[case]
    out = tmp_path / "out"
    rc = main([str(path), "--out", str(out)])
    assert rc == EXIT_INPUT
    _assert_one_line_error(capsys.readouterr().err, needle)
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "args, needle",
    [
        (["missing.binary"], "no such file"),
        (["short.binary"], "not a valid MERL"),
        (["empty.binary"], "invalid"),
        (["ct.binary", "--max-theta", "120"], "--max-theta"),
        ([], "give a MERL .binary file"),
    ],
)
def test_bad_input_subprocess(files, args, needle):
    proc = _run_cli([*args, "--out", "result"], cwd=files["dir"])
    assert proc.returncode == EXIT_INPUT, proc.stderr
    _assert_one_line_error(proc.stderr, needle)
    assert proc.stdout == ""
    assert not (files["dir"] / "result").exists()


def test_bad_options(files, tmp_path, capsys):
    rc = main([str(files["good"]), "--out", str(tmp_path / "o"), "--fix", "alpha"])
    assert rc == EXIT_INPUT
    _assert_one_line_error(capsys.readouterr().err, "NAME=VALUE")
    # Out of range or not finite: exit 2 before any work (p = 100 fitted at p = 5 with exit 0,
    # p = nan ran to exit 3).
    for held, needle in (
        (["p=100"], "outside its valid range [0.2, 5]"),
        (["p=nan"], "not a finite number"),
        (["p=1", "--fix", "p=2"], "--fix p given twice"),
    ):
        rc = main([str(files["good"]), "--out", str(tmp_path / "o"), "--fix", *held])
        assert rc == EXIT_INPUT
        _assert_one_line_error(capsys.readouterr().err, needle)
    assert not (tmp_path / "o").exists()
    taken = tmp_path / "a-file"
    taken.write_text("x")
    rc = main([str(files["good"]), "--out", str(taken), "--baseline", "ggx"])
    assert rc == EXIT_INPUT
    _assert_one_line_error(capsys.readouterr().err, "not a folder")
    assert taken.read_text() == "x"


def test_capped_fit_exits_0_with_a_warning(files, tmp_path, capsys, monkeypatch):
    """A fit stopped at the step limit is kept: exit 0, one warning line, recorded in params.json."""
    import twoscale.fit.driver as driver

    real_fit = driver.fit

    def capped_fit(data, **kw):
        kw["schedule"] = [driver.Stage(4096, 1, max_steps=1)]  # one solver step: the cap ends it
        return real_fit(data, **kw)

    monkeypatch.setattr(driver, "fit", capped_fit)
    out = tmp_path / "out"
    rc = main([str(files["good"]), "--out", str(out), "--baseline", "ggx", "--quiet", "--no-plots"])
    err = capsys.readouterr().err
    assert rc == 0, err
    warnings = [ln for ln in err.splitlines() if ln.startswith("warning: ")]
    assert any("not converged: step limit reached" in ln for ln in warnings), err
    res = load_result(out / "params.json")
    assert res.converged is False
    assert any("step limit" in w for w in res.warnings)


def test_failed_fit_exits_3_and_leaves_nothing(files, tmp_path, capsys, monkeypatch):
    """No start with a finite fit: exit 3, one error line, nothing written."""
    import math

    import twoscale.fit.solver as solver

    def broken(cand, g, stage, data, n_active, m, opts, twin=None):
        return cand.y, math.nan, np.zeros((0, 0)), 1, False, "non-finite values"

    monkeypatch.setattr(solver, "refine", broken)
    out = tmp_path / "out"
    rc = main([str(files["good"]), "--out", str(out), "--baseline", "ggx", "--quiet"])
    assert rc == EXIT_FIT
    _assert_one_line_error(capsys.readouterr().err, "no start gave a finite fit")
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_merl_protocol_and_bound_warning(files, tmp_path, capsys):
    """The apparatus factor is on by default (also for the baselines), off with --no-apparatus.
    The synthetic data have no grazing fall-off, so e ends at 0: a warning names it, exit 0."""
    out = tmp_path / "on"
    rc = main(
        [str(files["good"]), "--out", str(out), "--baseline", "ggx", "--preview", "--no-plots"]
    )
    err = capsys.readouterr().err
    assert rc == 0, err
    res = load_result(out / "params.json")
    assert res.config["apparatus"] is True and res.std_errors["e"] is not None
    assert any(w.startswith("e = ") and "lower end" in w for w in res.warnings)
    assert any(ln.startswith("warning: e = ") for ln in err.splitlines()), err
    out = tmp_path / "off"
    args = [str(files["good"]), "--out", str(out), "--baseline", "ggx", "--preview", "--no-plots"]
    rc = main([*args, "--no-apparatus", "--quiet"])
    assert rc == 0
    res = load_result(out / "params.json")
    assert res.config["apparatus"] is False and "e" not in res.std_errors
    assert res.warnings == []


def test_implausible_albedo_warns(files, tmp_path, capsys):
    """Values far above any material's (here 1,000× a GGX table's: not in 1/sr) fit with
    exit 0 but a warning that names the albedo, in the log, on stderr and in params.json; the
    same table at its own scale has none (test_merl_protocol_and_bound_warning)."""
    data = merl.read(files["good"])
    bright = tmp_path / "bright.binary"
    merl.write(bright, np.asarray(data.values) * 1000.0, np.asarray(data.valid))
    out = tmp_path / "out"
    args = [str(bright), "--out", str(out), "--baseline", "ggx", "--preview", "--no-plots"]
    rc = main(args)
    err = capsys.readouterr().err
    assert rc == 0, err
    res = load_result(out / "params.json")
    lines = [w for w in res.warnings if "reflects more light than it receives" in w]
    assert len(lines) == 1 and "albedo" in lines[0], res.warnings
    assert f"warning: {lines[0]}" in err.splitlines(), err


def test_compile_cache_folder_and_switch(tmp_path, monkeypatch):
    """Where the persistent cache goes (TWOSCALE_CACHE_DIR, else XDG_CACHE_HOME/twoscale/jax)
    and what enabling it sets; the end-to-end reuse is test_second_run_reuses_the_compilation_cache
    (two CLI processes, ≈ 30 s on 2 cores: the slow set)."""
    import jax

    from twoscale.fit import __main__ as cli

    monkeypatch.delenv("TWOSCALE_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cli.cache_dir() == tmp_path / "xdg" / "twoscale" / "jax"
    monkeypatch.setenv("TWOSCALE_CACHE_DIR", str(tmp_path / "mine"))
    assert cli.cache_dir() == tmp_path / "mine"
    before = {
        k: jax.config.values[k]
        for k in ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs")
    }
    try:
        assert cli.enable_compile_cache(lambda msg: None) == tmp_path / "mine"
        assert (tmp_path / "mine").is_dir()
        assert jax.config.values["jax_compilation_cache_dir"] == str(tmp_path / "mine")
        assert jax.config.values["jax_persistent_cache_min_compile_time_secs"] == 0.0
    finally:
        for k, v in before.items():
            jax.config.update(k, v)
    # A folder that cannot be made: the run goes on without a cache, saying why.
    (tmp_path / "file").write_text("")
    monkeypatch.setenv("TWOSCALE_CACHE_DIR", str(tmp_path / "file" / "sub"))
    said = []
    assert cli.enable_compile_cache(said.append) is None
    assert said and "compilation cache off" in said[0]


@pytest.mark.slow
def test_second_run_reuses_the_compilation_cache(files, tmp_path):
    """Two CLI runs on two files: the first fills the persistent cache, the second adds nothing
    to it (every compiled function is found there), and --no-compile-cache leaves it alone.
    Slow set; by default test_compile_cache_folder_and_switch checks the folder and settings."""
    cache = tmp_path / "cache"
    other = tmp_path / "other.binary"
    truth = CookTorranceParams(0.3, [0.5, 0.5, 0.5], [0.1, 0.1, 0.1])
    merl.write(other, synthetic(truth, CookTorranceConfig("ggx"), noise=0.01, seed=4))
    env = {"TWOSCALE_CACHE_DIR": str(cache), "TWOSCALE_COMPILE_CACHE": "1"}
    args = ["--baseline", "ggx", "--preview", "--no-plots", "--quiet"]
    first = _run_cli([str(files["good"]), "--out", str(tmp_path / "a"), *args], tmp_path, env)
    assert first.returncode == 0, first.stderr
    entries = sorted(p.name for p in cache.iterdir())
    assert entries, "the first run cached nothing"
    second = _run_cli([str(other), "--out", str(tmp_path / "b"), *args], tmp_path, env)
    assert second.returncode == 0, second.stderr
    assert sorted(p.name for p in cache.iterdir()) == entries
    off = tmp_path / "off-cache"
    third = _run_cli(
        [str(other), "--out", str(tmp_path / "c"), *args, "--no-compile-cache"],
        tmp_path,
        {"TWOSCALE_CACHE_DIR": str(off), "TWOSCALE_COMPILE_CACHE": "1"},
    )
    assert third.returncode == 0, third.stderr
    assert not off.exists()


@pytest.mark.parametrize(
    ("flags", "apparatus", "knee", "diffuse_fresnel", "fresnel", "metric"),
    [
        ([], True, True, False, "auto", "blend"),
        (["--diffuse-fresnel", "--metric", "scaled-log"], True, True, True, "auto", "scaled-log"),
        (["--no-apparatus-knee"], True, False, False, "auto", "blend"),
        (["--no-apparatus", "--fresnel", "exact"], False, False, False, "exact", "blend"),
    ],
)
def test_cli_passes_the_merl_protocol(
    files, tmp_path, monkeypatch, flags, apparatus, knee, diffuse_fresnel, fresnel, metric
):
    """The two-scale fit gets :func:`twoscale.fit.merl_protocol` (apparatus factor, Lambertian
    body) and the blended log metric unless a flag says otherwise; the material type and a
    dielectric coat's Fresnel form are left to the fit unless ``--fresnel`` fixes it."""
    import twoscale.fit.driver as driver
    from twoscale.fit import merl_protocol

    seen = {}

    def spy(data, *, config, material, **kwargs):
        seen.update(
            config=config,
            material=material,
            fresnel=kwargs.get("fresnel"),
            metric=kwargs.get("metric"),
        )
        raise driver.FitError("stopped by the test")

    monkeypatch.setattr(driver, "fit", spy)
    rc = main([str(files["good"]), "--out", str(tmp_path / "o"), "--quiet", *flags])
    assert rc == EXIT_FIT
    assert seen["config"] == merl_protocol(
        apparatus=apparatus, apparatus_knee=knee, diffuse_fresnel=diffuse_fresnel
    )
    assert seen["config"].apparatus_knee is knee
    assert seen["material"] == "auto"
    assert seen["fresnel"] == fresnel
    assert seen["metric"] == metric


def _configs_the_cli_passes(files, tmp_path, monkeypatch, runs) -> list:
    """The configuration ``main`` hands the fit for each list of extra arguments in ``runs``
    (the fit itself replaced by a spy that stops it: exit 3)."""
    import twoscale.fit.driver as driver

    seen = []

    def spy(data, *, config, material, **kwargs):
        seen.append(config)
        raise driver.FitError("stopped by the test")

    monkeypatch.setattr(driver, "fit", spy)
    for flags in runs:
        rc = main([str(files["good"]), "--out", str(tmp_path / "o"), "--quiet", *flags])
        assert rc == EXIT_FIT
    return seen


@pytest.mark.parametrize("baseline", [[], ["--baseline", "ggx"]])
def test_cli_passes_the_shadowing(files, tmp_path, monkeypatch, baseline):
    """``--shadowing uncorrelated`` reaches the two-scale model's configuration and the
    baseline's alike; the default is the reference's correlated form."""
    from twoscale.baselines import CookTorranceConfig
    from twoscale.fit import merl_protocol

    runs = (baseline, [*baseline, "--shadowing", "uncorrelated"])
    seen = _configs_the_cli_passes(files, tmp_path, monkeypatch, runs)
    assert [c.shadowing for c in seen] == ["correlated", "uncorrelated"]
    if baseline:
        assert seen[1] == CookTorranceConfig(
            "ggx",
            apparatus=True,
            apparatus_knee=True,
            shadowing="uncorrelated",
            apparatus_angles="theta_d",
        )
    else:
        assert seen[1] == merl_protocol(shadowing="uncorrelated")


@pytest.mark.parametrize("baseline", [[], ["--baseline", "ggx"]])
def test_cli_passes_the_apparatus_angles(files, tmp_path, monkeypatch, baseline):
    """``--apparatus-angles`` reaches the two-scale model's configuration and the baseline's
    alike; the default is the MERL protocol's ``L(θ_d)²``, ``theta_io`` the paper's
    ``L(θ_i) L(θ_o)``; a record keeps it."""
    from twoscale.baselines import CookTorranceConfig
    from twoscale.fit import merl_protocol
    from twoscale.fit.adapters import adapter_for, config_from_dict

    runs = (baseline, [*baseline, "--apparatus-angles", "theta_io"])
    seen = _configs_the_cli_passes(files, tmp_path, monkeypatch, runs)
    assert [c.apparatus_angles for c in seen] == ["theta_d", "theta_io"]
    if not baseline:
        assert seen[0] == merl_protocol()
        assert seen[1] == merl_protocol(apparatus_angles="theta_io")
    if baseline:
        want = CookTorranceConfig(
            "ggx", apparatus=True, apparatus_knee=True, apparatus_angles="theta_d"
        )
    else:
        want = merl_protocol(apparatus_angles="theta_d")
    assert seen[0] == want
    saved = adapter_for(want).config_to_dict()
    assert saved["apparatus_angles"] == "theta_d" and config_from_dict(saved) == want
    saved.pop("apparatus_angles")  # a record written before the switch existed
    assert config_from_dict(saved).apparatus_angles == "theta_io"

"""``python -m twoscale.fit``: success path, bad inputs, non-convergence, loading the result back.

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
    return {"good": good, "short": short, "header": header, "empty": empty, "dir": d}


def _run_cli(args, cwd):
    env = dict(os.environ)
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
    taken = tmp_path / "a-file"
    taken.write_text("x")
    rc = main([str(files["good"]), "--out", str(taken), "--baseline", "ggx"])
    assert rc == EXIT_INPUT
    _assert_one_line_error(capsys.readouterr().err, "not a folder")
    assert taken.read_text() == "x"


def test_non_convergence_leaves_nothing(files, tmp_path, capsys, monkeypatch):
    """An unconverged fit exits with status 3 and writes nothing (unless --allow-unconverged)."""
    import twoscale.fit.driver as driver

    real_fit = driver.fit

    def one_step_fit(data, **kw):
        kw["schedule"] = [driver.Stage(4096, 1, 1)]  # one solver step: cannot converge
        return real_fit(data, **kw)

    monkeypatch.setattr(driver, "fit", one_step_fit)
    out = tmp_path / "out"
    rc = main([str(files["good"]), "--out", str(out), "--baseline", "ggx", "--quiet"])
    assert rc == EXIT_FIT
    _assert_one_line_error(capsys.readouterr().err, "did not converge")
    assert not out.exists() and list(tmp_path.iterdir()) == []
    rc = main(
        [
            str(files["good"]),
            "--out",
            str(out),
            "--baseline",
            "ggx",
            "--allow-unconverged",
            "--no-plots",
        ]
    )
    assert rc == 0
    assert load_result(out / "params.json").converged is False

"""``python -m twoscale.fit ... --render``: ``render.png`` (the fit rendered in Mitsuba 3 next to the
measured sphere), and the early exit (status 2, before fitting) without Mitsuba or libLLVM.

The rendering tests skip when Mitsuba or its LLVM backend is absent (as tests/test_mitsuba.py);
the early-exit tests simulate the missing pieces and run everywhere. The fit is replaced by a
stand-in returning a two-scale record of the ``--example`` material (a real fit takes a minute).
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import twoscale
from tests.helpers import two_scale_record
from twoscale import merl
from twoscale.fit.__main__ import EXIT_INPUT, main
from twoscale.fit.record import FitResult
from twoscale.fit.synthetic import EXAMPLE

REPO = Path(__file__).resolve().parents[1]
CONFIG = twoscale.ModelConfig(material="conductor", apparatus=True, diffuse_fresnel=False)
PARAMS = twoscale.TwoScaleParams.conductor(**EXAMPLE)


def _record() -> FitResult:
    return two_scale_record(PARAMS, CONFIG)


@pytest.fixture(scope="module")
def merl_file(tmp_path_factory):
    """A small constant MERL file (a grey Lambertian-like material, ρ = 0.05/sr)."""
    path = tmp_path_factory.mktemp("render") / "grey.binary"
    merl.write(path, np.full(merl.SHAPE + (3,), 0.05), np.ones(merl.SHAPE, bool))
    return path


@pytest.fixture
def fit_calls(monkeypatch):
    """Replace the fit by the stand-in; the list records each call."""
    import twoscale.fit.driver as driver

    calls = []

    def stand_in(data, **kwargs):
        calls.append(kwargs)
        return _record()

    monkeypatch.setattr(driver, "fit", stand_in)
    return calls


@pytest.fixture(scope="module")
def variant():
    import twoscale.mitsuba as tm

    tm._set_llvm_path()  # before Mitsuba is imported (Dr.Jit reads DRJIT_LIBLLVM_PATH)
    pytest.importorskip("mitsuba", reason="Mitsuba 3 not installed (pip install -e '.[mitsuba]')")
    try:
        return tm.register("llvm_ad_rgb")
    except RuntimeError as err:  # no libLLVM: the message names apt-get install libllvm19
        pytest.skip(str(err))


def _one_line_error(stderr: str, needle: str) -> None:
    lines = [ln for ln in stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, stderr
    assert lines[0].startswith("error: ") and needle in lines[0], stderr
    assert "Traceback" not in stderr


# ------------------------------------------------------------------------------ rendering
def test_render_png(variant, merl_file, fit_calls, tmp_path, capsys):
    import matplotlib.image as mpimg

    out = tmp_path / "out"
    rc = main([str(merl_file), "--out", str(out), "--render", "--no-plots", "--no-albedo"])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert len(fit_calls) == 1
    assert sorted(p.name for p in out.iterdir()) == ["params.json", "render.png"]
    assert "render written" in err and "warning" not in err, err
    img = mpimg.imread(out / "render.png")[..., :3].astype(np.float64)
    assert np.all(np.isfinite(img))
    # Two panels on a white figure: measured (left) and the Mitsuba render (right). Both show a
    # lit sphere: dark pixels (the unlit side, the black background of the panel) and bright ones.
    h, w = img.shape[:2]
    for half in (img[:, : w // 2], img[:, w // 2 :]):
        lum = half.mean(axis=-1)
        assert (lum < 0.05).mean() > 0.05, "no dark pixels: blank or wrongly exposed"
        assert ((lum > 0.2) & (lum < 0.99)).mean() > 0.01, "no lit pixels on the sphere"


def test_mitsuba_sphere_matches_the_direct_evaluation(variant):
    """The render's scene is the one of plots.sphere_directions: the Mitsuba image agrees with
    ρ cos θ_i evaluated directly (JAX) per pixel, apparatus factor off."""
    import jax.numpy as jnp

    from twoscale.plots import sphere_directions
    from twoscale.render import render_sphere

    cfg = dataclasses.replace(CONFIG, apparatus=False)
    size = 128
    img = render_sphere(PARAMS, cfg, size=size, spp=16)
    assert img.shape == (size, size, 3) and np.all(np.isfinite(img))
    wi, wo, mask = sphere_directions(size, 30.0)
    lit = mask & (wi[..., 2] > 0) & (wo[..., 2] > 0)
    p = PARAMS.for_config(cfg)
    direct = np.zeros((size, size, 3))
    rho = np.asarray(twoscale.brdf(p, jnp.asarray(wi[lit]), jnp.asarray(wo[lit]), cfg))
    direct[lit] = rho * wi[lit][:, 2:3]
    # Mean radiance per channel: measured 1.7 % apart (pixel centres differ by < 1 pixel).
    np.testing.assert_allclose(img.mean(axis=(0, 1)), direct.mean(axis=(0, 1)), rtol=0.05)
    # The highlight in the same place (the light at +x, i.e. to the right, as in the pictures).
    peak_m = np.unravel_index(img[..., 1].argmax(), (size, size))
    peak_d = np.unravel_index(direct[..., 1].argmax(), (size, size))
    assert np.abs(np.subtract(peak_m, peak_d)).max() <= 2, (peak_m, peak_d)
    assert peak_m[1] > size // 2 + 5  # right of the centre
    # Off the sphere (two pixels away from its outline; the grids differ by < 1 pixel): black.
    y, x = np.mgrid[1 : -1 : size * 1j, -1 : 1 : size * 1j]
    assert img[np.hypot(x, y) > 1.0 + 4.0 / size].max() == 0.0


def test_plugin_uses_the_records_albedo_table(variant, tmp_path):
    """A params.json with an ``"albedo_table"`` gives the plugin's eval_diffuse_reflectance (a
    stand-in table here, 0.25 + 0.5 cos θ_i, so that its use is visible); without one the
    plugin builds its own 64-row table of the material."""
    import drjit as dr
    import mitsuba as mi

    import twoscale.mitsuba as tm

    n = 256
    cos = (np.arange(n) + 1.0) / n
    res = _record()
    res.albedo_table = {
        "n": n,
        "cos_theta_i": "(i+1)/n",
        "apparatus": False,
        "channels": ["R", "G", "B"],
        "values": np.stack([0.25 + 0.5 * cos] * 3, axis=-1).tolist(),
    }
    with_table = tm.load(res.save(tmp_path / "with.json"))
    res.albedo_table = None
    without = tm.load(res.save(tmp_path / "without.json"))
    wi = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]], np.float32)
    si = dr.zeros(mi.SurfaceInteraction3f, 2)
    si.wi = mi.Vector3f(np.ascontiguousarray(wi.T))
    got = np.asarray(with_table.eval_diffuse_reflectance(si).numpy()).T
    np.testing.assert_allclose(got, [[0.75] * 3, [0.65] * 3], atol=1e-6)
    own = np.asarray(without.eval_diffuse_reflectance(si).numpy()).T
    material = dataclasses.replace(CONFIG, apparatus=False)
    ref = np.asarray(twoscale.albedo(PARAMS.for_config(material), np.array([1.0, 0.8]), material))
    np.testing.assert_allclose(own, ref, atol=2e-3)


# ------------------------------------------------------------------------------ early errors
def test_no_mitsuba_exits_2_before_fitting(merl_file, fit_calls, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "mitsuba", None)  # `import mitsuba` raises ImportError
    out = tmp_path / "out"
    rc = main([str(merl_file), "--out", str(out), "--render", "--quiet"])
    assert rc == EXIT_INPUT
    _one_line_error(capsys.readouterr().err, "--render needs Mitsuba 3")
    assert fit_calls == [], "the fit ran before the error"
    assert not out.exists()


def test_no_libllvm_exits_2_before_fitting(merl_file, fit_calls, tmp_path, capsys, monkeypatch):
    import twoscale.mitsuba as tm

    def no_llvm(variant=None):
        raise RuntimeError(f"{tm._LLVM_HELP} (ImportError: simulated)")

    monkeypatch.setattr(tm, "_import", no_llvm)
    out = tmp_path / "out"
    rc = main([str(merl_file), "--out", str(out), "--render", "--quiet"])
    assert rc == EXIT_INPUT
    _one_line_error(capsys.readouterr().err, "apt-get install libllvm19")
    assert fit_calls == [] and not out.exists()


def test_render_with_a_baseline_is_a_bad_option(merl_file, fit_calls, tmp_path, capsys):
    rc = main([str(merl_file), "--out", str(tmp_path / "o"), "--render", "--baseline", "ggx"])
    assert rc == EXIT_INPUT
    _one_line_error(capsys.readouterr().err, "--render renders the two-scale model")
    assert fit_calls == []


def test_no_mitsuba_subprocess(tmp_path):
    """The real CLI, with a ``mitsuba`` that cannot be imported first on the path: exit 2, one
    line, and no fitting started (no progress line)."""
    fake = tmp_path / "fake"
    fake.mkdir()
    for name in ("mitsuba", "drjit"):  # whichever the check imports first
        (fake / f"{name}.py").write_text("raise ImportError('simulated: no Mitsuba here')\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(fake), str(REPO)])}
    env.pop("TWOSCALE_DEBUG", None)
    proc = subprocess.run(
        [sys.executable, "-m", "twoscale.fit", "--example", "--render", "--out", "res"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == EXIT_INPUT, proc.stderr
    _one_line_error(proc.stderr, "--render needs Mitsuba 3")
    assert "simulated: no Mitsuba here" in proc.stderr
    assert proc.stdout == "" and not (tmp_path / "res").exists()

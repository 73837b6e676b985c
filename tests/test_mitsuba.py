"""The Mitsuba 3 plugin (twoscale.mitsuba): values, sampling (χ²) and a render against Mitsuba's own
Beckmann ``roughconductor``. Skips when Mitsuba or its LLVM backend (libLLVM) is absent."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

import twoscale
import twoscale.mitsuba as tm
from tests.helpers import two_scale_record

tm._set_llvm_path()  # before Mitsuba is imported (Dr.Jit reads DRJIT_LIBLLVM_PATH)
mi = pytest.importorskip("mitsuba", reason="Mitsuba 3 not installed (pip install -e '.[mitsuba]')")
dr = pytest.importorskip("drjit")

CONDUCTOR = (
    twoscale.TwoScaleParams.conductor(
        beta=0.3, p=0.8, eta=(0.2, 0.5, 1.4), k=(3.5, 2.5, 1.9), sigma_s=0.02, b=3.0, c=2.2
    ),
    twoscale.ModelConfig(),
)
PLASTIC = (
    twoscale.TwoScaleParams.plastic(
        beta=0.15, p=1.5, eta=1.5, rho_d=(0.5, 0.3, 0.2), sigma_s=0.01, b=2.0, c=2.0
    ),
    twoscale.ModelConfig(material="plastic"),
)
MATERIALS = {"conductor": CONDUCTOR, "plastic": PLASTIC}


@pytest.fixture(scope="module")
def variant():
    try:
        return tm.register("llvm_ad_rgb")
    except RuntimeError as err:  # no libLLVM: the message names apt-get install libllvm19
        pytest.skip(str(err))


def _dirs(rng, n, lower=0.1):
    """Unit directions, a fraction ``lower`` of them below the horizon."""
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2]) * np.where(rng.random(n) < lower, -1.0, 1.0)
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def _si(wi):
    wi = np.atleast_2d(np.asarray(wi, np.float32))
    si = dr.zeros(mi.SurfaceInteraction3f, wi.shape[0])
    si.wi = mi.Vector3f(np.ascontiguousarray(wi.T))
    return si


def _vec(a):
    return mi.Vector3f(np.ascontiguousarray(np.asarray(a, np.float32).T))


def _close(a, b, rtol=1e-4):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-30)) <= rtol


@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_eval_pdf_sample_match_twoscale(variant, name):
    params, cfg = MATERIALS[name]
    bsdf = tm.bsdf(params, cfg)
    rng = np.random.default_rng(1)
    n = 700
    wi, wo = _dirs(rng, n), _dirs(rng, n)
    ctx = mi.BSDFContext()
    si = _si(wi)
    value = bsdf.eval(ctx, si, _vec(wo)).numpy().T
    pdf = bsdf.pdf(ctx, si, _vec(wo)).numpy()
    v2, p2 = bsdf.eval_pdf(ctx, si, _vec(wo))
    p32 = params.for_config(cfg).astype(jnp.float32)
    ref = np.asarray(twoscale.brdf(p32, jnp.asarray(wi), jnp.asarray(wo), cfg))
    ref = ref * np.clip(wo[:, 2:3], 0.0, None) * ((wi[:, 2] > 0) & (wo[:, 2] > 0))[:, None]
    ref_pdf = np.asarray(twoscale.pdf(p32, jnp.asarray(wi), jnp.asarray(wo), cfg))
    assert value.dtype == np.float32 and value.shape == (n, 3)
    assert np.count_nonzero(value[:, 0]) > n // 2
    assert _close(value, ref) and _close(pdf, ref_pdf)
    assert np.array_equal(v2.numpy().T, value) and np.array_equal(p2.numpy(), pdf)

    # sample: pdf = twoscale.pdf at the drawn direction, weight = eval / pdf (cos θ_o included)
    u = rng.random((n, 3)).astype(np.float32)
    bs, weight = bsdf.sample(ctx, si, mi.Float(u[:, 0]), mi.Point2f(u[:, 1], u[:, 2]))
    wo_s, pdf_s, weight = bs.wo.numpy().T, bs.pdf.numpy(), weight.numpy().T
    ok = pdf_s > 0
    assert ok.sum() > n // 2 and np.all(weight[~ok] == 0)
    assert np.all((wi[:, 2] > 0) | ~ok)
    assert _close(
        pdf_s[ok], np.asarray(twoscale.pdf(p32, jnp.asarray(wi), jnp.asarray(wo_s), cfg))[ok]
    )
    value_s = bsdf.eval(ctx, si, _vec(wo_s)).numpy().T
    assert _close(weight[ok], value_s[ok] / pdf_s[ok, None], 1e-5)
    assert np.all(bs.sampled_type.numpy() == int(mi.BSDFFlags.GlossyReflection))


def test_horizon_empty_and_flags(variant):
    bsdf = tm.bsdf(*CONDUCTOR)
    ctx = mi.BSDFContext()
    assert bsdf.flags() == int(mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide)
    # empty wavefronts
    empty = dr.zeros(mi.SurfaceInteraction3f, 0)
    assert dr.width(bsdf.eval(ctx, empty, dr.zeros(mi.Vector3f, 0))) == 0
    assert dr.width(bsdf.pdf(ctx, empty, dr.zeros(mi.Vector3f, 0))) == 0
    bs, w = bsdf.sample(ctx, empty, dr.zeros(mi.Float, 0), dr.zeros(mi.Point2f, 0))
    assert dr.width(w) == 0
    # wi below the horizon (back side) or wo below it: everything 0
    si = _si([[0.3, 0.0, -0.954]] * 4)
    wo = _vec([[0.0, 0.0, 1.0]] * 4)
    assert np.all(bsdf.eval(ctx, si, wo).numpy() == 0) and np.all(
        bsdf.pdf(ctx, si, wo).numpy() == 0
    )
    bs, w = bsdf.sample(ctx, si, mi.Float([0.5] * 4), mi.Point2f([0.3] * 4, [0.6] * 4))
    assert np.all(w.numpy() == 0) and np.all(bs.pdf.numpy() == 0)
    si_up = _si([[0.0, 0.0, 1.0]] * 4)
    assert np.all(bsdf.eval(ctx, si_up, _vec([[0.6, 0.0, -0.8]] * 4)).numpy() == 0)
    # a width-1 wi against many wo (as Mitsuba's χ² adapter passes it), inactive lanes give 0
    si1 = dr.zeros(mi.SurfaceInteraction3f, 3)
    si1.wi = mi.Vector3f(0.0, 0.0, 1.0)
    act = mi.Bool([True, False, True])
    v = bsdf.eval(ctx, si1, _vec([[0.0, 0.0, 1.0]] * 3), act).numpy()
    assert v.shape == (3, 3) and np.all(v[:, 1] == 0) and np.all(v[:, [0, 2]] > 0)
    # the denoiser's albedo: the directional albedo (0 on the back side)
    alb = bsdf.eval_diffuse_reflectance(_si([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])).numpy()
    p32 = CONDUCTOR[0].for_config(CONDUCTOR[1]).astype(jnp.float32)
    ref = np.asarray(twoscale.albedo(p32, jnp.float32(1.0), CONDUCTOR[1]))
    assert np.allclose(alb[:, 0], ref, rtol=0.02) and np.all(alb[:, 1] == 0)


def test_params_json_scene_dict(variant, tmp_path):
    """``{"type": "twoscale", "filename": ...}`` reads a fit record, apparatus factor off."""
    params, cfg = CONDUCTOR
    cfg_fit = dataclasses.replace(cfg, apparatus=True)
    res = two_scale_record(params.replace(e=0.8), cfg_fit, n_valid=0, n_fit=0, status="test record")
    path = res.save(tmp_path / "params.json")
    from_file = mi.load_dict({"type": "twoscale", "filename": str(path)})
    direct = tm.bsdf(params, cfg)
    with_apparatus = tm.load(path, apparatus=True)
    assert "apparatus=False" in str(from_file) and "apparatus=True" in str(with_apparatus)
    rng = np.random.default_rng(2)
    wi, wo = _dirs(rng, 64, 0.0), _dirs(rng, 64, 0.0)
    ctx = mi.BSDFContext()
    a = from_file.eval(ctx, _si(wi), _vec(wo)).numpy()
    b = direct.eval(ctx, _si(wi), _vec(wo)).numpy()
    c = with_apparatus.eval(ctx, _si(wi), _vec(wo)).numpy()
    assert np.allclose(a, b, rtol=1e-6, atol=0) and not np.allclose(a, c, rtol=1e-3)
    with pytest.raises(RuntimeError, match="give 'filename'"):
        mi.load_dict({"type": "twoscale"})


def _chi2_functors(bsdf, wi):
    ctx = mi.BSDFContext()

    def si_of(n):
        si = dr.zeros(mi.SurfaceInteraction3f, n)
        si.wi = mi.Vector3f(wi)
        return si

    def sample_func(s):  # as mitsuba.chi2.BSDFAdapter, with an already built BSDF
        n = dr.width(s)
        bs, weight = bsdf.sample(ctx, si_of(n), s[0], mi.Point2f(s[1], s[2]))
        w = dr.full(mi.Float, 1.0, n)
        w[dr.all(weight == 0)] = 0
        return bs.wo, w

    def pdf_func(wo):
        return bsdf.pdf(ctx, si_of(dr.width(wo)), wo)

    return sample_func, pdf_func


@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_chi2(variant, name):
    from mitsuba.chi2 import ChiSquareTest, SphericalDomain

    theta = np.radians(50.0)
    wi = [float(np.sin(theta)), 0.0, float(np.cos(theta))]
    sample_func, pdf_func = _chi2_functors(tm.bsdf(*MATERIALS[name]), wi)
    chi2 = ChiSquareTest(
        domain=SphericalDomain(),
        sample_func=sample_func,
        pdf_func=pdf_func,
        sample_dim=3,
        sample_count=100_000,
        res=61,
        ires=4,
    )
    assert chi2.run(), chi2.messages


def _sphere_scene(bsdf, spp):
    look = mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0])
    return mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": 2},
            "sensor": {
                "type": "perspective",
                "fov": 30,
                "to_world": look,
                "film": {"type": "hdrfilm", "width": 32, "height": 32, "rfilter": {"type": "box"}},
                "sampler": {"type": "independent", "sample_count": spp},
            },
            "emitter": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
            "sphere": {"type": "sphere", "bsdf": bsdf},
        }
    )


def _sphere_mask(n=32, fov=30.0, distance=4.0, radius=0.95):
    """Pixels whose centre ray passes within ``radius`` of the unit sphere's centre."""
    f = np.tan(np.radians(fov) / 2)
    x = ((np.arange(n) + 0.5) / n * 2 - 1) * f
    xx, yy = np.meshgrid(x, -x)
    d = np.stack([xx, yy, -np.ones_like(xx)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = np.array([0.0, 0.0, distance])
    t = -(d @ o)
    return np.linalg.norm(o + t[..., None] * d, axis=-1) < radius


def test_render_matches_roughconductor(variant):
    """The Beckmann special case (p = 1, no diffraction, uncorrelated Smith) against Mitsuba's
    ``roughconductor`` (Beckmann, α = β, same η, k, NDF sampling): sphere pixels within 1 %."""
    beta, eta, k = 0.3, (0.2, 0.5, 1.4), (3.5, 2.5, 1.9)
    params = twoscale.TwoScaleParams.conductor(beta=beta, p=1.0, eta=eta, k=k)
    cfg = twoscale.ModelConfig(diffraction=False, shadowing="uncorrelated")
    reference = {
        "type": "roughconductor",
        "distribution": "beckmann",
        "alpha": beta,
        "sample_visible": False,
        "eta": {"type": "rgb", "value": list(eta)},
        "k": {"type": "rgb", "value": list(k)},
    }
    img = np.asarray(mi.render(_sphere_scene(tm.bsdf(params, cfg), 16)))
    ref = np.asarray(mi.render(_sphere_scene(reference, 16)))
    assert img.shape == (32, 32, 3) and np.all(np.isfinite(img))
    mask = _sphere_mask()
    assert mask.sum() > 500
    rel = img[mask].mean(axis=0) / ref[mask].mean(axis=0) - 1.0
    assert np.all(np.abs(rel) < 0.01), rel
    assert abs(img.mean() / ref.mean() - 1.0) < 0.01

"""Colour: metal presets against their sources, RGB upsampling, spectrum → sRGB against colour-science."""

import json

import colour
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twoscale import fresnel, spectral
from twoscale.tables import DATA_DIR

CMFS = colour.MSDS_CMFS[spectral.CMFS_NAME]
RII = "ior_refractiveindex_info"


def _packaged():
    with np.load(DATA_DIR / spectral.PRESETS_FILE, allow_pickle=False) as f:
        return np.array(f["wavelengths"]), np.array(f["eta"]), np.array(f["k"]), str(f["meta"])


# --------------------------------------------------------------------------------------------------
# wavelengths


def test_spectral_wavelengths_are_bin_centres():
    np.testing.assert_allclose(
        spectral.spectral_wavelengths(4), [0.43, 0.53, 0.63, 0.73], rtol=1e-15
    )
    w = spectral.spectral_wavelengths(30, 0.4, 0.7)
    np.testing.assert_allclose(np.diff(w), 0.01, rtol=1e-12)
    assert w[0] == pytest.approx(0.405) and w[-1] == pytest.approx(0.695)
    with pytest.raises(ValueError):
        spectral.spectral_wavelengths(0)
    with pytest.raises(ValueError):
        spectral.spectral_wavelengths(3, 0.7, 0.4)


# --------------------------------------------------------------------------------------------------
# presets


def test_presets_physically_plausible():
    w = spectral.spectral_wavelengths(40)
    for name in spectral.PRESETS:
        eta, k = spectral.preset(name, w)
        assert eta.shape == k.shape == w.shape
        assert np.all(eta > 0.0) and np.all(k > 1.5), name  # metals: k well above n's scale
    # Johnson & Christy gold: n ≈ 1.38, k ≈ 1.91 at 451 nm; silver k ≈ 3.6 at 549 nm, n ≈ 0.05.
    eta, k = spectral.preset("gold", 0.45)
    assert 1.35 < eta < 1.5 and 1.85 < k < 2.0
    eta, k = spectral.preset("silver", 0.55)
    assert 3.0 < k < 4.0 and eta < 0.1
    eta, k = spectral.preset("aluminium", spectral.spectral_wavelengths(20))
    assert np.all(k > 4.0) and np.all(eta < 2.5)
    # Colour of the noble metals: n falls steeply from blue to red (absorption edge near 500-600 nm).
    for name in ("gold", "copper", "brass"):
        eta, _ = spectral.preset_rgb(name)
        assert eta[0] < 0.5 * eta[2], name


@pytest.mark.parametrize(
    "name,n,k",
    # At 550 nm, quoted in the shared data README (computed with the `refractiveindex` package).
    [
        ("Ni", 1.921, 3.616),
        ("Au", 0.424, 2.472),
        ("Cu", 1.007, 2.582),
        ("Ag", 0.060, 3.597),
        ("Cr", 3.181, 3.329),
    ],
)
def test_presets_match_quoted_values(name, n, k):
    eta, kk = spectral.preset(name, 0.55)
    # 5e-3: that package interpolates the coarse Johnson & Christy table linearly, we use PCHIP.
    assert eta == pytest.approx(n, abs=5e-3) and kk == pytest.approx(k, abs=5e-3)


def test_preset_exact_at_nodes_and_linear_between():
    w, eta, k, _ = _packaged()
    for i, name in enumerate(spectral.PRESETS):
        e, kk = spectral.preset(name, w)
        np.testing.assert_array_equal(e, eta[i])
        np.testing.assert_array_equal(kk, k[i])
        mid = 0.5 * (w[1:] + w[:-1])
        e, kk = spectral.preset(name, mid)
        np.testing.assert_allclose(e, 0.5 * (eta[i, 1:] + eta[i, :-1]), rtol=1e-13)
        np.testing.assert_allclose(kk, 0.5 * (k[i, 1:] + k[i, :-1]), rtol=1e-13)


def test_preset_names_aliases_and_errors():
    for alias, name in [
        ("Au", "gold"),
        ("GOLD", "gold"),
        ("aluminum", "aluminium"),
        ("Al", "aluminium"),
        ("Ni", "nickel"),
        ("Ag", "silver"),
        ("Cu", "copper"),
        ("Cr", "chromium"),
    ]:
        np.testing.assert_array_equal(spectral.preset(alias, 0.5), spectral.preset(name, 0.5))
    with pytest.raises(
        ValueError, match="nickel, aluminium, gold, silver, copper, chromium, brass"
    ):
        spectral.preset("unobtainium", 0.5)
    with pytest.raises(ValueError, match="wavelengths"):
        spectral.preset("gold", [0.5, 0.9])  # beyond the stored 360-830 nm


def test_preset_rgb_shape_and_order():
    eta, k = spectral.preset_rgb("copper")
    assert eta.shape == k.shape == (3,)
    for c, lam in enumerate(spectral.RGB_WAVELENGTHS):
        assert (eta[c], k[c]) == spectral.preset("copper", lam)


def test_preset_metadata_records_provenance():
    w, _, _, raw = _packaged()
    meta = json.loads(raw)
    assert meta["names"] == list(spectral.PRESETS)
    assert meta["grid_nm"] == {"first": 360, "last": 830, "step": 5}
    np.testing.assert_allclose(w, np.arange(360, 835, 5) / 1000, rtol=1e-15)
    assert "Pchip" in meta["resampling"]
    gold = spectral.preset_metadata("Au")
    assert gold["source"] == "data/main/Au/nk/Johnson.yml"
    assert "Johnson" in gold["references"] and "10.1103/PhysRevB.6.4370" in gold["references"]
    assert len(gold["sha256"]) == 64


def test_presets_against_source_yaml(shared_data):
    """Read each source page with PyYAML (independent of our parser) and compare at its own nodes."""
    yaml = pytest.importorskip("yaml")
    root = shared_data / RII
    for name in spectral.PRESETS:
        page = spectral.preset_metadata(name)["source"]
        doc = yaml.safe_load((root / page).read_text(encoding="utf-8"))
        rows = np.array(doc["DATA"][0]["data"].split(), dtype=float).reshape(-1, 3)
        rows = rows[(rows[:, 0] >= 0.36) & (rows[:, 0] <= 0.83)]
        assert len(rows) >= 15, name
        eta, k = spectral.preset(name, rows[:, 0])
        # Linear between 5 nm nodes of a PCHIP through the source: ≤ 0.6 % (silver's n ≈ 0.05).
        np.testing.assert_allclose(eta, rows[:, 1], rtol=1e-2, err_msg=name)
        np.testing.assert_allclose(k, rows[:, 2], rtol=2e-3, err_msg=name)


def test_packaged_table_is_up_to_date(shared_data):
    build = pytest.importorskip("tablegen.build_spectral_presets")
    w, eta, k, meta = build.build(shared_data / RII)
    w0, eta0, k0, raw = _packaged()
    np.testing.assert_array_equal(w, w0)
    np.testing.assert_allclose(eta, eta0, rtol=1e-14)
    np.testing.assert_allclose(k, k0, rtol=1e-14)
    assert meta == json.loads(raw)


# --------------------------------------------------------------------------------------------------
# refractiveindex.info reader


def test_reader_agrees_with_pyyaml_on_every_page(shared_data):
    yaml = pytest.importorskip("yaml")
    pages = sorted((shared_data / RII / "data").rglob("*.yml"))
    assert len(pages) > 50
    for page in pages:
        text = page.read_text(encoding="utf-8")
        ours, ref = spectral._parse_mapping(text.splitlines()), yaml.safe_load(text)
        for key in ("REFERENCES", "COMMENTS"):
            assert (ours.get(key) or "").strip() == (ref.get(key) or "").strip(), (page, key)
        assert [d["type"] for d in ours["DATA"]] == [d["type"] for d in ref["DATA"]], page
        for a, b in zip(ours["DATA"], ref["DATA"], strict=True):
            if "data" in b:
                np.testing.assert_array_equal(
                    np.array(a["data"].split(), float), np.array(b["data"].split(), float)
                )


def test_load_nk_yaml(tmp_path):
    page = tmp_path / "metal.yml"
    page.write_text(
        "# comment\nREFERENCES: |\n    A. Author.\n    Journal 1 (2000)\nDATA:\n"
        "  - type: tabulated nk\n    data: |\n        0.40 1.0 2.0\n        0.50 2.0 3.0\n"
        "        0.60 3.0 4.0\n"
    )
    data = spectral.read_nk_yaml(page)
    assert data.references == "A. Author.\nJournal 1 (2000)"
    n, k = spectral.load_nk_yaml(page, [0.4, 0.45, 0.6])
    np.testing.assert_allclose(n, [1.0, 1.5, 3.0], rtol=1e-14)  # PCHIP of linear data is linear
    np.testing.assert_allclose(k, [2.0, 2.5, 4.0], rtol=1e-14)
    with pytest.raises(ValueError, match="outside"):
        spectral.load_nk_yaml(page, [0.3])

    dielectric = tmp_path / "glass.yml"
    dielectric.write_text(
        "REFERENCES: x\nDATA:\n  - type: tabulated n\n    data: |\n        0.4 1.5\n        0.6 1.4\n"
        "  - type: tabulated k\n    data: |\n        0.4 1e-7\n        0.6 2e-7\n"
    )
    n, k = spectral.load_nk_yaml(dielectric, 0.5)
    assert n == pytest.approx(1.45) and k == pytest.approx(1.5e-7)

    formula = tmp_path / "sellmeier.yml"
    formula.write_text(
        "DATA:\n  - type: formula 1\n    wavelength_range: 0.2 7.0\n    coefficients: 0 1 0.1\n"
    )
    with pytest.raises(ValueError, match="formula"):
        spectral.read_nk_yaml(formula)


# --------------------------------------------------------------------------------------------------
# RGB → spectrum


def test_upsample_exact_at_rgb_wavelengths():
    rgb = jnp.array([[0.2, 0.9, 1.4], [3.5, 2.1, 1.9]])
    np.testing.assert_array_equal(spectral.upsample_rgb(rgb, spectral.RGB_WAVELENGTHS), rgb)
    w = np.sort(np.concatenate([spectral.spectral_wavelengths(30), spectral.RGB_WAVELENGTHS]))
    spec = spectral.upsample_rgb(rgb, w)
    for c, lam in enumerate(spectral.RGB_WAVELENGTHS):
        np.testing.assert_array_equal(spec[:, np.flatnonzero(w == lam)[0]], rgb[:, c])


def test_upsample_shape_of_the_spectrum():
    r, g, b = 0.3, 1.2, 0.7
    lam_r, lam_g, lam_b = spectral.RGB_WAVELENGTHS
    w = np.array([0.38, lam_b, 0.5 * (lam_b + lam_g), 0.6, 0.78])
    spec = np.asarray(spectral.upsample_rgb(jnp.array([r, g, b]), w))
    t = (0.6 - lam_g) / (lam_r - lam_g)
    np.testing.assert_allclose(spec, [b, b, 0.5 * (b + g), g + t * (r - g), r], rtol=1e-14)
    grey = spectral.upsample_rgb(jnp.full(3, 0.37), spectral.spectral_wavelengths(30))
    np.testing.assert_allclose(grey, 0.37, rtol=1e-15)


def test_upsample_is_linear_and_differentiable():
    w = spectral.spectral_wavelengths(16)
    rgb = jnp.array([0.5, 1.0, 2.0])
    jac = jax.jacobian(lambda v: spectral.upsample_rgb(v, w))(rgb)
    lam_r, lam_g, lam_b = spectral.RGB_WAVELENGTHS
    expected = np.stack(  # hat functions on the ascending nodes, flat beyond: channels R, G, B
        [np.interp(w, [lam_b, lam_g, lam_r], e) for e in ([0, 0, 1], [0, 1, 0], [1, 0, 0])], axis=1
    )
    np.testing.assert_allclose(jac, expected, rtol=1e-15)
    # Traced wavelengths are fine too (a fit may build them inside jit).
    traced = jax.jit(lambda v, lam: spectral.upsample_rgb(v, lam))(rgb, jnp.asarray(w))
    np.testing.assert_allclose(traced, spectral.upsample_rgb(rgb, w), rtol=1e-15)
    f = jax.jit(lambda v: spectral.spectrum_to_rgb(spectral.upsample_rgb(v, w), w))
    np.testing.assert_allclose(
        f(rgb), spectral.spectrum_to_rgb(spectral.upsample_rgb(rgb, w), w), rtol=1e-14
    )


# --------------------------------------------------------------------------------------------------
# spectrum → RGB


@pytest.mark.parametrize("illuminant", ["D65", "E"])
@pytest.mark.parametrize("n", [1, 3, 10, 30, 95])
def test_constant_spectrum_is_white(illuminant, n):
    w = spectral.spectral_wavelengths(n)
    m = spectral.rgb_matrix(w, illuminant)
    assert m.shape == (n, 3)
    np.testing.assert_allclose(m.sum(axis=0), 1.0, rtol=1e-13)  # the columns (sum over rows) are 1
    np.testing.assert_allclose(
        spectral.spectrum_to_rgb(jnp.full(n, 0.25), w, illuminant), 0.25, rtol=1e-13
    )


def test_luminance_of_each_bin():
    """Y = sRGB luminance row · rgb recovers the bin integrals of ȳ·S/∫ȳS (independent quadrature).

    D65 only: under another illuminant the CAT to D65 mixes X, Y, Z, so Y is not kept per bin.
    """
    illuminant = "D65"
    w = spectral.spectral_wavelengths(12)
    m = spectral.rgb_matrix(w, illuminant)
    # The exact inverse: colour's matrix_RGB_to_XYZ is rounded to 4 decimals on its own.
    y_row = np.linalg.inv(colour.RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB)[1]
    s = colour.SDS_ILLUMINANTS[illuminant].copy().align(CMFS.shape)
    ys = CMFS.values[:, 1] * s.values

    def integral(a, b):  # trapezoid on 4000 sub-intervals of ȳS interpolated linearly (nm)
        lam = np.linspace(a, b, 4001)
        return np.trapezoid(np.interp(lam, CMFS.wavelengths, ys), lam)

    edges = np.concatenate([[360], 500 * (w[1:] + w[:-1]), [830]])
    expected = np.array([integral(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True)])
    expected /= integral(360, 830)
    # Only the final white-point correction (≤ 1e-4 per channel) separates the two; in the blue bins
    # Y is a difference of much larger R, G, B terms (×40 at 380-413 nm), hence the scale.
    scale = np.abs(m) @ np.abs(y_row)
    np.testing.assert_array_less(np.abs(m @ y_row - expected), 2e-4 * scale)
    assert np.all(m @ y_row > 0.0)


@pytest.mark.parametrize(
    "illuminant,n,tol",
    # Worst patch over the 24: 2.3e-2 (D65) and 1.9e-2 (E) at N = 10; 1.6e-3 and 1.8e-3 at N = 30.
    [("D65", 10, 3e-2), ("D65", 30, 3e-3), ("E", 10, 3e-2), ("E", 30, 3e-3)],
)
def test_colorchecker_against_colour_science(illuminant, n, tol):
    """Point samples of each ColorChecker reflectance at N bin centres vs colour's own pipeline.

    Reference: the reflectance aligned to the 1 nm CMFs (colour's interpolation, flat extension),
    ``sd_to_XYZ(..., method="Integration")`` / 100, then ``XYZ_to_RGB`` to linear sRGB (no CCTF; CAT02 from
    E's white for "E"). The difference is the point sampling of the spectrum over 40 nm (N = 10) or
    13 nm (N = 30) bins, second order in the bin width: about ×9 smaller at N = 30.
    """
    w = spectral.spectral_wavelengths(n)
    illum = colour.SDS_ILLUMINANTS[illuminant].copy().align(CMFS.shape)  # colour warns if it must
    kwargs = (
        {}
        if illuminant == "D65"
        else {
            "illuminant": colour.CCS_ILLUMINANTS[spectral.CMFS_NAME]["E"],
            "chromatic_adaptation_transform": "CAT02",
        }
    )
    patches = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    values = np.array([sd[w * 1000] for sd in patches.values()])
    ours = np.asarray(spectral.spectrum_to_rgb(values, w, illuminant))
    xyz = [
        colour.sd_to_XYZ(sd.copy().align(CMFS.shape), CMFS, illum, method="Integration") / 100
        for sd in patches.values()
    ]
    ref = colour.XYZ_to_RGB(np.array(xyz), "sRGB", apply_cctf_encoding=False, **kwargs)
    assert np.abs(ours - ref).max() < tol


def test_metal_colours():
    """Normal-incidence Fresnel of the spectral presets: gold and copper are warm, silver near neutral."""
    w = spectral.spectral_wavelengths(30)
    rgb = {}
    for name in ("gold", "copper", "silver", "aluminium"):
        eta, k = spectral.preset(name, w)
        rgb[name] = np.asarray(spectral.spectrum_to_rgb(fresnel.conductor(1.0, eta, k), w))
    for name in ("gold", "copper"):
        r, g, b = rgb[name]
        assert r > g > b and b < 0.6 * r, (name, rgb[name])
    for name in ("silver", "aluminium"):
        assert np.ptp(rgb[name]) < 0.1 and rgb[name].min() > 0.85, (name, rgb[name])


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_dtype_preserved(dtype):
    w = spectral.spectral_wavelengths(10)
    spec = spectral.upsample_rgb(jnp.ones((4, 3), dtype), w)
    assert spec.dtype == dtype and spec.shape == (4, 10)
    rgb = spectral.spectrum_to_rgb(spec, w)
    assert rgb.dtype == dtype and rgb.shape == (4, 3)
    np.testing.assert_allclose(rgb, 1.0, rtol=10 * jnp.finfo(dtype).eps)
    assert jnp.issubdtype(spectral.spectrum_to_rgb(np.ones(10, int), w).dtype, jnp.floating)


def test_rgb_matrix_cached_read_only_and_validated():
    w = spectral.spectral_wavelengths(10)
    m = spectral.rgb_matrix(w)
    assert spectral.rgb_matrix(tuple(w), "D65") is m
    assert not m.flags.writeable
    with pytest.raises(ValueError, match="increasing"):
        spectral.rgb_matrix(w[::-1])
    with pytest.raises(ValueError, match="illuminant"):
        spectral.rgb_matrix(w, "nope")
    with pytest.raises(ValueError, match="samples"):
        spectral.spectrum_to_rgb(jnp.ones(9), w)
    with pytest.raises(ValueError, match="last axis"):
        spectral.upsample_rgb(jnp.ones(4), w)
    with pytest.raises(TypeError, match="concrete"):
        jax.jit(lambda v, lam: spectral.spectrum_to_rgb(v, lam))(jnp.ones(10), jnp.asarray(w))

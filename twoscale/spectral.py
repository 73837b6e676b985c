"""Colour: RGB wavelengths, spectral η(λ), k(λ) of metals, RGB upsampling, spectrum → linear sRGB [HP17 §3.10].

The model is evaluated per channel; a *channel* is a wavelength λ (µm). RGB mode uses the three
wavelengths :data:`RGB_WAVELENGTHS`; spectral mode uses N wavelengths (:func:`spectral_wavelengths`)
with spectral η(λ), k(λ) (:func:`preset`, :func:`load_nk_yaml`, or :func:`upsample_rgb` of RGB values)
and integrates the N values to linear sRGB with the CIE 1931 2° observer (:func:`spectrum_to_rgb`).

Conventions:

- Wavelengths are in **µm** everywhere, 1-D, strictly increasing where a spectrum is integrated.
  They are configuration, not data: :func:`rgb_matrix` and :func:`spectrum_to_rgb` need concrete
  values (a tuple or NumPy array) and cache their weights per wavelength tuple, so they may be called
  at trace time under ``jit``; :func:`upsample_rgb` is pure ``jnp`` and also takes traced ones.
- Spectra are arrays whose **last axis** is the wavelength axis; RGB triples are ordered (R, G, B) like
  :data:`RGB_WAVELENGTHS`.
- :func:`upsample_rgb` and :func:`spectrum_to_rgb` are fixed linear maps applied with ``jnp`` (a matmul
  over the last axis): jittable, differentiable, and they keep a floating input dtype.

Spectrum → RGB (:func:`rgb_matrix`). The spectrum is taken as piecewise constant on *bins* around its
samples: bin edges are the midpoints between neighbouring wavelengths, and the first and last bins run
out to the ends of the CMF table (360 nm, 830 nm), i.e. the spectrum is extended flat beyond its range,
as colour-science does when it aligns a spectral distribution to the CMFs. Each bin gets the exact
integral of x̄ȳz̄(λ)·S(λ) (CMFs at 1 nm, illuminant S aligned to them by colour-science, both taken as
piecewise linear), divided by ∫ȳS (so the white's Y is 1). XYZ → linear sRGB uses
``colour.RGB_COLOURSPACES['sRGB'].matrix_XYZ_to_RGB``. Under ``"D65"`` (sRGB's own white) nothing is
adapted; under any other illuminant (``"E"``, ``"A"``, ...) the illuminant's white is first adapted to
the sRGB D65 white with CAT02 (colour-science's default transform), so a perfect white reflector stays
white: the result is *white-balanced*. Finally each RGB column is divided by its sum, so a constant
spectrum of 1 maps to exactly (1, 1, 1); this corrects only the ~1e-4 mismatch between the integrated
illuminant white and the rounded sRGB white point (0.3127, 0.3290). With bin centres on 380–780 nm,
the result agrees with colour-science's ``sd_to_XYZ`` + ``XYZ_to_RGB`` (no CCTF) for the ColorChecker
reflectances to about 2e-3 with N = 30 samples and 3e-2 with N = 10 (the error is the point sampling of
the spectrum, second order in the bin width; see ``tests/test_spectral.py``).

RGB → spectrum (:func:`upsample_rgb`): piecewise-linear interpolation in λ through the three values
at λ_B < λ_G < λ_R, flat beyond λ_B and λ_R. It reproduces the three values exactly at
:data:`RGB_WAVELENGTHS`, never leaves the range of the three values (η, k stay positive, ρ_d stays in
[0, 1]; a natural cubic through three points can overshoot), and maps a constant triple to a constant
spectrum, so grey stays exactly grey through :func:`spectrum_to_rgb`.

Presets (:func:`preset`): n, k of seven metals from the refractiveindex.info database (CC0), resampled
by ``tablegen/build_spectral_presets.py`` onto 360–830 nm every 5 nm and stored in
``twoscale/data/spectral_presets.npz`` together with the source pages, their reference strings and
the resampling method (``preset_metadata()``). Between the stored nodes values are interpolated
linearly in λ (exact at the nodes).

References:
    [HP17] N. Holzschuch, R. Pacanowski, "A Two-Scale Microfacet Reflectance Model Combining Reflection
        and Diffraction", ACM TOG 36(4) 66, 2017 (docs/model.md §3.10).
    [CIE] CIE 015:2018 Colorimetry; CIE 1931 2° standard observer and D65 as tabulated by colour-science.
    [sRGB] IEC 61966-2-1:1999 (linear sRGB primaries, D65 white).
    [RII] M. N. Polyanskiy, "Refractiveindex.info database of optical constants", Sci. Data 11, 94 (2024).
"""

from __future__ import annotations

import functools
import json
import re
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from twoscale.tables import DATA_DIR

__all__ = [
    "RGB_WAVELENGTHS",
    "PRESETS",
    "NkData",
    "spectral_wavelengths",
    "preset",
    "preset_rgb",
    "preset_metadata",
    "read_nk_yaml",
    "load_nk_yaml",
    "upsample_rgb",
    "rgb_matrix",
    "spectrum_to_rgb",
]

RGB_WAVELENGTHS = (0.645, 0.526, 0.444)
"""(λ_R, λ_G, λ_B) in µm [docs/model.md §1]."""

PRESETS = ("nickel", "aluminium", "gold", "silver", "copper", "chromium", "brass")
"""Names of the packaged metal presets (see :func:`preset` for aliases)."""

_ALIASES = {
    "ni": "nickel",
    "al": "aluminium",
    "aluminum": "aluminium",
    "au": "gold",
    "ag": "silver",
    "cu": "copper",
    "cr": "chromium",
    "chrome": "chromium",
    "cuzn": "brass",
    "cu-zn": "brass",
}

PRESETS_FILE = "spectral_presets.npz"

CMFS_NAME = "CIE 1931 2 Degree Standard Observer"


# --------------------------------------------------------------------------------------------------
# Wavelength grids


def spectral_wavelengths(n: int, lo: float = 0.38, hi: float = 0.78) -> np.ndarray:
    """Return the centres of ``n`` equal bins covering ``[lo, hi]`` µm: ``lo + (i + ½)(hi − lo)/n``."""
    n = int(n)
    if n < 1:
        raise ValueError(f"need at least one wavelength, got n={n}")
    if not (0.0 < lo < hi):
        raise ValueError(f"need 0 < lo < hi (µm), got lo={lo}, hi={hi}")
    return lo + (np.arange(n) + 0.5) * ((hi - lo) / n)


def _wavelength_key(wavelengths) -> tuple[float, ...]:
    """Validate concrete, 1-D, finite, strictly increasing wavelengths (µm); return a hashable key."""
    if isinstance(wavelengths, jax.core.Tracer):
        raise TypeError(
            "wavelengths must be concrete (a tuple or NumPy array, e.g. from the configuration), "
            "not a traced array"
        )
    w = np.asarray(wavelengths, dtype=np.float64)
    if w.ndim != 1 or w.size == 0:
        raise ValueError(f"wavelengths must be a non-empty 1-D sequence (µm), got shape {w.shape}")
    if not np.all(np.isfinite(w)) or np.any(w <= 0.0):
        raise ValueError(f"wavelengths must be finite and positive (µm), got {w}")
    if np.any(np.diff(w) <= 0.0):
        raise ValueError(f"wavelengths must be strictly increasing, got {w}")
    return tuple(float(x) for x in w)


# --------------------------------------------------------------------------------------------------
# refractiveindex.info YAML files


@dataclass(frozen=True)
class NkData:
    """Tabulated complex index from one refractiveindex.info page: λ (µm), n, k, and its citation."""

    wavelengths: np.ndarray
    n: np.ndarray
    k: np.ndarray
    references: str
    comments: str

    def __call__(self, wavelengths) -> tuple[np.ndarray, np.ndarray]:
        """Interpolate ``(n, k)`` at ``wavelengths`` (µm) with a PCHIP (monotone C¹ cubic) in λ.

        PCHIP passes through every tabulated point and does not overshoot between them (n, k stay
        positive even across the coarse Johnson & Christy tables). No extrapolation: wavelengths
        outside the tabulated range raise ``ValueError``.
        """
        from scipy.interpolate import PchipInterpolator

        w = np.asarray(wavelengths, dtype=np.float64)
        lo, hi = self.wavelengths[0], self.wavelengths[-1]
        if np.any(w < lo) or np.any(w > hi):
            raise ValueError(
                f"wavelengths {w.min()}–{w.max()} µm outside the data range {lo}–{hi} µm"
            )
        n = PchipInterpolator(self.wavelengths, self.n)(w)
        k = PchipInterpolator(self.wavelengths, self.k)(w)
        return n, k


_KEY = re.compile(r"^(\s*)(- )?([A-Za-z_][\w ]*):\s*(.*?)\s*$")


def _block(lines: list[str], i: int, indent: int) -> tuple[list[str], int]:
    """Collect the lines after ``i`` that are blank or indented deeper than ``indent``."""
    out = []
    j = i + 1
    while j < len(lines) and (
        not lines[j].strip() or len(lines[j]) - len(lines[j].lstrip()) > indent
    ):
        out.append(lines[j])
        j += 1
    while out and not out[-1].strip():
        out.pop()
    return out, j


def _dedent(lines: list[str]) -> str:
    """Block-scalar text: the lines with their common indentation removed."""
    pad = min((len(s) - len(s.lstrip()) for s in lines if s.strip()), default=0)
    return "\n".join(s[pad:] for s in lines)


def _parse_mapping(lines: list[str]) -> dict:
    """Parse the YAML subset of refractiveindex.info pages.

    Supported: ``key: scalar``, ``key: |`` block scalars, nested mappings, and sequences of mappings
    (``- key: value`` items, as under ``DATA``). Comment lines (``#``) are skipped. This is not a
    general YAML parser; it exists so that reading a page needs no dependency.
    """
    lines = [s.rstrip() for s in lines if not s.lstrip().startswith("#")]
    out: dict = {}
    i = 0
    while i < len(lines):
        line = lines[i]
        if not line.strip():
            i += 1
            continue
        m = _KEY.match(line)
        if m is None:
            raise ValueError(f"cannot parse line {line!r}")
        indent, key, value = len(m.group(1)), m.group(3), m.group(4)
        if m.group(2):  # a sequence of mappings: gather every item at this indentation
            items = []
            while i < len(lines) and _KEY.match(lines[i]) and lines[i][indent:].startswith("- "):
                block, j = _block(lines, i, indent + 1)
                first = " " * (indent + 2) + lines[i][indent + 2 :]
                items.append(_parse_mapping([first, *block]))
                i = j
                while i < len(lines) and not lines[i].strip():
                    i += 1
            return {"__items__": items}
        block, j = _block(lines, i, indent)
        if value in ("|", "|-", ">", ">-"):
            text = _dedent(block)
            out[key] = text if value.startswith("|") else " ".join(text.split())
        elif value:
            out[key] = value.strip("'\"")
        else:
            nested = _parse_mapping(block)
            out[key] = nested.get("__items__", nested)
        i = j
    return out


def read_nk_yaml(path) -> NkData:
    """Read a refractiveindex.info page (``data/<shelf>/<book>/nk/<page>.yml``) with tabulated data.

    Accepts ``tabulated nk`` blocks (rows ``λ_µm n k``), or ``tabulated n`` with an optional
    ``tabulated k`` on the same wavelengths (k = 0 if absent). Formula (dispersion-equation) pages
    raise ``ValueError``. No YAML library is needed.
    """
    path = Path(path)
    doc = _parse_mapping(path.read_text(encoding="utf-8").splitlines())
    blocks = {}
    for item in doc.get("DATA", []):
        kind = item.get("type", "")
        if not kind.startswith("tabulated"):
            raise ValueError(f"{path}: {kind!r} data is not supported (only tabulated n, k)")
        cols = {"tabulated nk": 3, "tabulated n": 2, "tabulated k": 2}.get(kind)
        if cols is None:
            raise ValueError(f"{path}: unknown data type {kind!r}")
        rows = np.array(item.get("data", "").split(), dtype=np.float64)
        if rows.size == 0 or rows.size % cols:
            raise ValueError(f"{path}: malformed {kind!r} rows")
        blocks[kind] = rows.reshape(-1, cols)
    if "tabulated nk" in blocks:
        w, n, k = blocks["tabulated nk"].T
    elif "tabulated n" in blocks:
        w, n = blocks["tabulated n"].T
        k = np.zeros_like(n)
        if "tabulated k" in blocks:
            wk, kk = blocks["tabulated k"].T
            if not np.array_equal(w, wk):
                raise ValueError(f"{path}: tabulated n and k on different wavelengths")
            k = kk
    else:
        raise ValueError(f"{path}: no tabulated n, k data")
    if np.any(np.diff(w) <= 0.0):
        raise ValueError(f"{path}: wavelengths are not strictly increasing")
    return NkData(w, n, k, doc.get("REFERENCES", ""), doc.get("COMMENTS", ""))


def load_nk_yaml(path, wavelengths) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(eta, k)`` of a refractiveindex.info page at ``wavelengths`` (µm), PCHIP in λ.

    See :func:`read_nk_yaml` for the accepted files and :meth:`NkData.__call__` for the interpolation.
    """
    return read_nk_yaml(path)(wavelengths)


# --------------------------------------------------------------------------------------------------
# Presets


@functools.cache
def _preset_table() -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    path = DATA_DIR / PRESETS_FILE
    if not path.exists():
        raise FileNotFoundError(
            f"{path} not found; rebuild it with `python -m tablegen.build_spectral_presets`"
        )
    with np.load(path, allow_pickle=False) as f:
        meta = json.loads(str(f["meta"]))
        w, eta, k = (np.array(f[name]) for name in ("wavelengths", "eta", "k"))
    if tuple(meta["names"]) != PRESETS:
        raise ValueError(f"{path} holds presets {meta['names']}, expected {PRESETS}")
    return w, eta, k, meta


def _preset_index(name: str) -> int:
    key = str(name).strip().lower()
    key = _ALIASES.get(key, key)
    if key not in PRESETS:
        raise ValueError(
            f"unknown preset {name!r}; presets: {', '.join(PRESETS)} "
            f"(aliases: {', '.join(sorted(_ALIASES))})"
        )
    return PRESETS.index(key)


def preset(name: str, wavelengths) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(eta, k)`` of a packaged metal at ``wavelengths`` (µm, any shape, 0.36–0.83).

    Names (case-insensitive): nickel, aluminium, gold, silver, copper, chromium, brass, and the
    aliases Ni, Al, aluminum, Au, Ag, Cu, Cr, chrome, CuZn. Linear interpolation in λ between the
    stored 5 nm nodes (exact at the nodes); wavelengths outside the table raise ``ValueError``.
    Sources: :func:`preset_metadata`.
    """
    i = _preset_index(name)
    w_tab, eta, k, _ = _preset_table()
    w = np.asarray(wavelengths, dtype=np.float64)
    if np.any(w < w_tab[0]) or np.any(w > w_tab[-1]):
        raise ValueError(f"wavelengths must lie in [{w_tab[0]}, {w_tab[-1]}] µm, got {w}")
    return np.interp(w, w_tab, eta[i]), np.interp(w, w_tab, k[i])


def preset_rgb(name: str) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(eta, k)`` of a packaged metal at :data:`RGB_WAVELENGTHS`, each shape (3,) in R, G, B."""
    return preset(name, RGB_WAVELENGTHS)


def preset_metadata(name: str | None = None) -> dict:
    """Provenance of the packaged presets: source pages, references, grid and resampling method.

    With a ``name``, the entry of that preset (source file, reference, comments, source range).
    """
    meta = _preset_table()[3]
    if name is None:
        return json.loads(json.dumps(meta))  # a copy: the cached table stays intact
    return dict(meta["presets"][_preset_index(name)])


# --------------------------------------------------------------------------------------------------
# RGB → spectrum


def upsample_rgb(values_rgb, wavelengths):
    """Return a spectrum at ``wavelengths`` (µm) from values at :data:`RGB_WAVELENGTHS`.

    Piecewise-linear interpolation in λ through (λ_B, B), (λ_G, G), (λ_R, R), flat outside
    [λ_B, λ_R] (see the module docstring for why). Exact at the RGB wavelengths; linear in the values.
    Pure ``jnp``: the wavelengths may be concrete or traced (they are cast to the values' dtype).

    Args:
        values_rgb: (..., 3) in (R, G, B) order: η, k or ρ_d per channel.
        wavelengths: (N,) µm, any order.
    Returns:
        (..., N), dtype of ``values_rgb`` (floating).
    """
    values = _as_float(values_rgb)
    if values.shape[-1:] != (3,):
        raise ValueError(f"values_rgb must have a last axis of 3 (R, G, B), got {values.shape}")
    w = jnp.asarray(wavelengths, dtype=values.dtype)
    if w.ndim != 1:
        raise ValueError(f"wavelengths must be 1-D (µm), got shape {w.shape}")
    # Row c of the (3, N) weights interpolates the unit triple of channel c; jnp.interp is flat
    # beyond the end nodes. Nodes ascending: (λ_B, λ_G, λ_R), so channel c sits at node 2 − c.
    nodes = jnp.asarray(RGB_WAVELENGTHS[::-1], dtype=values.dtype)
    unit = jnp.eye(3, dtype=values.dtype)[::-1]
    weights = jnp.stack([jnp.interp(w, nodes, u) for u in unit])
    return values @ weights


# --------------------------------------------------------------------------------------------------
# spectrum → RGB


def _bin_integrals(x: np.ndarray, f: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Exact integrals of the piecewise-linear ``f(x)`` (nodes ``x``, columns of ``f``) over each bin.

    ``F(e) = F(x_j) + (e − x_j)(f(x_j) + f(e))/2`` with ``F`` the cumulative trapezoid at the nodes.
    """
    cum = np.concatenate(
        [np.zeros((1, f.shape[1])), np.cumsum(np.diff(x)[:, None] * 0.5 * (f[1:] + f[:-1]), axis=0)]
    )
    e = np.clip(edges, x[0], x[-1])
    j = np.clip(np.searchsorted(x, e, side="right") - 1, 0, len(x) - 2)
    fe = np.stack([np.interp(e, x, col) for col in f.T], axis=1)
    at_edges = cum[j] + (e - x[j])[:, None] * 0.5 * (f[j] + fe)
    return np.diff(at_edges, axis=0)


@functools.cache
def _rgb_matrix(key: tuple[float, ...], illuminant: str) -> np.ndarray:
    import colour

    cmfs = colour.MSDS_CMFS[CMFS_NAME]
    if illuminant not in colour.SDS_ILLUMINANTS:
        raise ValueError(
            f"unknown illuminant {illuminant!r}; use 'D65' or 'E' (or a key of colour.SDS_ILLUMINANTS)"
        )
    x = cmfs.wavelengths / 1000.0  # nm → µm
    s = colour.SDS_ILLUMINANTS[illuminant].copy().align(cmfs.shape).values
    f = cmfs.values * s[:, None]  # x̄S, ȳS, z̄S at 1 nm

    w = np.array(key)
    # Midpoints between samples; the end bins run to the CMF ends (flat extension of the spectrum).
    edges = np.concatenate([[x[0]], 0.5 * (w[1:] + w[:-1]), [x[-1]]])
    total = _bin_integrals(x, f, np.array([x[0], x[-1]]))[0]
    white = total / total[1]  # XYZ of a perfect white reflector, Y = 1
    xyz = _bin_integrals(x, f, edges) / total[1]

    srgb = colour.RGB_COLOURSPACES["sRGB"]
    to_rgb = np.asarray(srgb.matrix_XYZ_to_RGB)
    if illuminant != "D65":  # white-balance: adapt the illuminant's white to the sRGB (D65) white
        cat = colour.adaptation.matrix_chromatic_adaptation_VonKries(
            white, colour.xy_to_XYZ(srgb.whitepoint), transform="CAT02"
        )
        to_rgb = to_rgb @ cat
    rgb = xyz @ to_rgb.T
    rgb /= rgb.sum(axis=0)  # constant 1 → exactly (1, 1, 1) (a ~1e-4 white-point correction)
    rgb.flags.writeable = False
    return rgb


def rgb_matrix(wavelengths, illuminant: str = "D65") -> np.ndarray:
    """Return the (N, 3) weights ``M`` with ``rgb = spectrum @ M`` (linear sRGB, white-balanced).

    ``M[i] = A · ∫_{bin i} (x̄, ȳ, z̄)(λ) S(λ) dλ / ∫ ȳ S dλ``, then each column scaled so that
    ``M.sum(0) = (1, 1, 1)``; ``A`` is the sRGB XYZ→RGB matrix (after a CAT02 adaptation to D65 for
    illuminants other than D65). Bins and normalisation: see the module docstring. Bins are clipped
    to the CMF range 360–830 nm (a sample whose whole bin lies outside gets zero weight). Cached per ``(tuple(wavelengths), illuminant)``; read-only.

    Args:
        wavelengths: (N,) µm, strictly increasing.
        illuminant: ``"D65"`` (default) or ``"E"`` (equal energy), or any key of
            ``colour.SDS_ILLUMINANTS``.
    """
    return _rgb_matrix(_wavelength_key(wavelengths), str(illuminant))


def spectrum_to_rgb(values, wavelengths, illuminant: str = "D65"):
    """Integrate spectra to linear sRGB: ``values @ rgb_matrix(wavelengths, illuminant)``.

    Args:
        values: (..., N) reflectance-like spectra sampled at ``wavelengths``.
        wavelengths: (N,) µm, strictly increasing (concrete).
        illuminant: see :func:`rgb_matrix`.
    Returns:
        (..., 3) linear sRGB, dtype of ``values`` (floating).
    """
    values = _as_float(values)
    m = rgb_matrix(wavelengths, illuminant)
    if values.shape[-1:] != (m.shape[0],):
        raise ValueError(
            f"values have last axis {values.shape[-1:]}, expected {m.shape[0]} samples"
        )
    return values @ jnp.asarray(m, dtype=values.dtype)


def _as_float(x):
    """``x`` as a jnp array with a floating dtype (integers promote to the default float)."""
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.inexact) else x.astype(jnp.result_type(float))

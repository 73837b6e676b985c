"""Build ``twoscale/data/spectral_presets.npz``: n(λ), k(λ) of seven metals on a 5 nm grid.

Source: the refractiveindex.info database (CC0), as copied under ``shared/data/ior_refractiveindex_info``
(see its README). The project does not ship those files; it ships only this derived table. Each preset
is one database page, read with :func:`twoscale.spectral.read_nk_yaml` and resampled with a PCHIP
(monotone C¹ cubic through every tabulated point, no overshoot) onto 360–830 nm every 5 nm, the range
of the CIE 1931 colour-matching functions. The file records, per preset, the source page, the SHA-256
of the file read, its reference and comment strings, and its tabulated range.

Pages: Johnson & Christy (1972, 1974) for Ni, Au, Ag, Cu, Cr (the classic rendering data; coarse,
~15-50 nm apart in the visible, hence PCHIP); Rakić et al. (1998) Lorentz-Drude fit for Al (Johnson &
Christy did not measure Al); Querry (1985) Cu70Zn30 for brass (common "cartridge" brass).

Usage: ``python -m tablegen.build_spectral_presets [--source DIR] [--out FILE]`` (``--source``: the
``ior_refractiveindex_info`` folder; default ``$TWOSCALE_SHARED/data/...`` or ``../shared/data/...``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import time
from pathlib import Path

import numpy as np

from twoscale.spectral import PRESETS, PRESETS_FILE, read_nk_yaml
from twoscale.tables import DATA_DIR

VERSION = 1
GRID_NM = (360, 830, 5)  # first, last, step (nm)

# preset name → page path inside the database folder
SOURCES = {
    "nickel": "data/main/Ni/nk/Johnson.yml",
    "aluminium": "data/main/Al/nk/Rakic-LD.yml",
    "gold": "data/main/Au/nk/Johnson.yml",
    "silver": "data/main/Ag/nk/Johnson.yml",
    "copper": "data/main/Cu/nk/Johnson.yml",
    "chromium": "data/main/Cr/nk/Johnson.yml",
    "brass": "data/other/alloys/Cu-Zn/nk/Querry-Cu70Zn30.yml",
}

RESAMPLING = (
    "scipy.interpolate.PchipInterpolator in wavelength (µm) through the tabulated n and k "
    "separately, evaluated at 360-830 nm every 5 nm; no extrapolation (every source covers the grid)"
)


def default_source() -> Path:
    """``$TWOSCALE_SHARED/data/ior_refractiveindex_info``, else the ``shared`` folder beside the repo."""
    shared = Path(os.environ.get("TWOSCALE_SHARED", Path(__file__).resolve().parents[2] / "shared"))
    return shared / "data" / "ior_refractiveindex_info"


def grid() -> np.ndarray:
    """The table wavelengths in µm."""
    first, last, step = GRID_NM
    return np.arange(first, last + step, step) / 1000.0


def build(source: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Return ``(wavelengths, eta, k, meta)`` with ``eta``, ``k`` of shape (len(PRESETS), n_grid)."""
    source = Path(source)
    if tuple(SOURCES) != PRESETS:
        raise ValueError(f"SOURCES {tuple(SOURCES)} does not match twoscale.spectral.PRESETS")
    w = grid()
    eta, k, entries = [], [], []
    for name, page in SOURCES.items():
        path = source / page
        data = read_nk_yaml(path)
        n_i, k_i = data(w)
        eta.append(n_i)
        k.append(k_i)
        in_range = (data.wavelengths >= w[0]) & (data.wavelengths <= w[-1])
        entries.append(
            {
                "name": name,
                "source": page,
                "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
                "references": data.references,
                "comments": data.comments,
                "source_range_um": [float(data.wavelengths[0]), float(data.wavelengths[-1])],
                "source_points_in_grid_range": int(in_range.sum()),
            }
        )
    readme = (
        (source / "README.md").read_text(encoding="utf-8")
        if (source / "README.md").exists()
        else ""
    )
    version = re.search(r"database version (v[\w-]+)", readme)
    commit = re.search(r"commit ([0-9a-f]{40})", readme)
    meta = {
        "name": "spectral_presets",
        "version": VERSION,
        "names": list(PRESETS),
        "wavelength_unit": "um",
        "grid_nm": {"first": GRID_NM[0], "last": GRID_NM[1], "step": GRID_NM[2]},
        "resampling": RESAMPLING,
        "database": {
            "name": "refractiveindex.info database (polyanskiy/refractiveindex.info-database)",
            "version": version.group(1) if version else None,
            "commit": commit.group(1) if commit else None,
            "licence": "CC0 1.0",
            "citation": 'M. N. Polyanskiy, "Refractiveindex.info database of optical constants", '
            "Sci. Data 11, 94 (2024)",
        },
        "presets": entries,
        "generator": "tablegen/build_spectral_presets.py",
    }
    eta, k = np.array(eta), np.array(k)
    if not (np.all(np.isfinite(eta)) and np.all(np.isfinite(k)) and eta.min() > 0 and k.min() >= 0):
        raise ValueError("resampled n, k are not finite and positive")
    return w, eta, k, meta


def write(path: Path, w, eta, k, meta) -> None:
    """Write the table atomically (``wavelengths``, ``eta``, ``k`` float64; ``meta`` JSON string)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, wavelengths=w, eta=eta, k=k, meta=np.array(json.dumps(meta, indent=1)))
    tmp.replace(path)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", type=Path, default=default_source())
    parser.add_argument("--out", type=Path, default=DATA_DIR / PRESETS_FILE)
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    w, eta, k, meta = build(args.source)
    write(args.out, w, eta, k, meta)
    size = args.out.stat().st_size
    print(
        f"wrote {args.out} ({size} bytes, {len(PRESETS)} presets × {len(w)} wavelengths, "
        f"{time.perf_counter() - t0:.2f} s)"
    )


if __name__ == "__main__":
    main()

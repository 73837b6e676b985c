"""Render the Neural-BRDF stand-ins of MERL materials (60 of them) to MERL-format tables.

Source: ``shared/data/merl_nbrdf`` (Sztrajman et al., "Neural BRDF Representation and Importance
Sampling", CGF 40(6) 2021; MIT). Each material is a 6-21-21-3 MLP evaluated exactly as in the
paper's code (and the data README):

    x   = [sin θh, 0, cos θh, sin θd cos φd, sin θd sin φd, cos θd]   (half vector at φh = 0,
                                                                       difference vector)
    h1  = relu(x W1 + b1);  h2 = relu(h1 W2 + b2)
    rgb = exp(h2 W3 + b3) − 1      (BRDF in 1/sr, MERL's channel scales already applied)

on the MERL grid at the bins' lower edges (θh = (i/90)² π/2, θd = j π/180, φd = k π/180, as in
training). Cells with cos θ_i or cos θ_o ≤ ``min_cos`` (default 0.01, as in the held-out checks of
the fitting issue; real MERL files also leave the last grazing cells unmeasured) are written as
invalid (−1). These are approximations of the measurements
(errors of several %), not the measurements: use them to check that fits converge and generalise.

    python -m campaigns.nbrdf --out DIR [--materials nickel chrome ...] [--min-cos 0.01]

writes ``DIR/<material>.binary``. Never commit the rendered files (they derive from shared data).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

#: The first 12 (``nbrdf_merl_subset.npz``); the 60 of ``nbrdf_merl_60.npz`` include them.
SUBSET = (
    "nickel",
    "gray-plastic",
    "yellow-matte-plastic",
    "blue-metallic-paint2",
    "alum-bronze",
    "aluminium",
    "hematite",
    "gold-metallic-paint",
    "red-specular-plastic",
    "black-oxidized-steel",
    "chrome",
    "white-fabric",
)


MATERIALS = SUBSET  # kept for callers of the 12-material set

#: Cells with cos θ_i or cos θ_o at or below this are written invalid (see the module doc).
MIN_COS = 0.01


def default_npz(name: str = "nbrdf_merl_60.npz") -> Path:
    """``shared/data/merl_nbrdf/<name>`` beside the repository (or under $TWOSCALE_SHARED)."""
    shared = os.environ.get("TWOSCALE_SHARED")
    root = Path(shared) if shared else Path(__file__).resolve().parents[2] / "shared"
    return root / "data" / "merl_nbrdf" / name


def load_weights(npz_path=None) -> dict[str, dict[str, np.ndarray]]:
    """``{material: {W1, b1, W2, b2, W3, b3}}`` (float64 copies of the float32 weights)."""
    path = Path(npz_path) if npz_path else default_npz()
    out: dict[str, dict[str, np.ndarray]] = {}
    with np.load(path) as z:
        for key in z.files:
            parts = key.split("/")
            if len(parts) != 3 or parts[0] != "merl":
                continue
            out.setdefault(parts[1], {})[parts[2]] = np.asarray(z[key], dtype=np.float64)
    return out


def mlp_brdf(weights: dict[str, np.ndarray], theta_h, theta_d, phi_d) -> np.ndarray:
    """Evaluate one Neural-BRDF MLP at half/difference angles; returns ``(..., 3)`` in 1/sr.

    The result is 0 below the horizon (``cos θ_i`` or ``cos θ_o`` ≤ 0) and clipped at 0 (the
    network's ``exp(·) − 1`` can dip slightly below 0 where the BRDF is tiny).
    """
    th, td, pd = np.broadcast_arrays(
        *(np.asarray(a, dtype=np.float64) for a in (theta_h, theta_d, phi_d))
    )
    x = np.stack(
        [
            np.sin(th),
            np.zeros_like(th),
            np.cos(th),
            np.sin(td) * np.cos(pd),
            np.sin(td) * np.sin(pd),
            np.cos(td),
        ],
        axis=-1,
    )
    h1 = np.maximum(x @ weights["W1"] + weights["b1"], 0.0)
    h2 = np.maximum(h1 @ weights["W2"] + weights["b2"], 0.0)
    rgb = np.expm1(h2 @ weights["W3"] + weights["b3"])
    a = np.cos(th) * np.cos(td)
    b = np.sin(th) * np.sin(td) * np.cos(pd)
    above = (a - b > 0.0) & (a + b > 0.0)
    return np.where(above[..., None], np.maximum(rgb, 0.0), 0.0)


def render(weights: dict[str, np.ndarray], name: str = "nbrdf", min_cos: float = MIN_COS):
    """A :class:`twoscale.merl.MerlData` of the MLP on the MERL grid (lower-edge angles); cells
    with ``cos θ_i`` or ``cos θ_o ≤ min_cos`` are invalid."""
    from twoscale import merl

    th, td, pd = merl.grid_angles("lower")
    values = mlp_brdf(weights, th, td, pd)
    a = np.cos(th) * np.cos(td)
    b = np.sin(th) * np.sin(td) * np.cos(pd)
    valid = (a - b > min_cos) & (a + b > min_cos)
    return merl.MerlData(values=np.where(valid[..., None], values, 0.0), valid=valid, name=name)


def render_all(out_dir, materials=None, npz_path=None, min_cos: float = MIN_COS) -> list[Path]:
    """Write ``out_dir/<material>.binary`` for each material (default: every one in the weights
    file, in its order); returns the paths."""
    from twoscale import merl

    weights = load_weights(npz_path)
    names = list(materials) if materials else list(weights)
    unknown = [m for m in names if m not in weights]
    if unknown:
        raise ValueError(f"unknown Neural-BRDF material(s) {unknown}; have {sorted(weights)}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for name in names:
        data = render(weights[name], name, min_cos)
        paths.append(merl.write(out_dir / f"{name}.binary", data))
    return paths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m campaigns.nbrdf", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--out", required=True, help="output folder for <material>.binary")
    ap.add_argument("--materials", nargs="*", help="materials to render (default: all)")
    ap.add_argument(
        "--npz", help="weights file (default: shared/data/merl_nbrdf/nbrdf_merl_60.npz)"
    )
    ap.add_argument("--min-cos", type=float, default=MIN_COS, help="invalid at or below this cos θ")
    args = ap.parse_args(argv)
    try:
        paths = render_all(args.out, args.materials, args.npz, args.min_cos)
    except (OSError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for p in paths:
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Render the README's picture: spheres of the two-scale BRDF in Mitsuba 3 (twoscale.mitsuba).

    python -m benchmarks.render_example [OUT.png] [--params A/params.json B/params.json ...]

Without ``--params``: three spheres from parameters set in Python (a gold-like conductor with
diffraction, a rough copper-like conductor, a red plastic); with it, one sphere per fitted record
(the apparatus factor off). Light: a dim constant environment and a point light at the upper left.
Variant llvm_ad_rgb (cuda_ad_rgb where a GPU answers); 384×128 pixels, 32 samples per pixel.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import twoscale
import twoscale.mitsuba as tm

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "docs" / "images" / "render.png"


def default_materials():
    """``[(label, params, config)]`` of the picture without records."""
    return [
        (
            "gold-like, diffraction",
            twoscale.TwoScaleParams.conductor(
                beta=0.12,
                p=0.8,
                eta=(0.18, 0.42, 1.37),
                k=(3.4, 2.35, 1.77),
                sigma_s=0.02,
                b=3.0,
                c=2.2,
            ),
            twoscale.ModelConfig(),
        ),
        (
            "rough copper-like",
            twoscale.TwoScaleParams.conductor(
                beta=0.35, p=1.5, eta=(0.27, 0.68, 1.22), k=(3.61, 2.63, 2.29)
            ),
            twoscale.ModelConfig(diffraction=False),
        ),
        (
            "red plastic",
            twoscale.TwoScaleParams.plastic(
                beta=0.08, p=1.0, eta=1.5, rho_d=(0.45, 0.05, 0.04), sigma_s=0.01, b=2.0, c=2.0
            ),
            twoscale.ModelConfig(material="plastic"),
        ),
    ]


def scene_dict(bsdfs, width=384, height=128, spp=32):
    import mitsuba as mi

    n = len(bsdfs)
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 3},
        "sensor": {
            "type": "perspective",
            "fov": 40,
            "to_world": mi.ScalarTransform4f().look_at(
                origin=[0, 0, 10.0], target=[0, 0, 0], up=[0, 1, 0]
            ),
            "film": {"type": "hdrfilm", "width": width, "height": height},
            "sampler": {"type": "independent", "sample_count": spp},
        },
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": 0.15}},
        "light": {
            "type": "point",
            "position": [-6.0, 8.0, 10.0],
            "intensity": {"type": "rgb", "value": 250.0},
        },
    }
    for j, b in enumerate(bsdfs):
        x = (j - (n - 1) / 2) * 2.3
        scene[f"sphere{j}"] = {"type": "sphere", "center": [x, 0, 0], "radius": 1.0, "bsdf": b}
    return scene


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--params", nargs="*", default=[], help="params.json files of twoscale.fit")
    ap.add_argument("--spp", type=int, default=32)
    args = ap.parse_args(argv)
    tm.register()
    import mitsuba as mi

    if args.params:
        bsdfs = [tm.load(p) for p in args.params]
    else:
        bsdfs = [tm.bsdf(params, cfg) for _, params, cfg in default_materials()]
    t0 = time.perf_counter()
    img = np.asarray(mi.render(mi.load_dict(scene_dict(bsdfs, spp=args.spp))))
    wall = time.perf_counter() - t0
    if not np.all(np.isfinite(img)):
        raise SystemExit("render has NaN/inf pixels")
    srgb = np.asarray(
        mi.Bitmap(img).convert(srgb_gamma=True, component_format=mi.Struct.Type.UInt8)
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    import matplotlib.pyplot as plt

    plt.imsave(args.out, srgb)
    print(
        f"{args.out}: {img.shape[1]}x{img.shape[0]}, {args.spp} spp, {mi.variant()}, {wall:.1f} s"
    )


if __name__ == "__main__":
    main()

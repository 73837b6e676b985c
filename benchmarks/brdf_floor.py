"""What any per-direction evaluation of the two-scale model costs at least, against `brdf`.

    python -m benchmarks.brdf_floor [--repeats 7]

Issue 11 asks for `twoscale.brdf` within 3× a plain JAX GGX + Lambert at the 1,458,000 MERL
direction pairs. This script measures, in the same run and in float64 and float32:

1. the plain JAX GGX + Lambert (`benchmarks/reference.py`), the reference;
2. `twoscale.brdf`, the full model (conductor, specular + diffraction, tables path);
3. the part every evaluation of the model needs per pair whatever its lobes: the frame of the
   two directions (half and difference angles, and the azimuth difference φ, an `atan2`, that the
   correlated shadowing needs), the shadowing `G` (two 1-D lookups of Smith Λ) and the EPD `D`;
4. (3) plus the cheapest possible diffraction lobe short of evaluating it: one warped θ_h
   coordinate (a `log1p`) and a bicubic lookup of three channels in a per-call 2-D table over
   (θ_h, θ_d) whose values are random (what a lobe re-tabulated once per parameter set would
   cost per pair at the least, before its own table is built).

Rows (3) and (4) are floors, not implementations: they return no BRDF. They bound what an exact
per-direction path can reach on this machine; see the README's speed paragraph.
"""

from __future__ import annotations

import argparse

import jax
import numpy as np


def _floor_fns(n_h: int = 256, n_d: int = 64):
    import jax.numpy as jnp

    from twoscale import distribution, geometry, model, tables

    def frame_g_d(p, x, y):
        fr = geometry.frame_from_components(model._channels_first(x), model._channels_first(y))
        above = (fr.cos_i > 0) & (fr.cos_o > 0)
        ci = jnp.where(above, fr.cos_i, 1.0)
        co = jnp.where(above, fr.cos_o, 1.0)
        phi = jnp.where(above, fr.phi, 0.0)
        g = model._g_value(p.beta, p.p, ci, co, phi, "tables", True)
        d = distribution.ndf(fr.cos_h, p.beta, p.p)
        return fr, above, g * d / (4 * ci * co), g

    def floor(p, x, y):
        _, above, spec, _ = frame_g_d(p, x, y)
        return jnp.where(above, spec, 0.0)

    def floor_lookup(p, x, y, coeffs):
        fr, above, spec, g = frame_g_d(p, x, y)
        xh = jnp.log1p((1 - fr.cos_h * fr.cos_h) / 1e-4) / 20.0
        # The library's own cubic B-spline (one index and 4 weights per axis, shared by the
        # three channels, which are its components): 16 taps per channel.
        lobe = tables.Spline(coeffs, (0.0, 0.0), (1.0 / n_h, 1.0 / n_d), (n_h + 1, n_d + 1))
        return jnp.where(above[..., None], lobe(xh, fr.cos_d) * g[..., None] + spec[..., None], 0.0)

    table = np.random.default_rng(0).random((n_h + 3, n_d + 3, 3))
    return floor, floor_lookup, table


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import twoscale
    from benchmarks import common
    from benchmarks.reference import ggx_inputs, ggx_lambert
    from benchmarks.run import _grid, _params

    wi, wo = _grid(1)
    floor, floor_lookup, table = _floor_fns()
    m = common.machine()
    print(
        f"# Floors of a per-direction evaluation ({m['cpu']}, {m['cores']} cores, JAX {m['jax']})"
    )
    print()
    print(
        f"{wi.shape[0]:,} direction pairs; median of {args.repeats} warm runs; load average "
        f"{common.loadavg()}."
    )
    print()
    print("| what | float64 | ÷ GGX | float32 | ÷ GGX |")
    print("| --- | ---: | ---: | ---: | ---: |")
    rows = {}
    for dtype in (jnp.float64, jnp.float32):
        a, b = jnp.asarray(wi, dtype), jnp.asarray(wo, dtype)
        p = _params().astype(dtype)
        tab = jnp.asarray(table, dtype)
        cases = {
            "plain JAX GGX + Lambert (reference)": (ggx_lambert, ggx_inputs(wi, wo, dtype)),
            "`twoscale.brdf`, full model": (
                jax.jit(lambda q, x, y: twoscale.brdf(q, x, y)),
                (p, a, b),
            ),
            "floor: frame (with φ) + correlated G + D": (jax.jit(floor), (p, a, b)),
            "floor + 3-channel bicubic lookup (θ_h, θ_d)": (jax.jit(floor_lookup), (p, a, b, tab)),
        }
        for name, (fn, fargs) in cases.items():
            t = common.timed(lambda fn=fn, fargs=fargs: fn(*fargs), args.repeats)
            rows.setdefault(name, []).append(t["median"])
    ref = rows["plain JAX GGX + Lambert (reference)"]
    for name, (t64, t32) in rows.items():
        print(
            f"| {name} | {t64 * 1e3:.1f} ms | {t64 / ref[0]:.2f}× | {t32 * 1e3:.1f} ms | "
            f"{t32 / ref[1]:.2f}× |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

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


def _bicubic_weights(x, n):
    import jax.numpy as jnp

    x = jnp.clip(x, 0.0, 1.0) * n
    i = jnp.clip(jnp.floor(x), 0, n - 1)
    f = x - i
    f2, f3 = f * f, f * f * f
    w = [(1 - f) ** 3 / 6, (3 * f3 - 6 * f2 + 4) / 6, (-3 * f3 + 3 * f2 + 3 * f + 1) / 6, f3 / 6]
    return i.astype(jnp.int32), w


def _floor_fns(n_h: int = 256, n_d: int = 64):
    import jax.numpy as jnp

    from twoscale import distribution, geometry, model

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

    def floor_lookup(p, x, y, table):
        fr, above, spec, g = frame_g_d(p, x, y)
        xh = jnp.log1p((1 - fr.cos_h * fr.cos_h) / 1e-4) / 20.0
        ih, wh = _bicubic_weights(xh, n_h)
        idd, wd = _bicubic_weights(fr.cos_d, n_d)
        base = ih * (n_d + 3) + idd
        flat = table.reshape(3, -1)
        lobes = []
        for c in range(3):
            acc = 0.0
            for k in range(4):
                for m in range(4):
                    tap = flat[c].at[base + k * (n_d + 3) + m].get(mode="promise_in_bounds")
                    acc = acc + wh[k] * wd[m] * tap
            lobes.append(acc)
        return jnp.where(above, jnp.stack(lobes) * g + spec, 0.0)

    table = np.random.default_rng(0).random((3, n_h + 3, n_d + 3))
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

"""Generate ``twoscale/data/convolution.npz``: tabulated values of the lobe ``(S*D)(θ_h)``.

Run from the repository root: ``python -m tablegen.build_convolution`` (deterministic, one process,
a few minutes on 2 cores). Representation (see :mod:`twoscale.convolution`):

``log (S*D)(θ_h) = log(cos²θ_h + k sin²θ_h) + g(ln β, ln(p − 0.1), ln(c − 0.7), asinh(u/u₀), t)``

``g`` is tabulated at the nodes of a 5-D grid (``values``, float32: the values are O(10), so
float32's 6e-8 relative rounding is far below the interpolation error, and the file is half
the size); ``t ∈ [0, 1]`` is the normalised angle of
:func:`twoscale.convolution.normalised_angle` (``θ_h = 0`` at ``t = 0``, ``θ_h = π/2`` at
``t = 1``), whose per-node parameters ``(log ζ_end, log ζ_π, log T_max)`` are stored in the extra
``map`` (4-D, analytic :func:`twoscale.convolution.map_params`). ``k = L(π/2)/L(0)`` at
``u = 0`` (where ``L = A cos²θ_h + B sin²θ_h`` exactly) is the extra ``log_k`` over
``(ln β, ln(p − 0.1))``. The θ_h of each t node is found by bisection on the same jnp function the
library evaluates, and the lobe there by the exact quadrature (:func:`lobe_exact`, fewer nodes).
"""

from __future__ import annotations

import json
import math
import time

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_platform_name", "cpu")

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from twoscale import convolution as conv  # noqa: E402
from twoscale.tables import DATA_DIR, Axis  # noqa: E402

SETTINGS = {
    "n_beta": 17,
    "n_p": 26,
    "n_c": 14,
    "n_u": 21,
    "n_t": 40,
    "n_theta_quad": 61,
    "n_phi_quad": 61,
    "bisection_steps": 60,
}


def axes(s=SETTINGS):
    """The five table axes (coordinates as in :mod:`twoscale.convolution`)."""
    return (
        Axis("log_beta", math.log(1e-3), 0.0, s["n_beta"], "ln β"),
        Axis(
            "log_p_minus_offset",
            math.log(conv.P_TABLE_MIN - conv.P_OFFSET),
            math.log(5.0 - conv.P_OFFSET),
            s["n_p"],
            "ln(p − P_OFFSET), convolution.P_OFFSET",
        ),
        Axis(
            "log_c_minus_offset",
            math.log(1.01 - conv.C_OFFSET),
            math.log(5.0 - conv.C_OFFSET),
            s["n_c"],
            "ln(c − C_OFFSET), convolution.C_OFFSET",
        ),
        Axis(
            "asinh_u_over_scale",
            0.0,
            math.asinh(1000.0 / conv.U_SCALE),
            s["n_u"],
            "asinh(u / U_SCALE), convolution.U_SCALE",
        ),
        Axis("t", 0.0, 1.0, s["n_t"], "normalised angle (convolution.normalised_angle)"),
    )


def _theta_of_t(t, u, beta, q, log_map, steps):
    """θ_h with ``normalised_angle(cos θ_h) = t`` by bisection (t increases with θ_h)."""
    lo = jnp.zeros_like(t)
    hi = jnp.full_like(t, 0.5 * math.pi)

    def body(_, bounds):
        lo, hi = bounds
        mid = 0.5 * (lo + hi)
        below = conv.normalised_angle(jnp.cos(mid), u, beta, q, log_map) < t
        return jnp.where(below, mid, lo), jnp.where(below, hi, mid)

    lo, hi = jax.lax.fori_loop(0, steps, body, (lo, hi))
    theta = 0.5 * (lo + hi)
    return jnp.where(t <= 0.0, 0.0, jnp.where(t >= 1.0, 0.5 * math.pi, theta))


def build(s=SETTINGS, out=None, verbose=True):
    t0 = time.time()
    ax = axes(s)
    betas, ps, cs, us = conv.params_of_coords(*(a.nodes() for a in ax[:4]))
    us[0] = 0.0
    ts = ax[4].nodes()
    nq, nphi = s["n_theta_quad"], s["n_phi_quad"]

    exact = jax.jit(lambda ct, b, p, c, u: conv.lobe_exact(ct, b, p, c, u, n_theta=nq, n_phi=nphi))

    # k = L(π/2)/L(0) at u = 0, per (β, p).
    bb, pp = np.meshgrid(betas, ps, indexing="ij")
    ends = np.asarray(
        exact(np.array([1.0, 0.0])[None, None, :], bb[..., None], pp[..., None], 2.0, 0.0)
    )
    log_k = np.log(ends[..., 1] / ends[..., 0])

    # Map parameters at every (β, p, c, u) node.
    grid = np.meshgrid(betas, ps, cs, us, indexing="ij")
    # Stored as float32 (half the file space of float64, ≈ 1e-7 relative in t: far below the
    # table's error); the node values below are computed with the stored, rounded map.
    log_map = np.asarray(conv.map_params(*(jnp.asarray(g) for g in grid)))
    log_map = log_map.astype(np.float32).astype(np.float64)

    @jax.jit
    def node_lobes(beta, p, lk, lmap):
        # (c, u, t) for one (β, p): θ_h at the t nodes, then the exact lobe there.
        cc, uu, tt = jnp.meshgrid(jnp.asarray(cs), jnp.asarray(us), jnp.asarray(ts), indexing="ij")
        q = conv.shape_exponent(p)
        theta = _theta_of_t(tt, uu, beta, q, lmap[:, :, None, :], s["bisection_steps"])
        ct = jnp.cos(theta)
        lob = conv.lobe_exact(ct, beta, p, cc, uu, n_theta=nq, n_phi=nphi)
        base = ct * ct + jnp.exp(lk) * jnp.sin(theta) ** 2
        return jnp.log(lob) - jnp.log(base), lob

    values = np.empty((len(betas), len(ps), len(cs), len(us), len(ts)))
    for i, b in enumerate(betas):
        for j, p in enumerate(ps):
            g, lob = node_lobes(b, p, log_k[i, j], jnp.asarray(log_map[i, j]))
            lob = np.asarray(lob)
            if not np.all(np.isfinite(lob)) or np.any(lob <= 0):
                raise RuntimeError(f"non-finite or non-positive lobe at beta={b}, p={p}")
            values[i, j] = np.asarray(g)
        if verbose:
            print(f"beta {i + 1}/{len(betas)}  {time.time() - t0:.1f} s", flush=True)
    seconds = time.time() - t0
    _save(out or DATA_DIR / "convolution.npz", values, ax, log_k, log_map, s, seconds)
    if verbose:
        print(f"wrote convolution table {values.shape} in {seconds:.1f} s")
    return values


def _save(path, values, ax, log_k, log_map, s, seconds):
    """The :func:`twoscale.tables.save_table` format, with ``values`` stored as float32."""
    if not (np.all(np.isfinite(values)) and np.all(np.isfinite(log_k))):
        raise ValueError("convolution table has non-finite values")
    if not np.all(np.isfinite(log_map)):
        raise ValueError("convolution map parameters are non-finite")
    meta = {
        "name": "convolution",
        "version": 6,
        "axes": [a.__dict__ for a in ax],
        "components": [],
        "generator": {
            **s,
            "module": "tablegen.build_convolution",
            "values_dtype": "float32",
            "map_dtype": "float32",
        },
        "build_seconds": seconds,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(
        tmp,
        values=values.astype(np.float32),
        meta=np.array(json.dumps(meta)),
        log_k=log_k,
        map=log_map.astype(np.float32),
    )
    tmp.replace(path)


if __name__ == "__main__":
    build()

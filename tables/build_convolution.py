"""Generate ``twoscale/data/convolution.npz``: the compact lobe ``(S*D)(θ_h)`` table.

Run from the repository root: ``python -m tables.build_convolution`` (deterministic, one core,
a few minutes). Representation (see :mod:`twoscale.convolution`):

``log (S*D)(θ_h) = log(cos²θ_h + k sin²θ_h) + Σ_{j<K} a_j T_j(2t − 1)``, ``t = ξ/ξ_end``,
``ξ = ½ log(1 + sin²θ_h / w²)``, ``w² = 1/(1 + 4u²) + β²``,

per node of a grid over ``(log β, log p, log(c−1), asinh u)``; components
``(log k, log ξ_end, a_0 … a_{K−1})``. ``k = ⟨sin²θ_m⟩/(2⟨cos²θ_m⟩)`` (under ``D dω``) makes the
form exact at ``u = 0``; ``ξ_end`` is where the lobe falls to ``1e-4`` of its peak.

The lobe is computed with the quadrature of :func:`twoscale.convolution.lobe_exact`
(same nodes, fewer of them), factorised: for one ``(β, p)`` and one ``θ_h`` the geometry
(``1 ∓ μ``, ``D`` weights) is shared by every ``(c, u)``.
"""

from __future__ import annotations

import math
import time

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_platform_name", "cpu")

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from twoscale import convolution as conv  # noqa: E402
from twoscale.tables import DATA_DIR, Axis, save_table  # noqa: E402

SETTINGS = {
    "n_beta": 12,
    "n_p": 10,
    "n_c": 8,
    "n_u": 20,
    "n_theta_quad": 61,
    "n_phi_quad": 49,
    "n_theta_h_geom": 44,
    "n_theta_h_lin": 24,
    "theta_h_min": 1e-4,
    "K": conv.N_COEFFS,
    "fit_floor": 1e-4,
    "fit_floor_fade": 1e-5,
}


def axes(s=SETTINGS):
    """The four table axes (coordinates as in :mod:`twoscale.convolution`)."""
    return (
        Axis("log_beta", math.log(1e-3), 0.0, s["n_beta"], "ln β"),
        Axis("log_p", math.log(0.2), math.log(5.0), s["n_p"], "ln p"),
        Axis("log_c_minus_1", math.log(0.01), math.log(4.0), s["n_c"], "ln(c − 1)"),
        Axis("asinh_u", 0.0, math.asinh(1000.0), s["n_u"], "asinh u"),
    )


def theta_h_samples(s=SETTINGS) -> np.ndarray:
    """Shared θ_h samples: 0, geometric from θ_min to π/2 (narrow lobes), uniform (wide ones)."""
    geo = np.geomspace(s["theta_h_min"], 0.5 * np.pi, s["n_theta_h_geom"])
    lin = np.linspace(0.0, 0.5 * np.pi, s["n_theta_h_lin"])
    return np.unique(np.concatenate([[0.0], geo, lin]))


def _grid_lobe_fn(n_theta, n_phi):
    """``L[θ_h, c, u]`` for one ``(β, p)``: geometry per θ_h, then every (c, u) at once."""

    def one_theta(theta_h, beta, p, cs, us):
        geom = conv._quadrature_geometry(theta_h, 0.5 * jnp.pi - theta_h, beta, p, n_theta, n_phi)
        d_w, mu2, q, pw = geom
        log_term = jnp.log1p(4.0 * us[:, None, None, None] ** 2 * q)  # (u, 4, nθ, nφ)

        def per_c(c):
            s_val = mu2 * jnp.exp(-0.5 * (c + 1.0) * log_term)
            ring = 2.0 * jnp.pi * jnp.sum(s_val * pw, axis=-1)
            return jnp.sum(d_w * ring, axis=(-2, -1))  # (u,)

        return jax.lax.map(per_c, cs)  # (c, u)

    @jax.jit
    def fn(thetas, beta, p, cs, us):
        return jax.lax.map(lambda th: one_theta(th, beta, p, cs, us), thetas)

    return fn


def fit_nodes(theta_h, lobes, betas, us, s=SETTINGS):
    """Weighted linear least squares of the log-lobe residual; returns components (..., 2+K)."""
    k_ = s["K"]
    # k from u = 0 (first u node): L = A cos² + B sin² there, k = B/A = L(π/2)/L(0).
    assert us[0] == 0.0 and theta_h[0] == 0.0 and theta_h[-1] == 0.5 * np.pi
    k = lobes[..., -1, :, :1] / lobes[..., 0, :, :1]  # (β, p, c, 1)
    s2 = np.sin(theta_h) ** 2
    c2 = np.cos(theta_h) ** 2
    # lobes: (β, p, θ, c, u) -> (β, p, c, u, θ)
    lob = np.moveaxis(lobes, 2, -1)
    log_l = np.log(lob)
    w2 = (
        1.0 / (1.0 + 4.0 * us**2)[None, None, None, :, None] + betas[:, None, None, None, None] ** 2
    )
    xi = 0.5 * np.log1p(s2 / w2)
    rel = log_l - log_l.max(axis=-1, keepdims=True)
    floor = math.log(s["fit_floor"])
    # ξ_end: last crossing of the 1e-4 level (linear in ξ between samples), else ξ(π/2).
    n_t = rel.shape[-1]
    above = rel >= floor
    last = n_t - 1 - np.argmax(above[..., ::-1], axis=-1)  # last sample at or above the level
    inside = last == n_t - 1
    i0 = np.minimum(last, n_t - 2)
    take = lambda a, i: np.take_along_axis(a, i[..., None], -1)[..., 0]  # noqa: E731
    r0, r1 = take(rel, i0), take(rel, i0 + 1)
    x0, x1 = take(xi, i0), take(xi, i0 + 1)
    frac = np.clip((r0 - floor) / np.where(r0 > r1, r0 - r1, 1.0), 0.0, 1.0)
    xi_end = np.where(inside, xi[..., -1], x0 + frac * (x1 - x0))
    t = xi / xi_end[..., None]
    # Weights: 1 above the floor, fading linearly (in log) to 0 at fit_floor_fade; 0 for t > 1.
    fade = math.log(s["fit_floor_fade"])
    wt = np.clip((rel - fade) / (floor - fade), 0.0, 1.0) * (t <= 1.0 + 1e-12)
    y = log_l - np.log(c2 + k[..., None] * s2)
    v = np.polynomial.chebyshev.chebvander(2.0 * np.minimum(t, 1.0) - 1.0, k_ - 1)
    a_mat = np.einsum("...ti,...t,...tj->...ij", v, wt, v) + 1e-10 * np.eye(k_)
    b_vec = np.einsum("...ti,...t,...t->...i", v, wt, y)
    coef = np.linalg.solve(a_mat, b_vec[..., None])[..., 0]
    kk = np.broadcast_to(k, xi_end.shape)
    return np.concatenate([np.log(kk)[..., None], np.log(xi_end)[..., None], coef], axis=-1)


def build(s=SETTINGS, out=None, verbose=True):
    t0 = time.time()
    ax = axes(s)
    betas, ps, cs, us = (np.exp(ax[0].nodes()), np.exp(ax[1].nodes()), None, None)
    cs = 1.0 + np.exp(ax[2].nodes())
    us = np.sinh(ax[3].nodes())
    us[0] = 0.0
    theta_h = theta_h_samples(s)
    fn = _grid_lobe_fn(s["n_theta_quad"], s["n_phi_quad"])
    lobes = np.empty((len(betas), len(ps), len(theta_h), len(cs), len(us)))
    for i, b in enumerate(betas):
        for j, p in enumerate(ps):
            lobes[i, j] = np.asarray(
                fn(jnp.asarray(theta_h), b, p, jnp.asarray(cs), jnp.asarray(us))
            )
        if verbose:
            print(f"beta {i + 1}/{len(betas)}  {time.time() - t0:.1f} s", flush=True)
    if not np.all(np.isfinite(lobes)) or np.any(lobes <= 0):
        raise RuntimeError("non-finite or non-positive lobe values")
    comps = fit_nodes(theta_h, lobes, betas, us, s)
    seconds = time.time() - t0
    save_table(
        out or DATA_DIR / "convolution.npz",
        comps,
        ax,
        name="convolution",
        version=1,
        components=["log_k", "log_xi_end"] + [f"a{j}" for j in range(s["K"])],
        generator={**s, "module": "tables.build_convolution"},
        build_seconds=seconds,
    )
    if verbose:
        print(f"wrote convolution table {comps.shape} in {seconds:.1f} s")
    return comps


if __name__ == "__main__":
    build()

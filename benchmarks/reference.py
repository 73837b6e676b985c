"""The live peers of the speed table: a plain JAX GGX + Lambert and Mitsuba 3's conductors.

Every speed figure of :mod:`benchmarks.run` is also given as a ratio to :func:`ggx_lambert`
measured in the same run, so that a loaded or slower machine moves both together.

:func:`ggx_lambert` is what a user would write in twenty lines: a GGX (Trowbridge-Reitz)
microfacet lobe with Schlick's Fresnel per channel and the separable Smith shadowing, plus a
Lambertian body, at arbitrary direction pairs (``(N, 3)`` each, normal ``z``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

#: The reference material: roughness α, Schlick F0 and diffuse albedo per channel.
ALPHA = 0.1
F0 = (0.9, 0.7, 0.4)
RHO_D = (0.05, 0.04, 0.03)


def _smith_g1(cos_t, a2):
    c2 = cos_t * cos_t
    return 2.0 / (1.0 + jnp.sqrt(1.0 + a2 * (1.0 - c2) / c2))


@jax.jit
def ggx_lambert(wi, wo, alpha, f0, rho_d):
    """GGX + Schlick + separable Smith G + Lambert at direction pairs: ``(N, C)`` (1/sr)."""
    h = wi + wo
    h = h / jnp.linalg.norm(h, axis=-1, keepdims=True)
    cos_i, cos_o, cos_h = wi[..., 2], wo[..., 2], h[..., 2]
    cos_d = jnp.sum(wi * h, axis=-1)
    a2 = alpha * alpha
    t = cos_h * cos_h * (a2 - 1.0) + 1.0
    d = a2 / (jnp.pi * t * t)
    g = _smith_g1(cos_i, a2) * _smith_g1(cos_o, a2)
    f = f0 + (1.0 - f0) * (1.0 - cos_d[..., None]) ** 5
    spec = (d * g / (4.0 * cos_i * cos_o))[..., None] * f
    above = (cos_i > 0) & (cos_o > 0)
    return jnp.where(above[..., None], spec + rho_d / jnp.pi, 0.0)


def ggx_inputs(wi, wo, dtype):
    """The arguments of :func:`ggx_lambert` (directions and the reference material) in ``dtype``."""
    return (
        jnp.asarray(wi, dtype),
        jnp.asarray(wo, dtype),
        jnp.asarray(ALPHA, dtype),
        jnp.asarray(F0, dtype),
        jnp.asarray(RHO_D, dtype),
    )

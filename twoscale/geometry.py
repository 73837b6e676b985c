"""Frame convention, half/difference angles and MERL coordinates ↔ directions [docs/model.md §1, §7].

Convention: ``i`` (``wi``) and ``o`` (``wo``) are directions pointing *away* from the surface,
shaped ``(..., 3)``; the normal is ``z``. :func:`frame`, :func:`half_diff_from_dirs` and the
model's evaluators scale them to unit length first (:func:`unit`): a direction of any length
gives the value of its unit vector, a zero vector counts as below the horizon. The half vector
is ``h = (i+o)/|i+o|``, ``θ_h = ∠(h, z)`` and ``θ_d = ∠(i, h)`` (so ``cos θ_d = i·h``). The model works in the :class:`Frame` of cosines
(and sines) computed here once per direction pair.

Every function is elementwise over the leading axes, keeps the floating dtype of its inputs
(float32 stays float32), and is differentiable with finite gradients everywhere, including the
places where an angle is undefined (normal incidence for an azimuth, ``i = o`` for ``φ_d``,
``i = −o`` for ``h``). There the undefined quantity takes a documented value (0 for an azimuth,
``h = z`` for the half vector) through the JAX "double where" pattern, and its gradient is finite.

Noise floor used by the guards: a component of a unit vector carries an absolute rounding error of
about ``ε`` (machine epsilon of the dtype), so a 2-D vector of norm ≤ ``ε`` (``x² + y² ≤ ε²``) has
no meaningful direction. Its azimuth is then set to 0; the gradient of a guarded azimuth is bounded
by about ``1/ε`` instead of diverging.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from twoscale._numerics import eps, float_dtype, safe_sqrt

__all__ = [
    "Frame",
    "frame",
    "frame_from_components",
    "unit",
    "unit_components",
    "tan_theta",
    "spherical",
    "half_diff_from_dirs",
    "dirs_from_half_diff",
]


class Frame(NamedTuple):
    """Cosines and sines of the angles between ``i``, ``o``, ``h`` and the normal ``z``.

    Fields (all of the broadcast shape of the direction arrays without the last axis):
        cos_i: ``cos θ_i = i_z`` (not clamped: negative below the horizon).
        cos_o: ``cos θ_o = o_z`` (not clamped).
        cos_h: ``cos θ_h = h_z``, 1 where ``h`` is undefined (``i = −o``).
        sin_h: ``sin θ_h = |h_xy| ≥ 0``, 0 where ``h`` is undefined.
        cos_d: ``cos θ_d = i·h = |i+o|/2``, in [0, 1].
        sin_d: ``sin θ_d = |i−o|/2``, in [0, 1].
        phi: ``|φ_i − φ_o|`` wrapped into [0, π] (the azimuth difference of van Ginneken's
            correlated shadowing, docs/model.md §3.3); 0 where either azimuth is undefined (normal
            incidence or exit, ``|i_xy| ≤ ε`` or ``|o_xy| ≤ ε``).
    """

    cos_i: jax.Array
    cos_o: jax.Array
    cos_h: jax.Array
    sin_h: jax.Array
    cos_d: jax.Array
    sin_d: jax.Array
    phi: jax.Array


def _as_float(*xs):
    """Convert the inputs to their common floating dtype (at least float32)."""
    dtype = float_dtype(*xs)
    return tuple(jnp.asarray(x, dtype) for x in xs), dtype


def _guarded_atan2(y, x, floor2):
    """``atan2(y, x)``, or 0 (with zero gradient) where ``x² + y² ≤ floor2`` (direction undefined)."""
    ok = x * x + y * y > floor2
    return jnp.where(ok, jnp.arctan2(jnp.where(ok, y, 0.0), jnp.where(ok, x, 1.0)), 0.0)


def frame(wi, wo) -> Frame:
    """Compute the :class:`Frame` of a pair of directions (scaled to unit length first).

    ``s = i + o``, ``δ = i − o``: ``cos θ_h = s_z/|s|``, ``sin θ_h = |s_xy|/|s|``,
    ``cos θ_d = |s|/√(|s|²+|δ|²)``, ``sin θ_d = |δ|/√(|s|²+|δ|²)`` (for unit vectors
    ``√(|s|²+|δ|²) = 2``, so ``cos θ_d = |i+o|/2 = i·h``; the normalised form keeps
    ``cos² + sin² = 1`` and both in [0, 1] under rounding), and
    ``φ = atan2(|i_x o_y − i_y o_x|, i_x o_x + i_y o_y) = |φ_i − φ_o|`` wrapped into [0, π].

    Guards (values and gradients finite): ``|s| ≤ ε`` (``i = −o``, outside the domain) gives
    ``h = z`` (``cos_h = 1``, ``sin_h = 0``); ``|i_xy| ≤ ε`` or ``|o_xy| ≤ ε`` gives ``φ = 0``
    (there ``min(Λ_i, Λ_o) = 0``, so the value of ``φ`` does not matter to ``G``); the norms
    ``|s_xy|``, ``|δ|`` have gradient 0 where they vanish (``θ_h = 0``, ``i = o``).

    Args:
        wi: incident direction(s), shape ``(..., 3)``, pointing away from the surface (any
            length: scaled to unit length, :func:`unit_components`).
        wo: outgoing direction(s), shape ``(..., 3)``; broadcasts with ``wi``.
    Returns:
        :class:`Frame` with fields of shape ``broadcast(wi, wo).shape[:-1]`` and the inputs' dtype.
    """
    (wi, wo), dtype = _as_float(wi, wo)
    wi, wo = jnp.broadcast_arrays(wi, wo)
    return frame_from_components(
        unit_components((wi[..., 0], wi[..., 1], wi[..., 2])),
        unit_components((wo[..., 0], wo[..., 1], wo[..., 2])),
    )


#: Squared lengths within this many machine epsilons of 1 count as unit (:func:`unit_components`).
UNIT_TOLERANCE = 16


def unit_components(w):
    """The components ``(x, y, z)`` of a direction scaled to unit length (a zero vector stays
    zero, with finite gradients): the model's directions need not be normalised by the caller.

    Derivatives are those of ``w/|w|`` everywhere. Values: a direction whose squared length is
    1 to within :data:`UNIT_TOLERANCE` ulps is returned as it is, bit for bit (rescaling it
    would only move it by rounding, which a very sharp lobe amplifies: a density of 1e9 1/sr
    changes by ~1e-9 relative), so unit input, the usual case, keeps the values it had before
    directions were rescaled. (``x̂ + (x − x̂)`` is exactly ``x`` there: the difference of two
    numbers within a factor 2 of each other is exact.)
    """
    x, y, z = w
    n2 = x * x + y * y + z * z
    ok = n2 > 0.0
    inv = jnp.where(ok, jax.lax.rsqrt(jnp.where(ok, n2, 1.0)), 0.0)
    keep = jnp.abs(n2 - 1.0) <= UNIT_TOLERANCE * eps(jnp.result_type(n2))

    def one(c):
        scaled = c * inv
        return scaled + jax.lax.stop_gradient(jnp.where(keep, c - scaled, 0.0))

    return one(x), one(y), one(z)


def unit(w):
    """:func:`unit_components` of ``(..., 3)`` directions, as ``(..., 3)``."""
    w = jnp.asarray(w)
    return jnp.stack(unit_components((w[..., 0], w[..., 1], w[..., 2])), axis=-1)


def frame_from_components(wi, wo) -> Frame:
    """:func:`frame` of unit directions given as component arrays ``(x, y, z)`` each (the
    caller scales them to unit length: :func:`unit_components`).

    The components are floating arrays of one dtype and one (broadcast) shape; the model's
    per-pair path passes them as contiguous rows (a ``(..., 3)`` array's components are
    strided, which keeps XLA's CPU loops from vectorising).
    """
    ix, iy, iz = wi
    ox, oy, oz = wo
    e2 = eps(jnp.result_type(ix)) ** 2

    # Half vector from s = i + o without normalising first.
    sx, sy, sz = ix + ox, iy + oy, iz + oz
    s_xy2 = sx * sx + sy * sy
    s2 = s_xy2 + sz * sz
    s_len = safe_sqrt(s2)
    ok_h = s2 > e2  # |i + o| above rounding noise: h is defined
    s_den = jnp.where(ok_h, s_len, 1.0)
    cos_h = jnp.where(ok_h, sz / s_den, 1.0)
    sin_h = jnp.where(ok_h, safe_sqrt(s_xy2) / s_den, 0.0)

    # Difference angle: θ_d is half the angle between i and o.
    dx, dy, dz = ix - ox, iy - oy, iz - oz
    d2 = dx * dx + dy * dy + dz * dz
    d_len = safe_sqrt(d2)
    den2 = s2 + d2  # = 2|i|² + 2|o|² = 4 for unit vectors
    ok_d = den2 > 0.0  # false only for zero vectors
    den = jnp.where(ok_d, safe_sqrt(den2), 1.0)
    # sqrt is monotone and correctly rounded, so |s| ≤ den and |δ| ≤ den: both ratios lie in [0, 1].
    cos_d = jnp.where(ok_d, s_len / den, 1.0)
    sin_d = jnp.where(ok_d, d_len / den, 0.0)

    # Azimuth difference, wrapped into [0, π]; undefined when either direction is along z.
    ok_phi = (ix * ix + iy * iy > e2) & (ox * ox + oy * oy > e2)
    cross = jnp.where(ok_phi, ix * oy - iy * ox, 0.0)
    dot = jnp.where(ok_phi, ix * ox + iy * oy, 1.0)
    # cross² + dot² = |i_xy|²|o_xy|² > ε⁴ > 0 where ok_phi: atan2 and its gradient are finite.
    phi = jnp.where(ok_phi, jnp.arctan2(jnp.abs(cross), dot), 0.0)

    return Frame(cos_i=iz, cos_o=oz, cos_h=cos_h, sin_h=sin_h, cos_d=cos_d, sin_d=sin_d, phi=phi)


def tan_theta(cos_theta):
    """Compute ``tan θ = sin θ / cos θ`` from ``cos θ ∈ [0, 1]``, finite at grazing.

    ``sin θ = √((1 − cos θ)(1 + cos θ))`` (no cancellation near ``cos θ = 1``). The denominator is
    floored at ``ε`` (machine epsilon of the dtype): a cosine computed from unit vectors has an
    absolute error of about ``ε``, so below it the value is noise. Hence ``tan θ ≤ 1/ε``
    (4.5e15 in float64, 8.4e6 in float32; ``tan² θ`` stays finite), and the gradient is 0 below
    the floor. ``cos θ ≥ 1`` gives 0.

    Args:
        cos_theta: ``cos θ``, any shape.
    Returns:
        ``tan θ ≥ 0``, same shape and dtype.
    """
    ((c,), dtype) = _as_float(cos_theta)
    floor = eps(dtype)
    sin = safe_sqrt((1.0 - c) * (1.0 + c))
    return sin / jnp.where(c > floor, c, floor)


def spherical(theta, phi):
    """Unit vector ``(sin θ cos φ, sin θ sin φ, cos θ)`` with polar angle ``θ`` from ``z``.

    Args:
        theta: polar angle(s) in radians.
        phi: azimuth(s) in radians; broadcasts with ``theta``.
    Returns:
        Array of shape ``broadcast(theta, phi).shape + (3,)``.
    """
    (theta, phi), _ = _as_float(theta, phi)
    st = jnp.sin(theta)
    return jnp.stack(jnp.broadcast_arrays(st * jnp.cos(phi), st * jnp.sin(phi), jnp.cos(theta)), -1)


def half_diff_from_dirs(wi, wo):
    """Rusinkiewicz half/difference angles of a direction pair [docs/model.md §7.3].

    ``θ_h = ∠(h, z)``, ``φ_h = atan2(h_y, h_x)``, ``d = R_y(−θ_h) R_z(−φ_h) i``,
    ``θ_d = ∠(d, z)``, ``φ_d = atan2(d_y, d_x)``. Angles are computed as ``atan2`` of a sine and
    a cosine (accurate everywhere, unlike ``acos`` near 0), rotations from the components of
    ``s = i + o`` (no trigonometric round trip). Undefined azimuths are 0: ``φ_h = 0`` at
    ``θ_h = 0`` (then ``d = i``), ``φ_d = 0`` at ``θ_d = 0``; ``h = z`` at ``i = −o``.

    Args:
        wi: incident direction(s), ``(..., 3)``, of any length (:func:`unit`).
        wo: outgoing direction(s), ``(..., 3)``; broadcasts with ``wi``.
    Returns:
        ``(theta_h, theta_d, phi_d)``: ``θ_h, θ_d ∈ [0, π]``, ``φ_d ∈ (−π, π]`` (not folded; the
        MERL index folds it into [0, π) by reciprocity), each of the broadcast shape without the
        last axis.
    """
    (wi, wo), dtype = _as_float(wi, wo)
    wi, wo = jnp.broadcast_arrays(unit(wi), unit(wo))
    e2 = eps(dtype) ** 2
    ix, iy, iz = wi[..., 0], wi[..., 1], wi[..., 2]
    sx, sy, sz = ix + wo[..., 0], iy + wo[..., 1], iz + wo[..., 2]

    s_xy2 = sx * sx + sy * sy
    s2 = s_xy2 + sz * sz
    ok_h = s2 > e2  # h defined
    s_xy = safe_sqrt(s_xy2)
    theta_h = jnp.where(ok_h, jnp.arctan2(s_xy, jnp.where(ok_h, sz, 1.0)), 0.0)
    s_den = jnp.where(ok_h, safe_sqrt(s2), 1.0)
    cos_th = jnp.where(ok_h, sz / s_den, 1.0)
    sin_th = jnp.where(ok_h, s_xy / s_den, 0.0)
    # cos φ_h, sin φ_h; φ_h = 0 where h_xy is rounding noise (|s_xy| ≤ ε|s|).
    ok_ph = ok_h & (s_xy2 > e2 * s2)
    xy_den = jnp.where(ok_ph, s_xy, 1.0)
    cos_ph = jnp.where(ok_ph, sx / xy_den, 1.0)
    sin_ph = jnp.where(ok_ph, sy / xy_den, 0.0)

    # v = R_z(−φ_h) i, then d = R_y(−θ_h) v.
    vx = cos_ph * ix + sin_ph * iy
    vy = -sin_ph * ix + cos_ph * iy
    dx = cos_th * vx - sin_th * iz
    dz = sin_th * vx + cos_th * iz
    d_xy2 = dx * dx + vy * vy
    theta_d = jnp.arctan2(safe_sqrt(d_xy2), dz)  # |d| = 1 > 0: atan2 is well defined
    phi_d = _guarded_atan2(vy, dx, e2)
    return theta_h, theta_d, phi_d


def _dirs_from_half_diff(xp, theta_h, theta_d, phi_d):
    """:func:`dirs_from_half_diff` for an array namespace ``xp`` (``jax.numpy`` or ``numpy``)."""
    st_h, ct_h = xp.sin(theta_h), xp.cos(theta_h)
    st_d, ct_d = xp.sin(theta_d), xp.cos(theta_d)
    dx, dy, dz = st_d * xp.cos(phi_d), st_d * xp.sin(phi_d), ct_d
    # i = R_y(θ_h) d; o = 2(i·h)h − i = R_y(θ_h) (−d_x, −d_y, d_z) (the reflection of d about z,
    # rotated: the same vector, without the cancellation of 2(i·h)h − i).
    wi = xp.stack(xp.broadcast_arrays(ct_h * dx + st_h * dz, dy, ct_h * dz - st_h * dx), axis=-1)
    wo = xp.stack(xp.broadcast_arrays(st_h * dz - ct_h * dx, -dy, ct_h * dz + st_h * dx), axis=-1)
    return wi, wo


def _azimuth_difference(xp, wi, wo, e2):
    """``|φ_i − φ_o|`` in [0, π] as :func:`frame` computes it (0 where undefined), for ``xp``."""
    ix, iy, ox, oy = wi[..., 0], wi[..., 1], wo[..., 0], wo[..., 1]
    ok = (ix * ix + iy * iy > e2) & (ox * ox + oy * oy > e2)
    cross = xp.where(ok, ix * oy - iy * ox, 0.0)
    dot = xp.where(ok, ix * ox + iy * oy, 1.0)
    return xp.where(ok, xp.arctan2(xp.abs(cross), dot), 0.0)


def dirs_from_half_diff(theta_h, theta_d, phi_d):
    """Directions of the half/difference angles with ``φ_h = 0`` [docs/model.md §7.3].

    ``d = (sin θ_d cos φ_d, sin θ_d sin φ_d, cos θ_d)``, ``h = (sin θ_h, 0, cos θ_h)``,
    ``i = R_y(θ_h) d``, ``o = 2(i·h)h − i``; hence
    ``cos θ_i = cos θ_h cos θ_d − sin θ_h sin θ_d cos φ_d`` and
    ``cos θ_o = cos θ_h cos θ_d + sin θ_h sin θ_d cos φ_d``.

    Args:
        theta_h: half angle(s) in radians.
        theta_d: difference angle(s) in radians.
        phi_d: difference azimuth(s) in radians. The three broadcast together.
    Returns:
        ``(wi, wo)``, unit vectors of shape ``broadcast.shape + (3,)``.
    """
    (theta_h, theta_d, phi_d), _ = _as_float(theta_h, theta_d, phi_d)
    return _dirs_from_half_diff(jnp, theta_h, theta_d, phi_d)

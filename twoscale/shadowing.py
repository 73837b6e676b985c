"""Smith shadowing-masking for the exponential power distribution [HP17 Eq. 36-38].

Slopes are β-normalised. The EPD's slope density is ``P22(x, y) = c_p exp[−(x² + y²)^p]``,
``c_p = p/(π Γ(1/p))``, its marginal ``P2(r) = c_p ∫_{−∞}^{∞} exp[−(r² + q²)^p] dq`` (docs/model.md §3.3:
the paper's lower bound 0 is a typo for −∞), and with ``a = β tan θ``::

    Λ(a; p) = ∫_{1/a}^{∞} (r a − 1) P2(r) dr,        G1 = 1/(1 + Λ).

**Derived (single integral).** Write the slope as ``R (cos φ, sin φ)``: ``φ`` is uniform and
``V = R^{2p}`` is Gamma(1/p, 1)-distributed. Integrating over ``φ`` at fixed ``R > μ = 1/a`` gives
``Λ = (a/π) E[√(R² − μ²) − μ arccos(μ/R)]``, and with ``y = √(a²R² − 1)``,
``v0 = μ^{2p} = a^{−2p}``::

    Λ(a; p) = 1/(π Γ(1/p)) ∫_{v0}^{∞} (y − arctan y) v^{1/p − 1} e^{−v} dv,
    y² = (v/v0)^{1/p} − 1.

**Exact path** (``path="exact"``): that integral in ``ℓ = log(v − v0)`` by the trapezoidal rule
with :data:`QUAD_NODES` fixed nodes (geometric convergence: the integrand is analytic in a strip
around the real ``ℓ`` axis and decays exponentially at both ends). The node range adapts to
``(a, p)``: from ``max(min(log v0, 0), −20p) − 12`` (the integrand falls like ``e^{2.5ℓ}`` below
``log v0`` and like ``e^{3ℓ/(2p)}`` between ``log v0`` and 0) to ``log(40 + 6/p)`` (the Gamma tail).
Everything except ``y − arctan y`` is summed in logs, so the relative accuracy holds where Λ is
exponentially small (``Λ ~ e^{−a^{−2p}}`` as ``a → 0``); ``y − arctan y`` uses its series below
``y = 0.1`` (no cancellation). For ``a ≥`` :data:`A_ASYMPTOTIC` the large-``a`` expansion
(derived; the next term is ``O(a^{−2})``, below float64 resolution there)::

    Λ = a m(p) − 1/2 + c1(p)/a,   m = E[R]/π = Γ(3/(2p))/(π Γ(1/p)),   c1 = Γ(1/(2p))/(2π Γ(1/p)).

Measured (``tests/test_shadowing.py``, ``tablegen/check_smith.py``): ≤ 1e-11 relative to 30-digit
mpmath and to SciPy quadrature of the double integral, for ``a ∈ [1e-14, 1e15]``, ``p ∈ [0.1, 10]``.
Differentiable in ``a`` and ``p``; gradients finite everywhere.

**Table path** (``path="tables"``, the default): ``twoscale/data/smith_lambda.npz`` built by
``python -m tablegen.build_smith``. It stores the smooth quantity::

    T(log p, x) = log[Λ/(a m(p))] + a^{−2p}

(the ``+a^{−2p}`` removes the essential singularity ``e^{−a^{−2p}}`` at ``a → 0``; ``T → 0`` as
``a → ∞``) on a uniform grid in ``log p`` and a normalised coordinate ``x ∈ [0, 1]``:

* ``η = log(a · π m(p))`` — log of ``a`` times the mean slope ``E[R]``, so that the large-``a``
  regime starts near ``η = 0`` for every p (``E[R]`` is 2.4e5 at p = 0.1, 0.65 at p = 10);
* ``ξ = s η − (s − 1) softplus(2(η − 1/2))/2`` with ``s = 1 + softplus(4(2p − 1))/4 ≈ max(1, 2p)``:
  slope ``s`` in ``η`` below ``η ≈ 0`` (where, for large p, Λ varies on the scale ``1/(2p)`` in
  ``log a``) and slope 1 above (where it varies on the scale 1);
* ``x = (ξ − ξ_lo(p))/(ξ_hi(p) − ξ_lo(p))`` with ``ξ_lo`` at ``a^{−2p} = `` :data:`V_MAX`
  (there ``Λ < 1e-70``) and ``ξ_hi`` at ``a · π m(p) =`` :data:`A_TILDE_MAX` (there
  ``T ≈ −π/(2 a π m) ≈ −1.6e-7``).

Interpolation is the C² cubic B-spline of :mod:`twoscale.tables`; both axes extend one node
beyond the domain so its edges are interior to the spline. Reconstruction:
``Λ = exp(log a + log m + T − a^{−2p})``. Outside the table (continuous rules):

* ``x < 0`` (``a^{−2p} > V_MAX``): ``T`` is held at its edge value while ``−a^{−2p}`` keeps its
  exact form, so Λ keeps decaying like ``e^{−a^{−2p}}`` (it is below ``1e-70`` there);
* ``x > 1`` (``a > a_hi``): ``Λ = a m exp(T_hi)``, i.e. ``Λ/a`` is held at its edge value
  (relative error ≤ 1.6e-7: the neglected ``−1/2``);
* ``p`` is clamped to [:data:`P_MIN`, :data:`P_MAX`] (zero gradient in p outside; use the
  exact path there).

Measured accuracy (``python -m tablegen.check_smith``): see that module and ``tablegen/ACCURACY.md``.

Hot paths: :func:`smith_lambda_spline` slices the table at one ``p`` and returns a small
:class:`SmithLambdaSpline` module whose call is a 1-D lookup per sample.

Large and infinite ``a``: ``a`` is clamped to ``A_MAX(dtype) = finfo.max^{1/4}`` (1.4e9 in
float32, 1.3e77 in float64), so ``Λ(∞)`` is the large finite value ``Λ(A_MAX)`` and
``G1(∞) ≈ 1/(A_MAX m)`` — never NaN, and products such as ``λ(φ) · Λ`` stay finite. Negative ``a``
is treated as 0.

Joint masking-shadowing [HP17 §5; Heitz 2014, Eq. 101; van Ginneken et al. 1998]:
height-direction correlated ``G = 1/(1 + max(Λ_i, Λ_o) + λ(φ) min(Λ_i, Λ_o))`` with
``λ(φ) = 4.41 φ/(4.41 φ + 1)``, ``φ = |φ_i − φ_o|`` wrapped into [0, π] (docs/model.md §3.3), or the
uncorrelated product ``G1(i) G1(o)`` (Mitsuba 3, pbrt).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import gammaln

from twoscale import tables
from twoscale._numerics import float_dtype, tiny
from twoscale.tables import Spline

__all__ = [
    "smith_lambda_a",
    "smith_lambda",
    "smith_g1",
    "van_ginneken",
    "joint_g",
    "joint_g_from_lambdas",
    "joint_g_tangent",
    "smith_lambda_spline",
    "lambda_partials",
    "SmithLambdaSpline",
    "mean_slope",
]

TABLE_NAME = "smith_lambda"

# Exact path.
QUAD_NODES = 768  # trapezoidal nodes in log(v − v0); ≤ 1e-11 relative up to p = 10 (measured)
_TAIL_EFOLDS = 30.0  # below-bulk range kept in the power-law region: e^{−30} ≈ 1e-13
_FLOOR_EFOLDS = 12.0  # below min(log v0, 0): the integrand ∝ w^{2.5} there, e^{−30}
_V0_ZERO = 1e4  # a^{−2p} beyond this gives Λ = 0 exactly (e^{−1e4} underflows in any dtype)
A_ASYMPTOTIC = 1e6  # a above which Λ = a m − 1/2 + c1/a (error O(a^{−2}), far below one ulp)
_SERIES_Y = 0.1  # y − arctan y by its series below this (no cancellation)

# Table path: domain and coordinate (see the module docstring).
P_MIN, P_MAX = 0.1, 10.0
V_MAX = 200.0  # small-a edge: a^{−2p} = V_MAX
A_TILDE_MAX = 1e7  # large-a edge: a · E[R] = A_TILDE_MAX
XI_LO = -20.0  # table coordinate at the small-a edge (every p)
XI_HI = math.log(A_TILDE_MAX)  # table coordinate at the large-a edge (every p)
_XI_SHARPNESS = 2.0  # softplus sharpness of the ξ(η) knee
_XI_KNEE = 0.5  # η of the knee


def a_max(dtype) -> float:
    """Largest ``a`` the kernels use (``finfo.max^{1/4}``); larger values (and inf) are clamped."""
    return float(jnp.finfo(dtype).max) ** 0.25


# dtype rule: float_dtype(..., default=float). Unlike the model's float32 default, Python numbers
# and integer arrays follow JAX's default float here (float64 under x64), as the kernels document.


def log_mean_slope(p):
    """``log E[R] = lgamma(3/(2p)) − lgamma(1/p)``: log of the mean β-normalised slope magnitude."""
    return gammaln(1.5 / p) - gammaln(1.0 / p)


def mean_slope(p):
    """``E[R] = Γ(3/(2p))/Γ(1/p)`` (β-normalised); ``Λ ≈ a E[R]/π − 1/2`` as ``a → ∞``."""
    return jnp.exp(log_mean_slope(p))


def _y_minus_arctan(y):
    """``y − arctan y`` for ``y ≥ 0`` without cancellation (series ``Σ (−1)^{k+1} y^{2k+1}/(2k+1)``)."""
    small = y < _SERIES_Y
    ys = jnp.where(small, y, 0.0)  # double where: the series never sees a large y (overflow)
    y2 = ys * ys
    poly = 0.0
    for k in range(10, 0, -1):  # terms up to y^21: relative error < 1e-20 at y = 0.1
        poly = (-1.0) ** (k + 1) / (2 * k + 1) + y2 * poly
    return jnp.where(small, ys * y2 * poly, y - jnp.arctan(y))


def _lambda_quadrature(a, p, n_nodes: int = QUAD_NODES):
    """Λ by the trapezoidal rule in ``ℓ = log(v − v0)`` (``0 < a ≤ A_ASYMPTOTIC``, any shape)."""
    dtype = a.dtype
    log_v0 = jnp.minimum(-2.0 * p * jnp.log(a), math.log(_V0_ZERO))
    lo = jnp.maximum(jnp.minimum(log_v0, 0.0), -(2.0 * p / 3.0) * _TAIL_EFOLDS) - _FLOOR_EFOLDS
    hi = jnp.log(40.0 + 6.0 / p)
    t = jnp.asarray(np.linspace(0.0, 1.0, n_nodes), dtype)
    step = (hi - lo) / (n_nodes - 1)
    ell = lo[..., None] + (hi - lo)[..., None] * t  # log w, w = v − v0
    lv0, pp = log_v0[..., None], p[..., None]
    log_v = jnp.logaddexp(lv0, ell)
    # y² = (v/v0)^{1/p} − 1 with log(v/v0) = softplus(ℓ − log v0): no cancellation near v = v0.
    y = jnp.sqrt(jnp.expm1(jax.nn.softplus(ell - lv0) / pp))
    # dv = w dℓ: log of v^{1/p−1} e^{−v} w.
    log_w = (1.0 / pp - 1.0) * log_v - jnp.exp(log_v) + ell
    total = jnp.sum(_y_minus_arctan(y) * jnp.exp(log_w), axis=-1) * step
    return total * jnp.exp(-gammaln(1.0 / p)) / jnp.pi


def _lambda_asymptotic(a, p):
    """``Λ = a m − 1/2 + c1/a`` (large ``a``), ``m = E[R]/π``, ``c1 = E[1/R]/(2π)``."""
    m = mean_slope(p) / jnp.pi
    c1 = jnp.exp(gammaln(0.5 / p) - gammaln(1.0 / p)) / (2.0 * jnp.pi)
    return a * m - 0.5 + c1 / a


def _lambda_exact(a, p):
    big = a > A_ASYMPTOTIC
    # Double where: each branch only ever sees inputs inside its own domain.
    a_quad = jnp.where(big, A_ASYMPTOTIC, jnp.maximum(a, tiny(a.dtype)))
    a_asym = jnp.where(big, a, A_ASYMPTOTIC)
    return jnp.where(big, _lambda_asymptotic(a_asym, p), _lambda_quadrature(a_quad, p))


# ---------------------------------------------------------------------------------------------
# Table path


def _softplus(x, k):
    return jax.nn.softplus(k * x) / k


def _knee(eta):
    """``softplus(2(1/2 − η))/2``: ≈ ``1/2 − η`` below the knee at ``η = 1/2``, → 0 above it."""
    return _softplus(_XI_KNEE - eta, _XI_SHARPNESS)


def table_frame(p):
    """p-dependent constants of the table coordinate, as a dict of arrays (shape of ``p``).

    ``log_es`` = log E[R]; ``s`` = the slope of ``ξ`` in ``η`` below the knee, chosen so that
    ``a^{−2p} = V_MAX`` falls on ``ξ = XI_LO`` for every p; ``log_a_hi`` = log of the large-a
    edge (``a · E[R] = A_TILDE_MAX``, ``ξ = XI_HI``).
    """
    log_es = log_mean_slope(p)
    eta_lo = log_es - math.log(V_MAX) / (2.0 * p)  # η at a^{−2p} = V_MAX
    s = 1.0 + (eta_lo - XI_LO) / _knee(eta_lo)
    return {"log_es": log_es, "s": s, "log_a_hi": XI_HI - log_es}


def table_xi(log_a, frame):
    """Table coordinate ``ξ = η − (s − 1) softplus(2(1/2 − η))/2``, ``η = log(a E[R])`` (not clamped)."""
    eta = log_a + frame["log_es"]
    return eta - (frame["s"] - 1.0) * _knee(eta)


def essential(v0):
    """``h(v0) = v0 − log(1 + v0 + v0²/2)``, the part of ``−log Λ`` that blows up as ``a → 0``.

    ``Λ ~ v0^{1/p − 5/2} e^{−v0}`` for large ``v0 = a^{−2p}``, so adding ``h`` leaves a quantity
    linear in ``log v0`` there; ``h = O(v0³)`` for small ``v0`` keeps it out of the large-a regime,
    where ``v0`` varies quickly with p at fixed ``ξ`` (small p).
    """
    return v0 - jnp.log1p(v0 * (1.0 + 0.5 * v0))


def _v0(log_a, p):
    """``a^{−2p}`` from ``log a``, capped at ``_V0_ZERO`` (no overflow, no inf·0 in gradients)."""
    return jnp.exp(jnp.minimum(-2.0 * p * log_a, math.log(_V0_ZERO)))


def table_quantity(lam, log_a, p):
    """The stored quantity ``T = log Λ − log(a m(p)) + h(a^{−2p})`` (float64 on the grid)."""
    log_m = log_mean_slope(p) - math.log(math.pi)
    return jnp.log(lam) - log_a - log_m + essential(jnp.exp(-2.0 * p * log_a))


def _lambda_lookup(t_of_xi, a2, log_a, p, frame):
    """Λ from ``a²`` and ``log a`` (the same ``a``, in range) and the table ``T`` as a function of ξ.

    The module docstring's coordinate and reconstruction, written with four transcendentals per
    sample instead of eight (the per-cell cost of ``G`` on the MERL grid, where Λ is most of the
    work):

    * the knee of :func:`table_xi`, ``½ softplus(2(½ − η))`` with ``η = log(a E[R])``, is
      ``½ log1p(e^{1 − 2 log E[R]} / a²)``: one ``log1p`` of a quotient. ``a²`` is held inside
      ``[e^{−2} a_lo², a_hi²]`` for the knee only (``a_lo``: the table's small-a edge, where
      ``ξ = XI_LO``; ξ increases with ``a``, so below it ξ is clipped to ``XI_LO`` either way)
      so that the quotient stays finite;
    * ``exp(−h(v0)) = e^{−v0} (1 + v0 + v0²/2)`` (:func:`essential`): the reconstruction
      ``Λ = exp(log a + log m + T − v0) (1 + v0 (1 + v0/2))``, ``v0 = a_top^{−2p}``.

    The same values as :func:`table_xi` and :func:`essential` to rounding (``tests/test_shadowing.py``).
    """
    k = _lookup_parts(a2, log_a, p, frame)
    return _lambda_from_parts(t_of_xi(k["xi"]), log_a, k, frame)


def _lambda_from_parts(t_val, log_a, k, frame):
    """``Λ = exp(log a + log m + T − v0) (1 + v0 (1 + v0/2))`` from the table value ``T`` at
    ``k["xi"]`` and the quantities ``k`` of :func:`_lookup_parts`."""
    log_m = frame["log_es"] - math.log(math.pi)
    return jnp.exp(log_a + log_m + t_val - k["v0"]) * (1.0 + k["v0"] * (1.0 + 0.5 * k["v0"]))


def _lookup_parts(a2, log_a, p, frame):
    """The per-sample quantities of :func:`_lambda_lookup` (shared with
    :func:`lambda_partials`, which also needs which clamps are active)."""
    log_a_top = jnp.minimum(log_a, frame["log_a_hi"])
    a2_lo = jnp.exp(-math.log(V_MAX) / p - 2.0)  # e^{−2} a_lo²
    a2_hi = jnp.exp(2.0 * frame["log_a_hi"])
    x = jnp.exp(1.0 - 2.0 * frame["log_es"]) / jnp.clip(a2, a2_lo, a2_hi)
    knee = 0.5 * jnp.log1p(x)
    xi_raw = log_a_top + frame["log_es"] - (frame["s"] - 1.0) * knee
    expo = -2.0 * p * log_a_top
    return {
        "log_a_top": log_a_top,
        "a2_lo": a2_lo,
        "a2_hi": a2_hi,
        "x": x,
        "knee": knee,
        "xi_raw": xi_raw,
        "xi": jnp.clip(xi_raw, XI_LO, XI_HI),
        "expo": expo,
        "v0": _v0(log_a_top, p),
    }


def _a_parts(a):
    """``a²`` and ``log a`` (``a`` floored at the smallest normal) of ``a ∈ [0, a_max]``."""
    return a * a, jnp.log(jnp.maximum(a, tiny(a.dtype)))


def _a_parts_of_cos(cos_theta, beta, dtype):
    """``(β² tan²θ, a², log a)`` of a direction: ``a² = β² tan²θ`` capped at ``a_max²``, the
    cosine floored at machine epsilon as :func:`twoscale.geometry.tan_theta`, ``log a``
    floored at the smallest normal ``a²``."""
    c = jnp.asarray(cos_theta, dtype)
    floor = jnp.finfo(dtype).eps
    d = jnp.where(c > floor, c, floor)
    a2_raw = jnp.asarray(beta, dtype) ** 2 * (jnp.maximum((1.0 - c) * (1.0 + c), 0.0) / (d * d))
    a2 = jnp.minimum(a2_raw, a_max(dtype) ** 2)
    return a2_raw, a2, 0.5 * jnp.log(jnp.maximum(a2, tiny(dtype)))


def _lambda_table(a, p):
    p = jnp.clip(p, P_MIN, P_MAX)
    frame = table_frame(p)
    spline = tables.spline(TABLE_NAME, a.dtype)
    return _lambda_lookup(lambda xi: spline(jnp.log(p), xi), *_a_parts(a), p, frame)


class SmithLambdaSpline(eqx.Module):
    """Λ(a) at one fixed ``p``: the table sliced once, then a 1-D cubic lookup per call.

    Build it with :func:`smith_lambda_spline`; it is a pytree (differentiable in ``p`` through
    its leaves). ``spline_1d(a)`` equals ``smith_lambda_a(a, p)`` of the table path.
    """

    spline: Spline
    p: jax.Array
    log_es: jax.Array
    s: jax.Array
    log_a_hi: jax.Array

    def _frame(self):
        return {
            "log_es": self.log_es,
            "s": self.s,
            "log_a_hi": self.log_a_hi,
        }

    def __call__(self, a):
        """Λ(a) for ``a = β tan θ ≥ 0`` (any shape)."""
        a = jnp.clip(jnp.asarray(a, self.p.dtype), 0.0, a_max(self.p.dtype))
        return _lambda_lookup(self.spline, *_a_parts(a), self.p, self._frame())

    def of_cos(self, cos_theta, beta):
        """Λ of a direction, ``Λ(β tan θ)``, from its ``cos θ ∈ [0, 1]`` and the roughness β.

        The same value as ``self(beta * geometry.tan_theta(cos_theta))`` to rounding, from
        ``a² = β² (1 − cos²θ)/cos²θ`` (the cosine floored at machine epsilon, as
        :func:`twoscale.geometry.tan_theta`) and ``log a = ½ log a²``: no square root, no
        separate ``tan θ``. The model's shadowing calls this once per direction.
        """
        _, a2, log_a = _a_parts_of_cos(cos_theta, beta, self.p.dtype)
        return _lambda_lookup(self.spline, a2, log_a, self.p, self._frame())

    def g1(self, a):
        """``G1 = 1/(1 + Λ(a))``."""
        return 1.0 / (1.0 + self(a))


def lambda_partials(cos_theta, beta, p):
    """Λ(β tan θ; p) of the table path and its partial derivatives along β and p, by hand.

    ``(Λ, ∂Λ/∂β, ∂Λ/∂p)``, each of ``cos_theta``'s shape; ``beta`` and ``p`` scalars. Λ is
    :meth:`SmithLambdaSpline.of_cos` of :func:`smith_lambda_spline` (the same value); the
    partials are those of that function, written out from :func:`_lambda_lookup`'s
    reconstruction ``log Λ = log a + log m + T(ξ) − v0 + log(1 + v0 + v0²/2)``:
    ``∂ log Λ/∂ log a = 1 + T'(ξ) ∂ξ/∂log a − (1 − q) ∂v0/∂log a`` with
    ``q = (1 + v0)/(1 + v0 + v0²/2)``, and along p the same terms at fixed a plus the
    table's own dependence on p (its slice's coefficients, ``log E[R]``, the coordinate's
    slope s and large-a edge, whose derivatives come from one JVP of the slice per call).
    Per sample this costs the slope and one tangent of the 1-D spline at the value's
    gathered coefficients and a few products, where forward-mode differentiation of the lookup pushed
    each tangent through every operation of it (the fit's Jacobian: G and its derivatives
    along β and p were about half of its time). Equal to ``jax.jvp`` of ``of_cos`` to
    rounding (``tests/test_shadowing.py``).
    """
    dtype = float_dtype(cos_theta, beta, p, default=float)
    p = jnp.asarray(p, dtype)
    # The slice (the value's, bit-equal) and its derivative along p from one JVP (per call).
    sl, dsl = jax.jvp(lambda q: smith_lambda_spline(q, dtype), (p,), (jnp.ones_like(p),))
    b = jnp.asarray(beta, dtype)
    # a², log a and the lookup's quantities once, for the value (as of_cos) and the partials;
    # ∂ log a/∂ log β = 1 between the floors of a².
    a2_raw, a2, log_a = _a_parts_of_cos(cos_theta, beta, dtype)
    moves = (a2_raw < a_max(dtype) ** 2) & (a2 > tiny(dtype))
    pc, s, log_a_hi = sl.p, sl.s, sl.log_a_hi
    d_p, d_log_es, d_s, d_log_a_hi = dsl.p, dsl.log_es, dsl.s, dsl.log_a_hi
    frame = sl._frame()
    k = _lookup_parts(a2, log_a, pc, frame)
    x, knee, v0 = k["x"], k["knee"], k["v0"]
    below_top = log_a < log_a_hi
    xi_free = (k["xi_raw"] > XI_LO) & (k["xi_raw"] < XI_HI)
    v0_free = k["expo"] < math.log(_V0_ZERO)
    t_val, slope, (t_p,) = sl.spline.value_slope_and_tangents(k["xi"], dsl.spline.coeffs)
    lam = _lambda_from_parts(t_val, log_a, k, frame)
    one_minus_q = 1.0 - (1.0 + v0) / (1.0 + v0 * (1.0 + 0.5 * v0))
    # Along log a.
    d_top = below_top.astype(dtype)
    d_knee = jnp.where((a2 > k["a2_lo"]) & (a2 < k["a2_hi"]), -x / (1.0 + x), 0.0)
    d_xi = jnp.where(xi_free, d_top - (s - 1.0) * d_knee, 0.0)
    d_v0 = jnp.where(v0_free, -2.0 * pc * v0 * d_top, 0.0)
    g_log_a = 1.0 + slope * d_xi - one_minus_q * d_v0
    # Along p at fixed a.
    d_top_p = jnp.where(below_top, 0.0, d_log_a_hi)
    d_log_a2_knee = jnp.where(
        a2 <= k["a2_lo"],
        math.log(V_MAX) / (pc * pc) * d_p,
        jnp.where(a2 >= k["a2_hi"], 2.0 * d_log_a_hi, 0.0),
    )
    d_knee_p = 0.5 * x * (-2.0 * d_log_es - d_log_a2_knee) / (1.0 + x)
    d_xi_p = jnp.where(xi_free, d_top_p + d_log_es - d_s * knee - (s - 1.0) * d_knee_p, 0.0)
    d_v0_p = jnp.where(v0_free, -2.0 * v0 * (d_p * k["log_a_top"] + pc * d_top_p), 0.0)
    g_p = d_log_es + t_p + slope * d_xi_p - one_minus_q * d_v0_p
    return lam, jnp.where(moves, lam * g_log_a / b, 0.0), lam * g_p


def smith_lambda_spline(p, dtype=None) -> SmithLambdaSpline:
    """Slice the Λ table at a scalar ``p`` (clamped to [P_MIN, P_MAX]) for cheap 1-D lookups.

    Args:
        p: EPD shape exponent, a scalar (may be traced).
        dtype: float32 or float64; default: that of ``p`` (JAX's default float for Python numbers).
    Returns:
        A :class:`SmithLambdaSpline`; ``spline_1d(a)`` gives Λ, ``spline_1d.g1(a)`` gives G1.
    """
    dtype = jnp.dtype(dtype or float_dtype(p, default=float))
    p = jnp.clip(jnp.asarray(p, dtype), P_MIN, P_MAX)
    if p.ndim != 0:
        raise ValueError(f"smith_lambda_spline needs a scalar p, got shape {p.shape}")
    frame = table_frame(p)
    spline = tables.spline(TABLE_NAME, dtype).slice(jnp.log(p))
    return SmithLambdaSpline(spline=spline, p=p, **frame)


# ---------------------------------------------------------------------------------------------
# Public kernels


def _check_path(path: str) -> None:
    if path not in ("tables", "exact"):
        raise ValueError(f"path must be 'tables' or 'exact', got {path!r}")


def smith_lambda_a(a, p, *, path: str = "tables"):
    """Smith ``Λ(a; p)`` of the EPD as a function of ``a = β tan θ`` [HP17 Eq. 36-37].

    ``Λ(a; p) = ∫_{1/a}^{∞} (r a − 1) P2(r) dr``; 0 at ``a = 0``, ``≈ a Γ(3/(2p))/(πΓ(1/p)) − 1/2``
    as ``a → ∞``. p = 1 is Beckmann: ``Λ = (erf μ − 1)/2 + e^{−μ²}/(2μ√π)``, ``μ = 1/a``.

    Args:
        a: ``β tan θ ≥ 0`` (any shape; negative values count as 0, ``inf`` is clamped to
            ``a_max(dtype)``).
        p: EPD shape exponent (broadcasts with ``a``); the table covers [0.1, 10] (clamped), the
            exact path any p in about [0.05, 15].
        path: ``"tables"`` (C² spline, ≤ 1e-4 relative) or ``"exact"`` (quadrature, ~1e-11).
    Returns:
        Λ ≥ 0, broadcast shape, dtype of the inputs.
    """
    _check_path(path)
    dtype = float_dtype(a, p, default=float)
    a, p = jnp.broadcast_arrays(jnp.asarray(a, dtype), jnp.asarray(p, dtype))
    a = jnp.clip(a, 0.0, a_max(dtype))
    return _lambda_exact(a, p) if path == "exact" else _lambda_table(a, p)


def smith_lambda(tan_theta, beta, p, *, path: str = "tables"):
    """Smith ``Λ`` of a direction: :func:`smith_lambda_a` at ``a = β tan θ``.

    Args:
        tan_theta: ``tan θ ≥ 0`` of the direction (e.g. ``geometry.tan_theta(cos θ)``).
        beta: EPD roughness β > 0.
        p: EPD shape exponent.
        path: ``"tables"`` or ``"exact"``.
    """
    tan_theta, beta = jnp.asarray(tan_theta), jnp.asarray(beta)
    # tan θ = inf (grazing) is clamped *before* the product: ∂a/∂β = tan θ = inf times the
    # clamp's zero slope would be NaN. Beyond a_max(dtype) Λ's table/asymptote is clamped anyway.
    # ≥ a_max/β for every β ≥ 1e-3
    t_max = a_max(float_dtype(tan_theta, beta, p, default=float)) / 1e-3
    return smith_lambda_a(beta * jnp.minimum(tan_theta, t_max), p, path=path)


def smith_g1(tan_theta, beta, p, *, path: str = "tables"):
    """Smith monodirectional masking ``G1 = 1/(1 + Λ(β tan θ; p))`` [HP17 Eq. 38]; 1 at normal."""
    return 1.0 / (1.0 + smith_lambda(tan_theta, beta, p, path=path))


def van_ginneken(phi):
    """Van Ginneken's azimuthal correlation ``λ(φ) = 4.41 φ/(4.41 φ + 1)``.

    ``φ`` is first wrapped into [0, π] (``|φ| mod 2π``, folded at π), which reciprocity and
    isotropy require (docs/model.md §3.3; the reference does not wrap). ``λ(0) = 0``, ``λ(π) ≈ 0.933``.

    Args:
        phi: relative azimuth ``φ_i − φ_o`` in radians, any real value.
    """
    r = jnp.mod(jnp.abs(phi), 2.0 * jnp.pi)
    phi = jnp.pi - jnp.abs(r - jnp.pi)
    return 4.41 * phi / (4.41 * phi + 1.0)


def joint_g_from_lambdas(lambda_i, lambda_o, phi, *, correlated: bool = True, wrapped=False):
    """Joint masking-shadowing ``G`` from the two directions' Λ (computed once each, then reused).

    Correlated [Heitz 2014, Eq. 101 with van Ginneken's λ]:
    ``G = 1/(1 + max(Λ_i, Λ_o) + λ(φ) min(Λ_i, Λ_o))``; uncorrelated: ``1/((1 + Λ_i)(1 + Λ_o))``.

    Args:
        lambda_i, lambda_o: Λ of the incident and outgoing directions (≥ 0, finite).
        phi: relative azimuth in radians (wrapped into [0, π]); unused when uncorrelated.
        correlated: which form (static Python bool).
        wrapped: ``phi`` already lies in [0, π] (as :func:`twoscale.geometry.frame` gives it), so
            :func:`van_ginneken`'s wrap is skipped: the same λ(φ) without the float64 ``mod``
            and without the rounding of ``π − (π − φ)`` (absolute ~1e-16, relative up to 1e-6
            for small φ).
    """
    if correlated:
        hi = jnp.maximum(lambda_i, lambda_o)
        lo = jnp.minimum(lambda_i, lambda_o)
        lam = 4.41 * phi / (4.41 * phi + 1.0) if wrapped else van_ginneken(phi)
        return 1.0 / (1.0 + hi + lam * lo)
    return 1.0 / ((1.0 + lambda_i) * (1.0 + lambda_o))


def joint_g_tangent(
    g, lambda_i, lambda_o, d_i, d_o, phi, *, correlated: bool = True, wrapped=False
):
    """The derivative of :func:`joint_g_from_lambdas`'s ``g`` (its value, passed in) along
    tangents ``d_i``, ``d_o`` of ``Λ_i``, ``Λ_o`` (``phi`` held fixed; the same arguments
    otherwise). Where ``Λ_i = Λ_o`` the max and the min are the same function: either branch."""
    if correlated:
        lam = 4.41 * phi / (4.41 * phi + 1.0) if wrapped else van_ginneken(phi)
        i_hi = lambda_i >= lambda_o
        return -g * g * (jnp.where(i_hi, d_i, d_o) + lam * jnp.where(i_hi, d_o, d_i))
    return -g * (d_i / (1.0 + lambda_i) + d_o / (1.0 + lambda_o))


def joint_g(tan_theta_i, tan_theta_o, phi, beta, p, *, correlated: bool = True, path="tables"):
    """Joint masking-shadowing ``G(i, o)`` of the EPD (docs/model.md §3.3), used by both lobes.

    Args:
        tan_theta_i, tan_theta_o: ``tan θ ≥ 0`` of the two directions.
        phi: relative azimuth ``φ_i − φ_o`` (radians).
        beta, p: EPD roughness and shape.
        correlated: height-direction correlated form (default) or the uncorrelated product.
        path: ``"tables"`` or ``"exact"``.
    """
    lam_i = smith_lambda(tan_theta_i, beta, p, path=path)
    lam_o = smith_lambda(tan_theta_o, beta, p, path=path)
    return joint_g_from_lambdas(lam_i, lam_o, phi, correlated=correlated)

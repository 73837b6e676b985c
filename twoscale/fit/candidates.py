"""Candidates: the starts that travel through the schedule, their bookkeeping (which minimum
each reached, which go on), fixed parameters, and the full model's starts from its special case.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from twoscale.fit.adapters import adapter_for
from twoscale.fit.residuals import Layout
from twoscale.fit.schedule import Stage
from twoscale.params import SHARED_FIELDS as _PARAM_SCALARS


@dataclasses.dataclass
class Candidate:
    """One start travelling through the schedule."""

    label: str
    group: int  # index into the list of groups (configuration, free-parameter layout)
    y: jax.Array
    cost: float = math.inf  # RMS of the residuals on the last stage's cells
    steps: int = 0
    status: str = "not run"
    success: bool = False
    rr: float = math.nan  # rᵀr at y on the last stage's cells
    jtj: np.ndarray | None = None  # JᵀJ at y on the last stage's cells
    m: int = 0  # residuals in that stage
    nested: bool = False  # the nested start: carried through every stage (see fit(nested=...))
    moves: int = 0  # accepted solver steps so far
    twin: str | None = None  # this stage: stopped on reaching this candidate's minimum


#: Two solutions closer than this many standard errors are the same minimum (see :func:`fit`).
DUPLICATE_SE = 0.5


def same_solution(a: Candidate, b: Candidate, tol: float = DUPLICATE_SE) -> bool:
    """Are ``a`` and ``b`` (same group, same stage) within ``tol`` standard errors of each other?

    The distance is measured with ``a``'s Gauss-Newton matrix and residual variance:
    ``δᵀ JᵀJ δ / σ²`` with ``δ = y_a − y_b`` and ``σ² = rᵀr/(m − n)``, the squared length of
    ``δ`` in standard errors along the best-determined and worst-determined directions alike.
    """
    if a.group != b.group or a.jtj is None or a.y.shape != b.y.shape:
        return False
    n = int(a.y.shape[0])
    d = np.asarray(a.y) - np.asarray(b.y)
    if n == 0 or not np.all(np.isfinite(d)):
        return n == 0
    sigma2 = a.rr / max(a.m - n, 1)
    if not (math.isfinite(sigma2) and sigma2 > 0.0):
        return False
    dist2 = float(d @ np.asarray(a.jtj) @ d) / sigma2
    return dist2 < tol * tol


@dataclasses.dataclass
class Group:
    adapter: object
    spec: object
    frozen: object
    layout: Layout


#: A_spec(0) of the diffraction lobe added to the nested start (weak, but with a non-zero
#: gradient in σ_s: at σ_s = 0 exactly, ∂A_s/∂σ_s = 0 and the solver could not leave it).
NESTED_A_SPEC = 0.95


NESTED_LABEL = "nested"


#: The other full-model starts from the special case: ``(c, A_spec(0), b µm)``. A diffraction
#: lobe carrying 70 % or 30 % of the specular energy at normal incidence with a halo of
#: half-width ≈ 15° (b = 1 µm); a strong lobe (A_spec(0) = 0.05, 95 % of the energy) with a
#: narrow core and a power-law tail (b = 30 µm), the basin of sharp highlights that widen towards
#: grazing θ_d (phenolics, plastics: the winning start on 4 of 8 stand-ins tried); and a strong,
#: wide lobe (b = 0.3 µm). Starts that end in the same minimum are dropped after the first stage.
NESTED_GRID = (
    (1.5, 0.3, 1.0),
    (2.5, 0.7, 1.0),
    (1.5, 0.05, 30.0),
    (1.5, 0.05, 0.3),
)


#: The start placed from the special case's highlight, ``(c, A_spec(0))`` with b from its β
#: (:func:`narrow_b`): a strong diffraction lobe (95 % of the specular energy at normal
#: incidence) as narrow as the special case's EPD lobe. Sharp highlights often end in that
#: basin (on the 60 stand-ins of 2026-12-05, 18 full-model fits ended with b ≥ 56 µm, 12 of
#: them at ≥ 319 µm), which the fixed b of :data:`NESTED_GRID` reach only from afar: on
#: pink-jasper's first stage, the starts of that grid and A_spec(0) = 0.3 at this b all went to
#: the special case (log RMS 0.0983 on 4 051 cells); A_spec(0) = 0.05 at b = 0.5, 1 and 2× this
#: b, with c = 1.5, 3 or 5, reached 0.0901.
NARROW_START = (1.5, 0.05)


def narrow_b(beta: float, wavelength: float) -> float:
    """b (µm) of a diffraction lobe as wide as an EPD lobe of roughness β.

    The K-correlation lobe falls as ``[1 + (2u sin θ_h)²]^{−(c+1)/2}``, ``u = (b/λ) cos θ_d``
    (docs/model.md §3.8): its width at normal incidence is ``sin θ_h ≈ λ/(2b)``; the EPD lobe's
    is ``tan θ_h ≈ β``. So ``b = λ/(2β)``, kept inside b's range (at most 0.9 of its top, so
    the start's sigmoid slope is not small).
    """
    from twoscale.params import bounds_for

    bound = bounds_for("b", None)
    return float(
        np.clip(wavelength / (2.0 * max(float(beta), 1e-12)), 2.0 * bound.lo, 0.9 * bound.hi)
    )


def nested_starts(params, cfg, fixed: dict, grid=NESTED_GRID) -> list[tuple[str, object]]:
    """Starts of the full model ``cfg`` from the fit of its diffraction-off special case.

    The specular parameters (β, p, η, k or ρ_d, e) are those of the special case's fit; the
    nano-scale ones are the nested start (``A_spec(0)`` = :data:`NESTED_A_SPEC`: the special case
    itself, with a weak diffraction lobe whose gradient is not 0), the points ``(c,
    A_spec(0), b µm)`` of ``grid`` (default :data:`NESTED_GRID`) and a strong lobe as narrow as
    the special case's EPD (:data:`NARROW_START`, b from :func:`narrow_b`). Parameters held
    fixed (``fixed``: σ_s, b or c) override these values; a point that then repeats an earlier
    one's ``(σ_s, b, c)`` is left out (it would fit the same start again).
    """
    from twoscale.fit.adapters import START_B, START_C, sigma_s_for_a_spec

    wl = float(np.median(np.asarray(cfg.wavelengths)))
    points = [(NESTED_LABEL, NESTED_A_SPEC, START_C[0], START_B)] + [
        (f"from the special case, c={c:g} A_spec(0)={a:g} b={b:g}", a, c, b) for c, a, b in grid
    ]
    c, a = NARROW_START
    b = narrow_b(float(params.beta), wl)
    points.append((f"as narrow as the special case, c={c:g} A_spec(0)={a:g} b={b:.3g}", a, c, b))
    out, seen = [], set()
    for label, a_spec, c, b in points:
        c = float(fixed.get("c", c))
        b = float(fixed.get("b", b))
        sigma_s = float(fixed.get("sigma_s", sigma_s_for_a_spec(a_spec, b, c, wl)))
        if (sigma_s, b, c) in seen:
            continue
        seen.add((sigma_s, b, c))
        out.append((label, params.replace(sigma_s=sigma_s, b=b, c=c).for_config(cfg)))
    return out


#: The parameters every material type shares: the surface's geometry (EPD and PSD) and MERL's
#: apparatus factor (e, m), which are the model's scalar fields (:data:`twoscale.params.
#: SHARED_FIELDS`, one value for all channels). A type's own parameters (a conductor's η and
#: k, a plastic's η and ρ_d) set the lobes' amplitudes and colour, which a solver moves easily;
#: the geometry sets the basin (:func:`cross_seed`).
SHARED_FIELDS = _PARAM_SCALARS


def cross_seed(src: Candidate, g_src: Group, dst: Candidate, g_dst: Group) -> Candidate | None:
    """A start for ``dst``'s type with the shared parameters (:data:`SHARED_FIELDS`) of ``src``'s
    fit (another type's) and ``dst``'s own type parameters; None when nothing would change.

    Why: the two types' full models start from their own special cases, and one type's starts
    can all miss the basin the other type found (tungsten-carbide on 2026-12-04: every conductor
    start ended near 0.446 on the first stage, the plastic's narrow-lobe start at 0.327 with
    almost the same geometry a conductor can take). A type's fit is compared with the other's
    only after both have searched the same basins. Fixed parameters stay as they are (they are
    frozen in ``g_dst``).
    """
    from twoscale.fit.residuals import Problem

    p_src = Problem(g_src.adapter, g_src.layout, "log").params(src.y, g_src.frozen)
    p_dst = Problem(g_dst.adapter, g_dst.layout, "log").params(dst.y, g_dst.frozen)
    free = g_dst.spec
    changes = {}
    for name in SHARED_FIELDS:
        a, b = getattr(p_src, name, None), getattr(p_dst, name, None)
        if a is None or b is None or getattr(free, name) is not True:
            continue
        changes[name] = jnp.broadcast_to(jnp.asarray(a, jnp.result_type(b)), jnp.shape(b))
    if not changes:
        return None
    u = g_dst.adapter.to_unconstrained(p_dst.replace(**changes))
    y = g_dst.layout.ravel(eqx.partition(u, g_dst.spec)[0])
    if np.allclose(np.asarray(y), np.asarray(dst.y), rtol=0.0, atol=1e-9):  # round-off only
        return None
    return Candidate(
        f"{_kind(g_dst.adapter.config)} with the geometry of [{src.label}]", dst.group, y
    )


#: Largest |u| of a free parameter at a start (u the sigmoid's argument, see
#: :class:`twoscale.params.Bound`): 1e-3 of the range inside a bound. A start on or beyond a
#: bound maps to |u| = 40, where the parameter's derivative is ≈ 4e-18 and no solver step moves
#: it (a conductor start with k = 12.5 for a range ending at 10 stayed at 10 for good).
START_U_MAX = 6.9


def inside_bounds(free):
    """Free unconstrained start values moved to at most :data:`START_U_MAX` from 0."""
    return jax.tree_util.tree_map(
        lambda u: jnp.clip(u, -START_U_MAX, START_U_MAX) if eqx.is_inexact_array(u) else u, free
    )


def check_fixed(fixed: dict, configs) -> None:
    """Refuse held values that no stage of the fit could hold as given, before any work.

    ``configs``: every configuration the fit may use (the types compared, their special cases
    and floors). A name must be a parameter of at least one of them; its values finite, one or
    one per channel, and inside the valid range of every configuration that uses it (a value
    outside would be clamped to the range's end without a word: ``p = 100`` fitted at
    ``p = 5``, ``β = 0`` at ``β = 1e-3``). Raises ``ValueError`` naming the parameter.
    """
    adapters = [adapter_for(c) for c in configs]
    names = list(dict.fromkeys(n for a in adapters for n in a.field_names))
    for name, value in fixed.items():
        users = [a for a in adapters if name in a.field_names]
        if not users:
            raise ValueError(f"cannot fix {name!r}: parameters of this fit are {', '.join(names)}")
        try:
            v = np.asarray(value, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise ValueError(
                f"cannot fix {name}: not a number or a list of numbers: {value!r}"
            ) from None
        shown = ", ".join(f"{x:g}" for x in v)
        if not np.all(np.isfinite(v)):
            raise ValueError(f"cannot fix {name} = {shown}: not a finite number")
        for a in users:
            sizes = a.field_sizes(name)
            if v.size not in sizes:
                counts = " or ".join(str(n) for n in sizes)
                raise ValueError(
                    f"cannot fix {name}: give {counts} value(s), got {v.size} ({shown})"
                )
            lo, hi = a.field_range(name)
            if np.any(v < lo) or np.any(v > hi):
                raise ValueError(
                    f"cannot fix {name} = {shown}: outside its valid range [{lo:g}, {hi:g}]"
                    f" ({a.material})"
                )


def apply_fixed(params, fixed: dict, adapter):
    """Set the fixed fields (physical values) and return (params, spec of free leaves)."""
    spec = jax.tree_util.tree_map(lambda _: True, params)
    for name, value in fixed.items():
        if name not in adapter.field_names:
            raise ValueError(
                f"cannot fix {name!r}: parameters of this model are {', '.join(adapter.field_names)}"
            )
        current = getattr(params, name)
        if current is None:
            raise ValueError(f"cannot fix {name!r}: this configuration does not use it")
        new = jnp.broadcast_to(jnp.asarray(value, dtype=jnp.float64), jnp.shape(current))
        params = eqx.tree_at(lambda p, n=name: getattr(p, n), params, new)
        spec = eqx.tree_at(lambda s, n=name: getattr(s, n), spec, False)
    return params, spec


def _kind(cfg) -> str:
    """The label prefix of a configuration's candidates: its material, and Schlick's form."""
    material = getattr(cfg, "material", None) or adapter_for(cfg).material
    return material + (" (Schlick)" if getattr(cfg, "fresnel", "exact") == "schlick" else "")


def make_candidates(configs, start_lists, fixed: dict):
    """Groups (one per configuration) and their candidates from ``[(label, params)]`` lists."""
    groups: list[Group] = []
    cands: list[Candidate] = []
    for cfg, start_list in zip(configs, start_lists, strict=True):
        adapter = adapter_for(cfg)
        group = None
        for label, p0 in start_list:
            p0, spec = apply_fixed(p0, fixed, adapter)
            free, frozen = eqx.partition(adapter.to_unconstrained(p0), spec)
            free = inside_bounds(free)
            layout = Layout.of(free)
            if group is None:
                group = Group(adapter, spec, frozen, layout)
                groups.append(group)
            elif layout != group.layout:
                raise ValueError("all starts must have the same parameter structure")
            cands.append(
                Candidate(
                    f"{_kind(cfg)} {label}",
                    len(groups) - 1,
                    layout.ravel(free),
                    nested=label.startswith(NESTED_LABEL),
                )
            )
    return groups, cands


def keep_best(cands, groups, stage: Stage, last: bool):
    """The best ``stage.keep`` *distinct* solutions per group (and the nested start, unless
    ``last``: the next stage is the last), and ``{dropped label: label of the better twin}``."""
    finite = [c for c in cands if math.isfinite(c.cost)]
    kept, duplicates = [], {}
    for gi in range(len(groups)):
        mine = sorted((c for c in finite if c.group == gi), key=lambda c: c.cost)
        chosen: list[Candidate] = []
        for c in mine:
            if c.twin is not None:  # stopped on its way into a finished start's minimum
                duplicates[c.label] = c.twin
                continue
            # A solution within DUPLICATE_SE standard errors of a better kept one is the same
            # minimum reached from another start: dropped, so no minimum is refined twice.
            twin = next((k for k in chosen if same_solution(k, c)), None)
            if twin is not None:
                duplicates[c.label] = twin.label
                continue
            # The nested start goes on even when a subsample ranks it lower, so that a later
            # stage compares it with the others on more cells.
            if last:
                if len(chosen) < stage.keep:
                    chosen.append(c)
            elif sum(not k.nested for k in chosen) < stage.keep or c.nested:
                chosen.append(c)
        kept.extend(chosen)
    return kept, duplicates

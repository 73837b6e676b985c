"""Device passes of a BRDF fit to MERL data: residuals, their normal equations, and the
compressed problem (the host-side preparation of the cells is :mod:`twoscale.fit.cells`).

Metrics (docs/model.md §8, Löw et al. 2012), per valid cell and channel, with ``ρ`` the BRDF (1/sr):

- ``"linear"``: ``r = (ρ_model − ρ_meas) cos θ_i``
- ``"log"``:    ``r = log(1 + ρ_model cos θ_i) − log(1 + ρ_meas cos θ_i)``
- ``"scaled-log"``: ``r = log(1 + ρ_model cos θ_i / s_c) − log(1 + ρ_meas cos θ_i / s_c)``, with
  ``s_c`` the median measured ``ρ cos θ_i`` of channel ``c`` over the fitted cells
  (:meth:`twoscale.fit.cells.Cells.log_scale`, carried by the buffer as ``1 / s_c``)
- ``"blend"``: both log residuals of every cell and channel, the scaled one and the plain one
  (two residuals per cell and channel; its RMS is that of all of them)

Layout for speed and memory. Data live in a *buffer* of fixed shape ``(n_chunks, CHUNK, ...)``
(:data:`PAIR_CHUNKS` chunks of reciprocal cell pairs for fitting, enough for every MERL cell;
:data:`DIRECTION_CHUNKS` chunks of single direction pairs for evaluation), padded with weight-0
entries; a dynamic count ``n_active`` says how many leading chunks hold data, and every pass over
the data is a ``scan`` over the chunks that skips the inactive ones. So one compiled function
serves every stage, every start and every material of a campaign (only the model configuration
and the set of free parameters change the compiled code), and memory stays bounded on the full
grid.

Factorised models. For an adapter with ``bin_terms`` (the two-scale model), each pass first
computes the factors of the model that depend on the ``(θ_h, θ_d)`` bin only (Fresnel, ``R``,
``A_s``, ``D``, the convolved lobe: 8 100 bins), with their tangents along every seed, once;
each chunk then gathers them by the pairs' bin indices and adds the per-cell factors
(shadowing, cosines). That is what makes a full-data pass cheap (``benchmarks/results``).
The bin factors stay apart as factors of ``θ_d`` (Fresnel, ``A_s``, ``R``: 90 × C values), of
``θ_h`` (``D``: 90) and of both (the lobe) and are multiplied per cell: differentiating their
products on every bin made each pass ≈ 9 ms (a third) slower on the first stage's 4 096 cells.
The per-cell part runs channel first (:func:`twoscale.model.brdf_from_factors`), which more
than halved its cost: normal equations on all 1.1 M cells of a synthetic conductor 807 → 373 ms.

The optimiser works on a flat vector ``y`` of the free unconstrained parameters (:class:`Layout`).
Each pass accumulates the normal equations ``(JᵀJ, Jᵀr, rᵀr)`` chunk by chunk (forward mode:
one vmapped ``jvp`` per seed of :meth:`Problem.seeds`, which colours the per-channel parameters).
Only the model's value at each pair is differentiated; the metric enters as a weight per pair
and channel (:func:`chunk_normal_equations`), and the Gram products run over pairs, not over
the residuals' rows. Against rows built as residuals and differentiated (the code before
2026-12-07, fourteenth session; one process, both compiled, 12 warm runs each, alternating, on
the 2-core machine), medians on all 1.1 M cells: the reference conductor 306 → 258 ms, the
MERL protocol's plastic 392 → 300 ms and its conductor with the floor 432 → 315 ms, the same
normal equations to 6e-16.
Levenberg-Marquardt only ever needs those: :func:`compressed_residuals` returns an
``(n+1)``-vector ``r̃ = [L⁻¹ Jᵀr, √(rᵀr − |L⁻¹ Jᵀr|²)]`` with Jacobian ``J̃ = [Lᵀ; 0]``
(``JᵀJ + εI = L Lᵀ``, Cholesky, ε a 1e-13 relative jitter), for which ``|r̃|² = |r|²``,
``J̃ᵀJ̃ = JᵀJ + εI`` and ``J̃ᵀr̃ = Jᵀr``: the same objective, gradient and Gauss-Newton matrix as
the full residual vector,
so the solver's steps, trust-region ratios and accept/reject decisions are those of the full
problem, while its linear algebra is ``(n+1) × n`` instead of ``3.3 M × n``.

Reciprocal pairs. The MERL cells ``(θ_h, θ_d, φ_d)`` and ``(θ_h, θ_d, π − φ_d)`` hold the same
direction pair with ``i`` and ``o`` swapped (and mirrored in the plane ``y = 0``), so a reciprocal,
isotropic model has the same value at both. :func:`pair_cells` groups the fitted cells in such
pairs and the model is evaluated once per pair, halving the cost of every pass; each member keeps
its own measurement and its own weight ``cos θ_i`` (``cos θ_o`` of the first member for the second).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

METRICS = ("blend", "log", "scaled-log", "linear")

#: The default metric (docs/model.md §8): on the 60 Neural-BRDF stand-ins it lowered the full
#: model's plain log RMSE on 47 and raised it on none against the scaled log metric alone, and
#: removed the materials whose linear RMSE was more than 2× a baseline's (campaigns/RESULTS.md).
DEFAULT_METRIC = "blend"


def residuals_per_cell(metric: str) -> int:
    """Residuals per cell and channel: 2 for ``"blend"`` (scaled and plain log), else 1."""
    return 2 if metric == "blend" else 1


def check_metric(metric: str) -> str:
    if metric not in METRICS:
        raise ValueError(f"metric must be one of {METRICS}, got {metric!r}")
    return metric


def _chunk_at(data, i):
    return jax.tree_util.tree_map(lambda a: jax.lax.dynamic_index_in_dim(a, i, 0, False), data)


#: Chunks of a pair buffer handled together by one step of a pass (:func:`_fold_chunks`). The
#: buffer's chunks (:data:`twoscale.fit.cells.CHUNK` pairs) are the granularity of the stages'
#: subsamples; each step of a pass costs a fixed ≈ 0.2 ms on top of its work (its dozens of
#: XLA kernels), so a pass takes four of them at a time: normal equations on all 1.1 M cells of
#: a synthetic conductor ≈ 325 → 285 ms. Two at a time: 314 ms on all cells, but 9.5 against
#: 11.5 ms on the first stage's ≈ 4 000 cells (2 chunks), where four compute 2 masked chunks.
FOLD = 4

#: Entries of a pair buffer that hold one value per chunk, not one per pair.
PER_CHUNK = ("s",)


def _fold_chunks(step, init, data, n_active, fold: int | None = None):
    """``acc = step(acc, chunk)`` over the first ``n_active`` chunks of ``data``.

    A ``scan`` over the chunk indices whose body skips the inactive ones (``cond``); an active
    step slices its chunk out of the buffer inside the ``cond``. (Scanning over the chunks
    themselves made XLA copy every chunk's slice, active or not: 7.7 ms of an 18.8 ms pass on
    the first stage's 4 096 cells, 2 active chunks of 360, measured on the 2-core machine.)

    ``fold`` consecutive chunks (default :data:`FOLD` where it divides the number of chunks,
    else 1) go to ``step`` as one: a free reshape of the buffer. The weights ``w`` of pairs in
    chunks from ``n_active`` on are set to 0 there, so the result is that of ``n_active`` chunks
    (up to the order of the sums).
    """
    n_chunks, chunk = jax.tree_util.tree_leaves(data)[0].shape[:2]
    if fold is None:
        fold = FOLD if n_chunks % FOLD == 0 else 1
    if n_chunks % fold:
        raise ValueError(f"fold {fold} does not divide {n_chunks} chunks")
    if fold > 1:
        data = {
            k: v[::fold]
            if k in PER_CHUNK
            else v.reshape(n_chunks // fold, fold * chunk, *v.shape[2:])
            for k, v in data.items()
        }

    def active_step(acc, i):
        part = _chunk_at(data, i)
        if fold > 1:
            granule = jnp.arange(fold * chunk) // chunk
            active = i * fold + granule < n_active
            w = part["w"]
            part = {**part, "w": jnp.where(active.reshape(-1, *(1,) * (w.ndim - 1)), w, 0.0)}
        return step(acc, part)

    def body(acc, i):
        return jax.lax.cond(i * fold < n_active, active_step, lambda a, _: a, acc, i), None

    return jax.lax.scan(body, init, jnp.arange(n_chunks // fold))[0]


# --------------------------------------------------------------------------------------------
# Flat free-parameter vector
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Layout:
    """Ravel / unravel the free leaves of an (unconstrained) parameter pytree.

    ``free`` is the first output of ``eqx.partition(u, spec)`` (frozen leaves are None); the
    layout is static and hashable, so compiled solves are reused for every start.
    """

    treedef: Any
    shapes: tuple[tuple[int, ...], ...]
    names: tuple[str, ...] = ()  # field name of each free leaf

    @classmethod
    def of(cls, free) -> Layout:
        with_path, treedef = jax.tree_util.tree_flatten_with_path(free)
        names = tuple(
            getattr(path[0], "name", str(path[0])) if path else "" for path, _ in with_path
        )
        return cls(treedef, tuple(tuple(np.shape(leaf)) for _, leaf in with_path), names)

    @property
    def sizes(self) -> tuple[int, ...]:
        return tuple(math.prod(s) for s in self.shapes)

    @property
    def size(self) -> int:
        return sum(self.sizes)

    def ravel(self, free) -> jax.Array:
        leaves = jax.tree_util.tree_leaves(free)
        if not leaves:
            return jnp.zeros((0,), dtype=jnp.float64)
        return jnp.concatenate([jnp.ravel(jnp.asarray(x, dtype=jnp.float64)) for x in leaves])

    def unravel(self, y):
        leaves, start = [], 0
        for shape, size in zip(self.shapes, self.sizes, strict=True):
            leaves.append(jnp.reshape(y[start : start + size], shape))
            start += size
        return jax.tree_util.tree_unflatten(self.treedef, leaves)


class Problem(eqx.Module):
    """One least-squares problem: model adapter, layout, metric.

    The layout and the metric are static; the adapter is a pytree whose configuration is
    static and whose arrays (a two-scale dielectric coat's Fresnel form) are arguments of the
    compiled functions, so that the problems of a fit's Fresnel twins share them.
    """

    adapter: Any
    layout: Layout = eqx.field(static=True)
    metric: str = eqx.field(static=True)

    def seeds(self) -> tuple[np.ndarray, np.ndarray]:
        """Compressed forward-mode seeds (Curtis-Powell-Reid colouring over the channels).

        Element ``c`` of a field the adapter declares *separable* (``adapter.separable_fields``)
        only changes output channel ``c`` (e.g. a conductor's η_c, k_c), so one tangent with a 1
        in every element of that field gives all its columns at once, each read off its own
        channel. Returns ``(seed (s, n), mask (n, C), owner (n,))``: column ``j`` of the Jacobian
        is the JVP along ``seed[owner[j]]`` restricted to the channels where ``mask[j]`` is 1.
        """
        n_ch = self.adapter.config.n_channels
        separable = set(self.adapter.separable_fields)
        rows, mask, owner = [], [], []
        start = 0
        for name, shape, size in zip(
            self.layout.names, self.layout.shapes, self.layout.sizes, strict=True
        ):
            cols = range(start, start + size)
            if name in separable and shape == (n_ch,) and n_ch > 1:
                seed = np.zeros(self.layout.size)
                seed[list(cols)] = 1.0
                rows.append(seed)
                for c, _ in enumerate(cols):
                    m = np.zeros(n_ch)
                    m[c] = 1.0
                    mask.append(m)
                    owner.append(len(rows) - 1)
            else:
                for j in cols:
                    seed = np.zeros(self.layout.size)
                    seed[j] = 1.0
                    rows.append(seed)
                    mask.append(np.ones(n_ch))
                    owner.append(len(rows) - 1)
            start += size
        n = self.layout.size
        seed = np.asarray(rows).reshape(-1, n)
        return seed, np.asarray(mask).reshape(n, n_ch), np.asarray(owner, dtype=np.int64)

    def params(self, y, frozen):
        """Physical parameters for the flat free vector ``y`` and the frozen leaves."""
        return self.adapter.from_unconstrained(eqx.combine(self.layout.unravel(y), frozen))

    @property
    def factorised(self) -> bool:
        """Does the adapter split its model into per-bin terms and a per-cell part?"""
        return self.adapter.factorised

    def terms(self, y, frozen):
        """``(params, the adapter's per-bin terms)`` at ``y`` (computed once per pass), or None.

        The physical parameters travel with the bin terms so that a pass maps ``y`` to them
        (and differentiates that map) once, not once per chunk: that per-chunk work, dozens of
        small operations on scalars, was ≈ 8 % of a pass over all cells in 2 048-pair chunks.
        """
        if not self.factorised:
            return None
        params = self.params(y, frozen)
        return params, self.adapter.bin_terms(params)

    def chunk_prediction(self, y, frozen, chunk, terms=None) -> jax.Array:
        """The model at one chunk of pairs, ``(chunk, 1, C)``.

        ``terms``: :meth:`terms` at ``y`` for a factorised adapter (the model is then evaluated
        from the pairs' bin indices and cosines, and ``y`` is not used), None for the others
        (from the directions).
        """
        if terms is None:
            pred = self.adapter.evaluate(self.params(y, frozen), chunk["wi"], chunk["wo"])
        else:
            params, bins = terms
            pred = self.adapter.evaluate_cells(params, bins, chunk)
        return pred[:, None, :]

    def chunk_residual(self, y, frozen, chunk, terms=None) -> jax.Array:
        """Residuals of one chunk of pairs, flattened ``(chunk × 2 × C,)`` (``× 2`` again for
        ``"blend"``); absent members give 0. ``terms``: see :meth:`chunk_prediction`."""
        pred = self.chunk_prediction(y, frozen, chunk, terms)
        return metric_residual(pred, chunk, self.metric).reshape(-1)


def metric_residual(pred, chunk, metric: str):
    """Weighted residuals ``(chunk, 2, C)`` of predictions ``(chunk, 1, C)`` against both members
    (``(chunk, 4, C)`` for ``"blend"``: the scaled log residuals of both members, then the plain
    log ones)."""
    cos = chunk["cos"][..., None]
    w = chunk["w"][..., None]

    def log_residual(weight, measured):
        return (jnp.log1p(pred * weight) - measured) * w

    if metric == "log":
        return log_residual(cos, chunk["log"])
    if metric == "scaled-log":
        return log_residual(cos * chunk["s"], chunk["log_s"])
    if metric == "blend":
        return jnp.concatenate(
            [log_residual(cos * chunk["s"], chunk["log_s"]), log_residual(cos, chunk["log"])],
            axis=-2,
        )
    return (pred - chunk["rho"]) * cos * w


def metric_slopes(pred, chunk, metric: str):
    """The residuals of predictions ``(chunk, 1, C)`` as seen by the normal equations:
    ``(values, slopes, rᵀr)``, where ``values`` and ``slopes`` are tuples of ``(chunk, 2, C)``
    arrays, one per residual of a member (two for ``"blend"``), and each residual's derivative
    is its slope times the derivative of the prediction (the members of a pair share the
    model's value, and each metric is a function of that value alone):

    - ``"linear"``: slope ``w cos θ_i``;
    - the log metrics: ``w k / (1 + ρ k)`` for ``k = cos θ_i`` (plain) or ``cos θ_i / s_c``
      (scaled); ``"blend"``: both.
    """
    parts = ("scaled-log", "log") if metric == "blend" else (metric,)
    values = tuple(metric_residual(pred, chunk, m) for m in parts)
    cos = chunk["cos"][..., None]
    w = chunk["w"][..., None]

    def slope(m):
        if m == "linear":
            return cos * w
        k = cos * chunk["s"] if m == "scaled-log" else cos
        return w * k / (1.0 + pred * k)

    return values, tuple(slope(m) for m in parts), sum(jnp.sum(r * r) for r in values)


def sum_squares(problem: Problem, y, frozen, data, n_active) -> jax.Array:
    """``rᵀr`` over the active chunks (primal only)."""
    terms = problem.terms(y, frozen)

    def step(acc, chunk):
        r = problem.chunk_residual(y, frozen, chunk, terms)
        return acc + jnp.sum(r * r)

    return _fold_chunks(step, jnp.zeros((), y.dtype), data, n_active)


def linearised_terms(problem: Problem, y, frozen):
    """:meth:`Problem.terms` at ``y`` and their tangents along every seed, or ``(None, None)``."""
    if not problem.factorised:
        return None, None
    seeds = jnp.asarray(problem.seeds()[0], dtype=y.dtype)

    def terms(yy):
        return problem.terms(yy, frozen)

    return jax.vmap(lambda t: jax.jvp(terms, (y,), (t,)), out_axes=(None, 0))(seeds)


def chunk_normal_equations(problem: Problem, y, frozen, chunk, terms=None, terms_dot=None):
    """Per channel, the Gram matrix of one chunk's Jacobian on the compressed seeds and its
    product with the residuals, ``(C, s, s)`` and ``(C, s)``, and the chunk's ``rᵀr``.

    The model is differentiated once per pair of cells: ``dρ`` along every seed, ``(s, n, C)``.
    Every residual of the pair's members is a function of the pair's ``ρ`` alone, with
    derivative ``a dρ`` (:func:`metric_slopes`), so the pair adds ``W dρ_a dρ_b`` to the Gram
    matrix and ``V dρ_a`` to its product with the residuals, ``W = Σ a²`` and ``V = Σ a r`` over
    its residuals (2 members, × 2 for ``"blend"``): one ``(s, n) × (n, s)`` product per channel
    instead of one over all the residuals' rows. A per-channel parameter's column is its seed's
    column on its own channel and 0 on the others (:func:`_expand`).

    ``terms``, ``terms_dot``: :func:`linearised_terms` (factorised adapters), computed once per
    pass: the per-bin part of the model is differentiated once, not once per chunk.
    """
    if terms is None:
        seeds = jnp.asarray(problem.seeds()[0], dtype=y.dtype)

        def f(yy):
            return problem.chunk_prediction(yy, frozen, chunk)[:, 0]

        pred, d_pred = jax.vmap(lambda t: jax.jvp(f, (y,), (t,)), out_axes=(None, 0))(seeds)
    else:

        def f2(tt):  # the terms carry the parameters: y enters through them alone
            return problem.chunk_prediction(None, frozen, chunk, tt)[:, 0]

        pred, d_pred = jax.vmap(lambda td: jax.jvp(f2, (terms,), (td,)), out_axes=(None, 0))(
            terms_dot
        )
    values, slopes, rr = metric_slopes(pred[:, None], chunk, problem.metric)
    # Sums over the members written out (a reduction over an axis of 2 was slower on CPU).
    weight = sum(a[:, 0] * a[:, 0] + a[:, 1] * a[:, 1] for a in slopes)
    v = sum(a[:, 0] * r[:, 0] + a[:, 1] * r[:, 1] for a, r in zip(slopes, values, strict=True))
    scaled = d_pred * jnp.sqrt(weight)
    hi = jax.lax.Precision.HIGHEST
    gram = jnp.einsum("anc,bnc->cab", scaled, scaled, precision=hi)
    proj = jnp.einsum("anc,nc->ca", d_pred, v, precision=hi)
    return gram, proj, rr


def _expand(problem: Problem, gram, proj):
    """``(JᵀJ, Jᵀr)`` of the free parameters from the per-channel blocks of
    :func:`chunk_normal_equations`: ``JᵀJ[i, j] = Σ_c mask[i, c] mask[j, c] P_c[owner i,
    owner j]`` (accumulating the ``s × s`` blocks per channel multiplies ``s² = 49`` instead
    of ``n² = 121`` numbers per pair for a conductor's 11 parameters and 7 seeds, and never
    builds the expanded Jacobian)."""
    _, mask, owner = problem.seeds()
    m = jnp.asarray(mask, gram.dtype)  # (n, C)
    o = np.asarray(owner)
    jtj = jnp.einsum("ic,jc,cij->ij", m, m, gram[:, o][:, :, o])
    jtr = jnp.einsum("ic,ci->i", m, proj[:, o])
    return jtj, jtr


def normal_equations(problem: Problem, y, frozen, data, n_active):
    """``(JᵀJ, Jᵀr, rᵀr)`` over the active chunks, without keeping the Jacobian (accumulated per
    channel on the compressed seeds, :func:`chunk_normal_equations`)."""
    terms, terms_dot = linearised_terms(problem, y, frozen)
    n_seeds = problem.seeds()[0].shape[0]
    n_ch = problem.adapter.config.n_channels

    def step(acc, chunk):
        gram, proj, rr_chunk = chunk_normal_equations(problem, y, frozen, chunk, terms, terms_dot)
        g_acc, p_acc, rr = acc
        return g_acc + gram, p_acc + proj, rr + rr_chunk

    init = (
        jnp.zeros((n_ch, n_seeds, n_seeds), y.dtype),
        jnp.zeros((n_ch, n_seeds), y.dtype),
        jnp.zeros((), y.dtype),
    )
    gram, proj, rr = _fold_chunks(step, init, data, n_active)
    jtj, jtr = _expand(problem, gram, proj)
    return jtj, jtr, rr


#: Relative jitter added to the diagonal of JᵀJ before its Cholesky factorisation, so that a
#: rank-deficient JᵀJ still factorises (it acts like a tiny Levenberg-Marquardt damping).
_JITTER = 1e-13


def _compress(jtj, jtr, rr):
    """``(r̃, J̃)`` with ``|r̃|² = rr``, ``J̃ᵀJ̃ = JᵀJ + εI``, ``J̃ᵀr̃ = Jᵀr`` (see module doc).

    ``JᵀJ + εI = L Lᵀ`` (Cholesky: unique, continuous in y, so r̃ changes smoothly along the
    iterations and the solver's convergence test on r̃ is meaningful), ``J̃ = [Lᵀ; 0]``,
    ``r̃ = [L⁻¹ Jᵀr; √(rr − |L⁻¹ Jᵀr|²)]``.
    """
    n = jtj.shape[0]
    scale = jnp.maximum(jnp.max(jnp.diag(jtj)), jnp.finfo(jtj.dtype).tiny)
    chol = jnp.linalg.cholesky(jtj + _JITTER * scale * jnp.eye(n, dtype=jtj.dtype))
    q = jax.scipy.linalg.solve_triangular(chol, jtr, lower=True)
    tail = jnp.sqrt(jnp.maximum(rr - q @ q, 0.0))
    r_c = jnp.concatenate([q, tail[None]])
    j_c = jnp.concatenate([chol.T, jnp.zeros((1, n), jtj.dtype)])
    return r_c, j_c


def compressed_residuals(problem: Problem, y, frozen, data, n_active) -> jax.Array:
    """The ``(n+1)``-vector ``r̃`` equivalent to the full residuals (see module doc).

    Its derivative in ``y`` is ``J̃`` (``frozen`` and ``data`` are constants). It is written as
    ``r̃(y₀) + J̃(y₀)(y − y₀)`` with ``y₀ = stop_gradient(y)`` rather than as a ``custom_jvp``:
    a ``custom_jvp`` traces the model twice (its primal and its rule) every time a solver
    evaluates the residuals, this form once; tracing the model is seconds of a compiled solve.
    """
    y0, frozen, data = jax.lax.stop_gradient((y, frozen, data))
    r_c, j_c = _compress(*normal_equations(problem, y0, frozen, data, n_active))
    return r_c + j_c @ (y - y0)


def predict(fn, params, data, n_active, n_out: int) -> jax.Array:
    """``fn(params, wi, wo)`` at the buffer's cells, ``(n_chunks, chunk, n_out)`` (inactive chunks 0)."""
    n_chunks, chunk = data["wi"].shape[:2]

    def body(i, out):
        ch = _chunk_at(data, i)
        pred = fn(params, ch["wi"], ch["wo"])
        return jax.lax.dynamic_update_index_in_dim(out, pred.astype(out.dtype), i, 0)

    out = jnp.zeros((n_chunks, chunk, n_out), dtype=data["wi"].dtype)
    return jax.lax.fori_loop(0, n_active, body, out)

"""Residuals of a BRDF fit to MERL data, their normal equations, and the compressed problem.

Metrics (docs/model.md §8, Löw et al. 2012), per valid cell and channel, with ``ρ`` the BRDF (1/sr):

- ``"linear"``: ``r = (ρ_model − ρ_meas) cos θ_i``
- ``"log"``:    ``r = log(1 + ρ_model cos θ_i) − log(1 + ρ_meas cos θ_i)``

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

The optimiser works on a flat vector ``y`` of the free unconstrained parameters (:class:`Layout`).
Each pass accumulates the normal equations ``(JᵀJ, Jᵀr, rᵀr)`` chunk by chunk (forward mode:
one vmapped ``jvp`` per seed of :meth:`Problem.seeds`, which colours the per-channel parameters).
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
import functools
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

METRICS = ("log", "linear")

#: Entries (cell pairs, or direction pairs) per chunk of a pass over the data: the granularity of
#: the subsample stages (2 048 pairs ≈ 4 000 cells).
CHUNK = 2048
#: Chunks of a fitting buffer: at most 90·90·91 reciprocal pairs (φ_d bins 0…90 are the first
#: members) fit in 360 × 2048.
PAIR_CHUNKS = -(-(90 * 90 * 91) // CHUNK)
#: Chunks of an evaluation buffer: every one of the 90·90·180 MERL cells fits in 712 × 2048.
DIRECTION_CHUNKS = -(-(90 * 90 * 180) // CHUNK)


def check_metric(metric: str) -> str:
    if metric not in METRICS:
        raise ValueError(f"metric must be one of {METRICS}, got {metric!r}")
    return metric


# --------------------------------------------------------------------------------------------
# Cells: the valid part of a MERL table, flattened (NumPy, host side)
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Cells:
    """Valid MERL cells, flattened: directions, measured values and their grid index.

    Attributes:
        wi, wo: ``(N, 3)`` unit directions (lower-edge bin convention).
        rho: ``(N, C)`` measured BRDF (1/sr).
        index: ``(N,)`` flat index into the ``(90, 90, 180)`` grid.
    """

    wi: np.ndarray
    wo: np.ndarray
    rho: np.ndarray
    index: np.ndarray

    def __len__(self) -> int:
        return int(self.wi.shape[0])

    @property
    def cos_i(self) -> np.ndarray:
        return self.wi[:, 2]

    def take(self, idx) -> Cells:
        return Cells(self.wi[idx], self.wo[idx], self.rho[idx], self.index[idx])

    def within(self, max_theta_deg: float) -> np.ndarray:
        """Mask of the cells with ``θ_i, θ_o ≤ max_theta_deg`` (1e-12 slack on the cosines)."""
        cmin = math.cos(math.radians(max_theta_deg)) - 1e-12
        return (self.wi[:, 2] >= cmin) & (self.wo[:, 2] >= cmin)


@dataclasses.dataclass(frozen=True)
class CellSelection:
    """Which cells of a MERL table enter the fit and the reported errors."""

    valid: Cells  # all valid cells above the horizon: the reported RMSE uses these
    fit: Cells  # the cells fitted (valid, optionally θ_i, θ_o ≤ max_theta)
    n_measured_valid: int  # cells the file marks valid (before the horizon test)
    n_below_horizon: int  # valid in the file but at/below the horizon in the bin convention


def select_cells(data, *, max_theta_deg: float | None = None, convention: str = "lower"):
    """Flatten a :class:`twoscale.merl.MerlData` to the cells used by a fit.

    A cell is *valid* when the file marks it valid and both directions are above the horizon
    in the bin convention (the model is 0 below it; such cells are counted, not fitted). With
    ``max_theta_deg`` the fitted cells also have ``θ_i, θ_o ≤ max_theta_deg``; the reported
    RMSE always uses all valid cells.

    Raises:
        ValueError: no valid cell (or none left after the angle cut), or a bad angle.
    """
    if max_theta_deg is not None and not 0.0 < max_theta_deg <= 90.0:
        raise ValueError(f"max_theta_deg must be in (0, 90], got {max_theta_deg}")
    values = np.asarray(data.values, dtype=np.float64)
    valid = np.asarray(data.valid, dtype=bool)
    wi, wo = data.directions(convention)
    wi = np.asarray(wi, dtype=np.float64).reshape(-1, 3)
    wo = np.asarray(wo, dtype=np.float64).reshape(-1, 3)
    n_ch = values.shape[-1]
    rho = values.reshape(-1, n_ch)
    valid = valid.reshape(-1) & np.all(np.isfinite(rho), axis=-1)
    keep = valid & (wi[:, 2] > 0.0) & (wo[:, 2] > 0.0)
    n_meas = int(valid.sum())
    if not keep.any():
        raise ValueError("no valid cell in the data (every cell is masked or below the horizon)")
    index = np.flatnonzero(keep)
    cells = Cells(wi[index], wo[index], rho[index], index)
    fit_cells = cells
    if max_theta_deg is not None:
        ok = cells.within(max_theta_deg)
        if not ok.any():
            raise ValueError(f"no valid cell with θ_i, θ_o ≤ {max_theta_deg}°")
        fit_cells = cells.take(np.flatnonzero(ok))
    return CellSelection(cells, fit_cells, n_meas, n_meas - int(keep.sum()))


@dataclasses.dataclass(frozen=True)
class Pairs:
    """Fitted cells grouped in reciprocal pairs (see module doc).

    Attributes:
        wi, wo: ``(P, 3)`` directions of the pair's first member (``φ_d ≤ 90°``).
        rho: ``(P, 2, C)`` measured values of both members (0 where absent).
        cos: ``(P, 2)`` ``cos θ_i`` of both members (the second's is the first's ``cos θ_o``).
        w: ``(P, 2)`` 1 where the member is a fitted cell, else 0.
        ih, jd: ``(P,)`` the pair's θ_h and θ_d bin indices (shared by both members).
        phi: ``(P,)`` azimuth difference ``|φ_i − φ_o|`` of the pair (shared by both members).
    """

    wi: np.ndarray
    wo: np.ndarray
    rho: np.ndarray
    cos: np.ndarray
    w: np.ndarray
    ih: np.ndarray
    jd: np.ndarray
    phi: np.ndarray

    def __len__(self) -> int:
        return int(self.wi.shape[0])

    @property
    def n_cells(self) -> int:
        return int(self.w.sum())

    def take(self, idx) -> Pairs:
        return Pairs(*(getattr(self, f.name)[idx] for f in dataclasses.fields(self)))


def pair_cells(cells: Cells) -> Pairs:
    """Group MERL cells (lower-edge directions) with their reciprocal partners.

    The partner of ``i_φ = k`` is ``180 − k``; ``k = 0`` and ``k = 90`` are their own partners and
    stay single. A pair's directions are those of its member with ``k ≤ 90``.
    """
    from twoscale import merl
    from twoscale.geometry import _azimuth_difference, _dirs_from_half_diff

    idx = np.asarray(cells.index, dtype=np.int64)
    k = idx % merl.N_PHI_D
    second = k > 90
    first_index = np.where(second, idx - k + (merl.N_PHI_D - k), idx)
    keys, slot_pair = np.unique(first_index, return_inverse=True)
    n_ch = cells.rho.shape[-1]
    rho = np.zeros((keys.size, 2, n_ch))
    cos = np.zeros((keys.size, 2))
    w = np.zeros((keys.size, 2))
    slot = second.astype(np.int64)
    rho[slot_pair, slot] = cells.rho
    w[slot_pair, slot] = 1.0
    ih, rest = np.divmod(keys, merl.N_THETA_D * merl.N_PHI_D)
    jd, kp = np.divmod(rest, merl.N_PHI_D)
    wi, wo = _dirs_from_half_diff(np, *merl.bin_to_angles(ih, jd, kp, "lower"))
    cos[:, 0] = wi[:, 2]
    cos[:, 1] = wo[:, 2]
    phi = _azimuth_difference(np, wi, wo, np.finfo(np.float64).eps ** 2)
    return Pairs(wi, wo, rho, cos, w, ih.astype(np.int32), jd.astype(np.int32), phi)


def pack(pairs: Pairs, n_chunks: int = PAIR_CHUNKS, chunk: int = CHUNK):
    """Pairs → device buffer ``{wi, wo, rho, cos, w, hd, phi}``, ``(n_chunks, chunk, ...)``.

    ``hd = 90 ih + jd``: the pair's ``(θ_h, θ_d)`` bin.

    Padding entries repeat the first pair (finite everywhere) with weight ``w = 0``.
    Returns ``(buffer, n_active)``: the number of leading chunks that hold pairs.
    """
    n = len(pairs)
    cap = n_chunks * chunk
    if n > cap:
        raise ValueError(f"{n} pairs do not fit a buffer of {n_chunks} × {chunk}")
    n_active = max(1, -(-n // chunk))
    pad = cap - n

    def padded(a, fill=None):
        a = np.asarray(a)
        a = a if np.issubdtype(a.dtype, np.integer) else a.astype(np.float64)
        if fill is not None:
            tail = np.full((pad,) + a.shape[1:], fill)
        else:
            tail = np.broadcast_to(a[:1], (pad,) + a.shape[1:])
        return np.concatenate([a, tail], axis=0).reshape((n_chunks, chunk) + a.shape[1:])

    buf = {
        "wi": padded(pairs.wi),
        "wo": padded(pairs.wo),
        "rho": padded(pairs.rho),
        "cos": padded(pairs.cos),
        "w": padded(pairs.w, fill=0.0),
        "hd": padded(pairs.ih * N_BINS_D + pairs.jd),
        "phi": padded(pairs.phi),
    }
    return {k: jnp.asarray(v) for k, v in buf.items()}, n_active


def pack_directions(wi, wo, n_chunks: int = DIRECTION_CHUNKS, chunk: int = CHUNK):
    """Directions → device buffer ``{wi, wo}`` of shape ``(n_chunks, chunk, 3)`` (for :func:`predict`).

    Padding repeats the normal direction. Returns ``(buffer, n_active)``.
    """
    n = wi.shape[0]
    if n > n_chunks * chunk:
        raise ValueError(f"{n} directions do not fit a buffer of {n_chunks} × {chunk}")
    out = {}
    for name, a in (("wi", wi), ("wo", wo)):
        buf = np.empty((n_chunks * chunk, 3))
        buf[:n] = a
        buf[n:] = (0.0, 0.0, 1.0)
        out[name] = jnp.asarray(buf.reshape(n_chunks, chunk, 3))
    return out, max(1, -(-n // chunk))


def _chunk_at(data, i):
    return jax.tree_util.tree_map(lambda a: jax.lax.dynamic_index_in_dim(a, i, 0, False), data)


#: θ_d bins of the MERL grid (``hd = N_BINS_D · ih + jd``) and all (θ_h, θ_d) bins.
N_BINS_D = 90
N_BINS = 90 * 90
#: Bin lists of a stage are padded to a multiple of this (one compiled size per multiple).
BIN_BLOCK = 1024


def stage_bins(pairs: Pairs, n_pairs: int):
    """The (θ_h, θ_d) bins of the first ``n_pairs`` pairs, when they are few enough to pay.

    A factorised pass computes the per-bin terms (and their tangents) on every bin used. On a
    small subsample (the first stage: ≈ 2 000 pairs touch ≈ 1 800 of the 8 100 bins) that is
    cheaper on the bins listed here than on all. Returns ``{"ih", "jd": (K,), "remap": (8100,)}``
    (``K`` padded to a multiple of :data:`BIN_BLOCK` with bin 0; ``remap`` maps ``hd`` to the
    position in the list, 0 for unlisted bins), or None when the list would not be at least 2×
    smaller than the grid.
    """
    hd = np.unique(pairs.ih[:n_pairs].astype(np.int64) * N_BINS_D + pairs.jd[:n_pairs])
    k = -(-max(hd.size, 1) // BIN_BLOCK) * BIN_BLOCK
    if 2 * k > N_BINS:
        return None
    listed = np.zeros(k, np.int64)
    listed[: hd.size] = hd
    remap = np.zeros(N_BINS, np.int32)
    remap[hd] = np.arange(hd.size, dtype=np.int32)
    ih, jd = np.divmod(listed, N_BINS_D)
    return {
        "ih": jnp.asarray(ih, jnp.int32),
        "jd": jnp.asarray(jd, jnp.int32),
        "remap": jnp.asarray(remap),
    }


def _split(data):
    """``(chunks, bins)``: the chunked buffer and the stage's bin list (None: every bin)."""
    if "bins" in data:
        return {k: v for k, v in data.items() if k != "bins"}, data["bins"]
    return data, None


def _fold_chunks(step, init, data, n_active):
    """``acc = step(acc, chunk)`` over the first ``n_active`` chunks of ``data``.

    A ``scan`` over every chunk whose body skips the inactive ones (``cond``). Measured on
    the CPU backend, this is 3× faster than a ``fori_loop`` that slices chunk ``i`` out of the
    buffer with ``dynamic_index`` (XLA then moves far more memory per iteration).
    """
    n_chunks = jax.tree_util.tree_leaves(data)[0].shape[0]

    def body(acc, xs):
        i, chunk = xs
        return jax.lax.cond(i < n_active, lambda a: step(a, chunk), lambda a: a, acc), None

    return jax.lax.scan(body, init, (jnp.arange(n_chunks), data))[0]


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
    """A static description of one least-squares problem: model adapter, layout, metric."""

    adapter: Any = eqx.field(static=True)
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
        separable = set(getattr(self.adapter, "separable_fields", ()))
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
        return hasattr(self.adapter, "bin_terms")

    def terms(self, y, frozen, bins=None):
        """The adapter's per-bin terms at ``y`` (computed once per pass), or None."""
        if not self.factorised:
            return None
        return self.adapter.bin_terms(self.params(y, frozen), bins)

    def chunk_residual(self, y, frozen, chunk, terms=None, bins=None) -> jax.Array:
        """Residuals of one chunk of pairs, flattened ``(chunk × 2 × C,)``; absent members give 0.

        ``terms``: :meth:`terms` at ``y`` for a factorised adapter (the model is then evaluated
        from the pairs' bin indices and cosines), None for the others (from the directions).
        """
        params = self.params(y, frozen)
        if terms is None:
            pred = self.adapter.evaluate(params, chunk["wi"], chunk["wo"])
        else:
            pred = self.adapter.evaluate_cells(params, terms, chunk, bins)
        return metric_residual(pred[:, None, :], chunk, self.metric).reshape(-1)


def metric_residual(pred, chunk, metric: str):
    """Weighted residuals ``(chunk, 2, C)`` of predictions ``(chunk, 1, C)`` against both members."""
    cos = chunk["cos"][..., None]
    if metric == "log":
        r = jnp.log1p(pred * cos) - jnp.log1p(chunk["rho"] * cos)
    else:
        r = (pred - chunk["rho"]) * cos
    return r * chunk["w"][..., None]


def sum_squares(problem: Problem, y, frozen, data, n_active) -> jax.Array:
    """``rᵀr`` over the active chunks (primal only)."""

    data, bins = _split(data)
    terms = problem.terms(y, frozen, bins)

    def step(acc, chunk):
        r = problem.chunk_residual(y, frozen, chunk, terms, bins)
        return acc + jnp.sum(r * r)

    return _fold_chunks(step, jnp.zeros((), y.dtype), data, n_active)


def linearised_terms(problem: Problem, y, frozen, bins=None):
    """:meth:`Problem.terms` at ``y`` and their tangents along every seed, or ``(None, None)``."""
    if not problem.factorised:
        return None, None
    seeds = jnp.asarray(problem.seeds()[0], dtype=y.dtype)

    def terms(yy):
        return problem.terms(yy, frozen, bins)

    return jax.vmap(lambda t: jax.jvp(terms, (y,), (t,)), out_axes=(None, 0))(seeds)


def chunk_jacobian(problem: Problem, y, frozen, chunk, terms=None, terms_dot=None, bins=None):
    """Residuals ``(m,)`` and transposed Jacobian ``(n, m)`` of one chunk (compressed seeds).

    ``terms``, ``terms_dot``: :func:`linearised_terms` (factorised adapters), computed once per
    pass: the per-bin part of the model is differentiated once, not once per chunk.
    """
    seed, mask, owner = problem.seeds()
    n_ch = problem.adapter.config.n_channels
    seeds = jnp.asarray(seed, dtype=y.dtype)
    if terms is None:

        def f(yy):
            return problem.chunk_residual(yy, frozen, chunk)

        r, jac_s = jax.vmap(lambda t: jax.jvp(f, (y,), (t,)), out_axes=(None, 0))(seeds)
    else:

        def f2(yy, tt):
            return problem.chunk_residual(yy, frozen, chunk, tt, bins)

        r, jac_s = jax.vmap(lambda t, td: jax.jvp(f2, (y, terms), (t, td)), out_axes=(None, 0))(
            seeds, terms_dot
        )
    # Expand the compressed columns: rows are (entry, member, channel) with channel fastest.
    jac_t = jac_s[owner].reshape(owner.size, -1, n_ch) * jnp.asarray(mask, y.dtype)[:, None, :]
    return r, jac_t.reshape(owner.size, -1)


def normal_equations(problem: Problem, y, frozen, data, n_active):
    """``(JᵀJ, Jᵀr, rᵀr)`` over the active chunks, without keeping the Jacobian."""
    n = y.shape[0]
    data, bins = _split(data)
    terms, terms_dot = linearised_terms(problem, y, frozen, bins)

    def step(acc, chunk):
        r, jac_t = chunk_jacobian(problem, y, frozen, chunk, terms, terms_dot, bins)
        jtj, jtr, rr = acc
        return jtj + jac_t @ jac_t.T, jtr + jac_t @ r, rr + r @ r

    init = (jnp.zeros((n, n), y.dtype), jnp.zeros((n,), y.dtype), jnp.zeros((), y.dtype))
    return _fold_chunks(step, init, data, n_active)


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


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def compressed_residuals(problem: Problem, y, frozen, data, n_active) -> jax.Array:
    """The ``(n+1)``-vector ``r̃`` equivalent to the full residuals (see module doc)."""
    r_c, _ = _compress(*normal_equations(problem, y, frozen, data, n_active))
    return r_c


@compressed_residuals.defjvp
def _compressed_jvp(problem, primals, tangents):
    y, frozen, data, n_active = primals
    r_c, j_c = _compress(*normal_equations(problem, y, frozen, data, n_active))
    return r_c, j_c @ tangents[0]


def predict(fn, params, data, n_active, n_out: int) -> jax.Array:
    """``fn(params, wi, wo)`` at the buffer's cells, ``(n_chunks, chunk, n_out)`` (inactive chunks 0)."""
    n_chunks, chunk = data["wi"].shape[:2]

    def body(i, out):
        ch = _chunk_at(data, i)
        pred = fn(params, ch["wi"], ch["wo"])
        return jax.lax.dynamic_update_index_in_dim(out, pred.astype(out.dtype), i, 0)

    out = jnp.zeros((n_chunks, chunk, n_out), dtype=data["wi"].dtype)
    return jax.lax.fori_loop(0, n_active, body, out)

"""The cells of a fit, prepared on the host (NumPy): the valid part of a MERL table flattened
(:func:`select_cells`), grouped in reciprocal pairs (:func:`pair_cells`) and packed into the
fixed-shape chunked buffers the device passes of :mod:`twoscale.fit.residuals` fold over
(:func:`pack`, :func:`pack_directions`).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from twoscale.merl import N_CELLS, N_THETA_D, N_THETA_H, n_first_phi_bins

LOG_SCALE_FLOOR = 1e-4
"""Least scale (1/sr) of the ``"scaled-log"`` metric: a channel whose median ``ρ cos θ_i`` is
below this (an all-black channel) is measured in absolute terms below it."""

#: Entries (cell pairs, or direction pairs) per chunk of a pass over the data: the granularity of
#: the subsample stages (2 048 pairs ≈ 4 000 cells).
CHUNK = 2048


#: Chunks of a fitting buffer: at most 90·90·91 reciprocal pairs (φ_d bins 0…90 are the first
#: members) fit in 360 × 2048.
PAIR_CHUNKS = -(-(N_THETA_H * N_THETA_D * n_first_phi_bins("lower")) // CHUNK)


#: Chunks of an evaluation buffer: every one of the 90·90·180 MERL cells fits in 712 × 2048.
DIRECTION_CHUNKS = -(-N_CELLS // CHUNK)


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

    def log_scale(self) -> np.ndarray:
        """``(C,)``: the scale ``s_c`` of the ``"scaled-log"`` metric (docs/model.md §8): the
        median over these cells of the measured ``ρ cos θ_i`` per channel, at least
        :data:`LOG_SCALE_FLOOR` (1/sr)."""
        med = np.median(self.rho * self.cos_i[:, None], axis=0)
        return np.maximum(med, LOG_SCALE_FLOOR)

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
        ValueError: no valid cell (or none left after the angle cut), every valid cell 0 in
            every channel (a black table: nothing to fit), or a bad angle.
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
    if not np.any(rho[keep] > 0.0):
        raise ValueError(
            "every valid cell is 0 in every channel (nothing to fit: a table of zeros, or values "
            "lost on the way to the file)"
        )
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

    The partner of ``i_φ = k`` is :func:`twoscale.merl.reciprocal_phi_bin` (``180 − k``);
    ``k = 0`` and ``k = 90`` are their own partners and stay single. A pair's directions are
    those of its member with ``k ≤ 90``.
    """
    from twoscale import merl
    from twoscale.geometry import _azimuth_difference, _dirs_from_half_diff

    idx = np.asarray(cells.index, dtype=np.int64)
    k = idx % merl.N_PHI_D
    second = k >= merl.n_first_phi_bins("lower")
    first_index = np.where(second, idx - k + merl.reciprocal_phi_bin(k, "lower"), idx)
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


def pack(pairs: Pairs, n_chunks: int = PAIR_CHUNKS, chunk: int = CHUNK, log_scale=None):
    """Pairs → device buffer ``{wi, wo, rho, cos, w, hd, phi, s, log_s, log}``,
    ``(n_chunks, chunk, ...)``.

    ``hd = 90 ih + jd``: the pair's ``(θ_h, θ_d)`` bin. ``s``: ``(n_chunks, C)``, the inverse
    of ``log_scale`` (``(C,)``, the ``"scaled-log"`` metric's scale; 1 when None) repeated for
    every chunk, so each chunk carries it. ``log_s``, ``log``: :func:`measured_logs` (use
    :func:`with_scale` to change ``s``).

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
    n_ch = pairs.rho.shape[-1]
    scale = np.ones(n_ch) if log_scale is None else np.asarray(log_scale, dtype=np.float64)
    if scale.shape != (n_ch,) or not np.all(scale > 0):
        raise ValueError(f"log_scale must be {n_ch} positive values, got {scale!r}")
    buf["s"] = np.broadcast_to(1.0 / scale, (n_chunks, n_ch)).copy()
    buf.update(measured_logs(buf["rho"], buf["cos"], buf["s"]))
    return {k: jnp.asarray(v) for k, v in buf.items()}, n_active


def measured_logs(rho, cos, s) -> dict:
    """The log metrics' measured terms, computed once per buffer rather than in every pass:
    ``{"log_s": log(1 + ρ cos θ_i s), "log": log(1 + ρ cos θ_i)}``, ``(n_chunks, chunk, 2, C)``,
    for ``rho`` ``(n_chunks, chunk, 2, C)``, ``cos`` ``(n_chunks, chunk, 2)`` and the inverse
    scales ``s`` ``(n_chunks, C)`` of :func:`pack`."""
    xp = jnp if isinstance(rho, jax.Array) else np
    k = cos[..., None] * rho
    return {"log_s": xp.log1p(k * s[:, None, None, :]), "log": xp.log1p(k)}


def with_scale(buffer: dict, inverse_scale) -> dict:
    """``buffer`` with every chunk's inverse log scale ``s`` replaced by ``inverse_scale``
    (``(C,)``) and its measured log terms (:func:`measured_logs`) recomputed to match."""
    s = jnp.broadcast_to(jnp.asarray(inverse_scale, buffer["s"].dtype), buffer["s"].shape)
    return {**buffer, "s": s, **measured_logs(buffer["rho"], buffer["cos"], s)}


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


#: θ_d bins of the MERL grid (``hd = N_BINS_D · ih + jd``).
N_BINS_D = N_THETA_D

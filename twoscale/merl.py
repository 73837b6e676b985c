"""MERL ``.binary`` BRDF files: read, write, validity mask, sample directions [docs/model.md §7].

NumPy I/O (float64 NumPy arrays in and out; nothing here needs JAX's x64 mode).

File format (Matusik et al. 2003): a header of three little-endian int32 ``(90, 90, 180)`` =
``(n_θh, n_θd, n_φd)``, then ``3 × 1,458,000`` little-endian float64, channel-major (all R, then G,
then B), each channel in C order ``[θ_h][θ_d][φ_d]``; 34,992,012 bytes in all. A raw value times
the channel scale (R 1/1500, G 1.15/1500, B 1.66/1500) is the BRDF in 1/sr (without the cosine).
Negative entries (−1 in all channels in the real files) mark missing / below-horizon cells.

In :class:`MerlData` a cell is *valid* iff its three raw channels are ≥ 0. Invalid cells hold 0.0 in
``values`` (never NaN, so sums and products stay finite) and are excluded through ``valid``:
always use the mask, a 0 is not a measurement.

Bins and angles: ``i_h = ⌊90 √(θ_h/(π/2))⌋``, ``i_d = ⌊90 θ_d/(π/2)⌋``, ``i_φ = ⌊180 φ_d/π⌋`` with
``φ_d`` folded into [0, π) by ``+π`` (reciprocity), all clamped into range. A bin's angle is either
its lower edge (``convention="lower"``, the majority convention: ``θ_h = (i/90)² π/2``,
``θ_d = j π/180``, ``φ_d = k π/180``) or its centre (``convention="centre"``:
``θ_h = ((i+½)/90)² π/2``, ``θ_d = (j+½) π/180``, ``φ_d = (k+½) π/180``).

Errors: a missing file raises :class:`FileNotFoundError` (with the path; it is not a format
problem, and ``except OSError`` catches it with the other I/O failures). Anything wrong with the
bytes of an existing file raises :class:`MerlFormatError` (a :class:`ValueError`) whose message
starts with the path and says what is wrong. Bad arguments raise :class:`ValueError`.
"""

from __future__ import annotations

import errno
import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twoscale._atomic import write_atomic
from twoscale.geometry import _dirs_from_half_diff

__all__ = [
    "SHAPE",
    "N_THETA_H",
    "N_THETA_D",
    "N_PHI_D",
    "N_CELLS",
    "SCALE",
    "HEADER_BYTES",
    "FILE_BYTES",
    "CONVENTIONS",
    "MerlFormatError",
    "MerlData",
    "bin_to_angles",
    "angles_to_bin",
    "grid_angles",
    "axis_angles",
    "reciprocal_phi_bin",
    "n_first_phi_bins",
    "grid_directions",
    "bihemispherical_albedo",
    "valid_geometric",
    "read",
    "write",
    "from_function",
]

N_THETA_H, N_THETA_D, N_PHI_D = 90, 90, 180
SHAPE = (N_THETA_H, N_THETA_D, N_PHI_D)
N_CELLS = N_THETA_H * N_THETA_D * N_PHI_D  # 1,458,000
SCALE = np.array([1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0])  # raw × SCALE = BRDF in 1/sr (RGB)
SCALE.setflags(write=False)
HEADER_BYTES = 12
BODY_BYTES = 3 * N_CELLS * 8
FILE_BYTES = HEADER_BYTES + BODY_BYTES  # 34,992,012
CONVENTIONS = ("lower", "centre")

_CHANNELS = "RGB"
# Snap tolerance of angles_to_bin: an angle within this relative distance below a bin edge counts
# as on the edge, so that the lower-edge angles of bin_to_angles (which carry a few ulps of
# rounding) map back to their own bins. 16 ulps of an angle is far below any measurement accuracy.
_EDGE_SNAP = 16 * np.finfo(np.float64).eps


class MerlFormatError(ValueError):
    """The bytes of a MERL ``.binary`` file are not a valid MERL BRDF (message names the file)."""


def _check_convention(convention: str) -> float:
    """Offset of the bin angle within its bin: 0 (lower edge) or ½ (centre)."""
    if convention == "lower":
        return 0.0
    if convention == "centre":
        return 0.5
    raise ValueError(f"unknown bin convention {convention!r}: expected one of {CONVENTIONS}")


def bin_to_angles(i_h, i_d, i_phi, convention: str = "lower"):
    """Angles ``(θ_h, θ_d, φ_d)`` in radians of MERL bin indices.

    ``lower``: ``θ_h = (i_h/90)² π/2``, ``θ_d = i_d π/180``, ``φ_d = i_φ π/180``.
    ``centre``: ``θ_h = ((i_h+½)/90)² π/2``, ``θ_d = (i_d+½) π/180``, ``φ_d = (i_φ+½) π/180``.

    Args:
        i_h, i_d, i_phi: integer indices in ``[0, 90)``, ``[0, 90)``, ``[0, 180)`` (broadcast).
        convention: ``"lower"`` (bin lower edge) or ``"centre"``.
    Returns:
        Three float64 arrays of the broadcast shape.
    Raises:
        ValueError: unknown convention, non-integer or out-of-range indices.
    """
    off = _check_convention(convention)
    out = []
    for name, idx, n in (
        ("i_h", i_h, N_THETA_H),
        ("i_d", i_d, N_THETA_D),
        ("i_phi", i_phi, N_PHI_D),
    ):
        idx = np.asarray(idx)
        if not np.issubdtype(idx.dtype, np.integer):
            raise ValueError(f"{name} must be integer indices, got dtype {idx.dtype}")
        if idx.size and (idx.min() < 0 or idx.max() >= n):
            raise ValueError(f"{name} out of range [0, {n}): min {idx.min()}, max {idx.max()}")
        out.append(idx.astype(np.float64) + off)
    ih, jd, kp = np.broadcast_arrays(*out)
    theta_h = (ih / N_THETA_H) ** 2 * (np.pi / 2)
    theta_d = jd * (np.pi / 180)
    phi_d = kp * (np.pi / 180)
    return theta_h, theta_d, phi_d


def _floor_index(x, n):
    """``clip(⌊x⌋, 0, n−1)`` with edge snapping (see ``_EDGE_SNAP``), as int64."""
    x = np.asarray(x, np.float64)
    return np.clip(np.floor(x + np.abs(x) * _EDGE_SNAP), 0, n - 1).astype(np.int64)


def angles_to_bin(theta_h, theta_d, phi_d):
    """MERL bin indices ``(i_h, i_d, i_φ)`` of half/difference angles in radians.

    ``i_h = ⌊90 √(θ_h/(π/2))⌋`` (``θ_h ≤ 0`` gives 0), ``i_d = ⌊90 θ_d/(π/2)⌋``,
    ``i_φ = ⌊180 φ_d/π⌋`` after folding ``φ_d < 0`` into [0, π) by ``+π`` (reciprocity); each
    clamped into its range (so ``φ_d = π`` gives 179, as in MERL's reference code). An angle within
    16 ulps below a bin edge is snapped onto the edge, so ``angles_to_bin(*bin_to_angles(i))`` is
    ``i`` in both conventions.

    Args:
        theta_h: half angle(s), nominally in [0, π/2].
        theta_d: difference angle(s), nominally in [0, π/2].
        phi_d: difference azimuth(s), nominally in (−π, π] (what :func:`half_diff_from_dirs` gives).
    Returns:
        Three int64 arrays of the broadcast shape.
    Raises:
        ValueError: a non-finite angle.
    """
    th, td, pd = np.broadcast_arrays(
        *(np.asarray(a, np.float64) for a in (theta_h, theta_d, phi_d))
    )
    for name, a in (("theta_h", th), ("theta_d", td), ("phi_d", pd)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} contains non-finite values")
    i_h = _floor_index(N_THETA_H * np.sqrt(np.maximum(th, 0.0) / (np.pi / 2)), N_THETA_H)
    i_d = _floor_index(td * (N_THETA_D / (np.pi / 2)), N_THETA_D)
    i_phi = _floor_index(np.where(pd < 0.0, pd + np.pi, pd) * (N_PHI_D / np.pi), N_PHI_D)
    return i_h, i_d, i_phi


def reciprocal_phi_bin(i_phi, convention: str = "lower"):
    """The φ_d bin holding the same direction pair with ``i`` and ``o`` swapped (and mirrored in
    the plane ``y = 0``): ``(180 − k) mod 180`` at lower edges (bins 0 and 90 are their own
    partners), ``179 − k`` at bin centres. An isotropic, reciprocal BRDF has equal values in
    partner cells."""
    _check_convention(convention)
    k = np.asarray(i_phi)
    return (N_PHI_D - k) % N_PHI_D if convention == "lower" else N_PHI_D - 1 - k


def n_first_phi_bins(convention: str = "lower") -> int:
    """Bins ``k < n`` hold one member of every reciprocal pair (and the self-partners): 91 at
    lower edges (0…90), 90 at centres."""
    _check_convention(convention)
    return N_PHI_D // 2 + 1 if convention == "lower" else N_PHI_D // 2


def axis_angles(convention: str = "lower"):
    """The 1-D axes ``(θ_h (90,), θ_d (90,), φ_d (180,))`` of the grid, in radians."""
    th, _, _ = bin_to_angles(np.arange(N_THETA_H), 0, 0, convention)
    _, td, _ = bin_to_angles(0, np.arange(N_THETA_D), 0, convention)
    _, _, pd = bin_to_angles(0, 0, np.arange(N_PHI_D), convention)
    return th, td, pd


def _axis_angles(convention: str):
    """``(θ_h, θ_d, φ_d)`` of the bins as broadcastable ``(90,1,1)``, ``(1,90,1)``, ``(1,1,180)`` arrays."""
    return bin_to_angles(
        np.arange(N_THETA_H)[:, None, None],
        np.arange(N_THETA_D)[None, :, None],
        np.arange(N_PHI_D)[None, None, :],
        convention=convention,
    )


def grid_angles(convention: str = "lower"):
    """``(θ_h, θ_d, φ_d)`` of every MERL cell, each a float64 array of shape ``(90, 90, 180)``."""
    return tuple(np.broadcast_to(a, SHAPE).copy() for a in _axis_angles(convention))


def _grid_directions(convention: str):
    """``(wi, wo)`` of every MERL cell (``φ_h = 0``), each float64 ``(90, 90, 180, 3)``."""
    # Trigonometric functions of the 1-D axes only; products broadcast to the grid.
    return _dirs_from_half_diff(np, *_axis_angles(convention))


def grid_directions(convention: str = "lower"):
    """``(wi, wo)`` of every MERL cell (``φ_h = 0``), float64 ``(90, 90, 180, 3)`` each."""
    _check_convention(convention)
    return _grid_directions(convention)


def _grid_cosines(convention: str):
    """``(cos θ_i, cos θ_o)`` of every MERL cell [docs/model.md §7.3]."""
    th, td, pd = _axis_angles(convention)
    a = np.cos(th) * np.cos(td)
    b = np.sin(th) * np.sin(td) * np.cos(pd)
    return a - b, a + b


def bihemispherical_albedo(values, valid) -> np.ndarray:
    """``(C,)``: ``(1/π) ∫∫ ρ cos θ_i cos θ_o dω_i dω_o`` of a ``(90, 90, 180, C)`` table over its
    valid cells (the white-sky albedo, in [0, 1] for an energy-conserving BRDF).

    Each cell stands for its bin (midpoint rule at the lower-edge directions, the measure
    ``dω_i dω_o = 4 cos θ_d dω_h dω_d`` with ``dω_h = sin θ_h dθ_h dφ_h`` integrated over φ_h,
    bin widths from the θ_h bin edges; the table's φ_d ∈ [0, π) stands for [0, 2π) by
    reciprocity); invalid cells count as 0. A Lambertian table of albedo ρ with every cell valid
    gives 1.048 ρ (the quadrature's accuracy).
    """
    edges_h = (np.arange(N_THETA_H + 1) / N_THETA_H) ** 2 * (np.pi / 2)
    mid_h = 0.5 * (edges_h[:-1] + edges_h[1:])
    d_d = np.pi / 2 / N_THETA_D
    mid_d = (np.arange(N_THETA_D) + 0.5) * d_d
    measure = (
        (np.sin(mid_h) * np.diff(edges_h))[:, None, None]
        * (4.0 * np.cos(mid_d) * np.sin(mid_d) * d_d)[None, :, None]
        * (2.0 * np.pi * (2.0 * np.pi / N_PHI_D))  # φ_h; φ_d over [0, 2π) by reciprocity
    )
    cos_i, cos_o = _grid_cosines("lower")
    w = np.where(np.asarray(valid) & (cos_i > 0) & (cos_o > 0), cos_i * cos_o * measure, 0.0)
    return np.einsum("hdp,hdpc->c", w, np.asarray(values, dtype=np.float64)) / np.pi


def valid_geometric(convention: str = "lower") -> np.ndarray:
    """Cells whose directions are both above the horizon: ``cos θ_i > 0`` and ``cos θ_o > 0``.

    About 76.2 % of the cells (lower convention) or 75.2 % (centre). Real MERL files mark about
    75.8 % valid, and their valid set is not exactly this one.
    """
    cos_i, cos_o = _grid_cosines(convention)
    return (cos_i > 0.0) & (cos_o > 0.0)


@dataclass(frozen=True, eq=False, repr=False)
class MerlData:
    """A MERL BRDF in memory.

    Attributes:
        values: float64 ``(90, 90, 180, 3)``, BRDF in 1/sr (channel scales applied), RGB last;
            0.0 in invalid cells. Read-only.
        valid: bool ``(90, 90, 180)``, True where all three raw channels are ≥ 0. Read-only.
        path: the file it was read from, or None.
        name: material name (the file stem for files read from disk).
        size: the file's size in bytes (files read from disk; else None).
        sha256: the SHA-256 of the file's bytes, hex (files read from disk; else None): what a
            fit record cites to name its input unambiguously.

    Construction checks shapes, finiteness and non-negativity of the valid cells, and zeroes the
    invalid ones (copying only if needed).
    """

    values: np.ndarray
    valid: np.ndarray
    path: Path | None = None
    name: str = ""
    size: int | None = None
    sha256: str | None = None

    def __post_init__(self):
        values = np.asarray(self.values, dtype=np.float64)
        valid = np.asarray(self.valid)
        if values.shape != (*SHAPE, 3):
            raise ValueError(f"MerlData.values must have shape {(*SHAPE, 3)}, got {values.shape}")
        if valid.shape != SHAPE or valid.dtype != np.bool_:
            raise ValueError(
                f"MerlData.valid must be a bool array of shape {SHAPE}, got {valid.dtype} {valid.shape}"
            )
        v = values[valid]
        if not np.all(np.isfinite(v)):
            raise ValueError(
                f"MerlData.values: {np.count_nonzero(~np.isfinite(v))} non-finite valid values"
            )
        if np.any(v < 0.0):
            raise ValueError(f"MerlData.values: {np.count_nonzero(v < 0.0)} negative valid values")
        if np.any(values[~valid] != 0.0):  # also true for NaN
            values = np.where(valid[..., None], values, 0.0)
        values, valid = (
            values.view(),
            valid.view(),
        )  # read-only views; the caller's arrays untouched
        values.setflags(write=False)
        valid.setflags(write=False)
        object.__setattr__(self, "values", values)
        object.__setattr__(self, "valid", valid)
        if self.path is not None:
            object.__setattr__(self, "path", Path(self.path))

    def __repr__(self):
        return f"MerlData(name={self.name!r}, path={self.path!r}, valid_fraction={self.valid_fraction:.4f})"

    @property
    def valid_fraction(self) -> float:
        """Fraction of valid cells (about 0.758 for the real MERL files)."""
        return float(np.count_nonzero(self.valid)) / N_CELLS

    def angles(self, convention: str = "lower"):
        """``(θ_h, θ_d, φ_d)`` of every cell, float64 ``(90, 90, 180)`` each (see :func:`grid_angles`)."""
        return grid_angles(convention)

    def directions(self, convention: str = "lower"):
        """``(wi, wo)`` of every cell with ``φ_h = 0``, float64 ``(90, 90, 180, 3)`` each."""
        return grid_directions(convention)


def _fail(path, problem: str):
    return MerlFormatError(f"{path}: not a valid MERL .binary file: {problem}")


def read(path) -> MerlData:
    """Read a MERL ``.binary`` file.

    Args:
        path: file path.
    Returns:
        :class:`MerlData` with ``name`` the file stem.
    Raises:
        FileNotFoundError: no such file (the message names it).
        MerlFormatError: short file, header other than ``(90, 90, 180)``, truncated or oversized
            body, NaN or inf in the body.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise FileNotFoundError(errno.ENOENT, "MERL file not found", str(path)) from None
    n = len(data)
    if n < HEADER_BYTES:
        raise _fail(path, f"file is {n} bytes, shorter than the {HEADER_BYTES}-byte header")
    dims = tuple(int(d) for d in np.frombuffer(data, "<i4", count=3))
    if dims != SHAPE:
        hint = ""
        if tuple(int(d) for d in np.frombuffer(data, ">i4", count=3)) == SHAPE:
            hint = " (the header is big-endian; MERL files are little-endian)"
        raise _fail(path, f"header dimensions {dims}, expected {SHAPE}{hint}")
    if n != FILE_BYTES:
        what = "truncated" if n < FILE_BYTES else f"{n - FILE_BYTES} extra bytes after the body"
        raise _fail(path, f"{what}: file is {n} bytes, expected {FILE_BYTES}")
    raw = np.frombuffer(data, "<f8", offset=HEADER_BYTES).reshape(3, *SHAPE)
    finite = np.isfinite(raw)
    if not finite.all():
        bad = np.argwhere(~finite)
        c, ih, jd, kp = (int(x) for x in bad[0])
        raise _fail(
            path,
            f"{len(bad)} non-finite values (NaN or inf) in the body, the first in channel "
            f"{_CHANNELS[c]} at bin (i_h, i_d, i_phi) = ({ih}, {jd}, {kp}): {raw[c, ih, jd, kp]}",
        )
    valid = (raw >= 0.0).all(axis=0)
    values = np.empty((*SHAPE, 3))  # C-contiguous, RGB last
    np.multiply(np.moveaxis(raw, 0, -1), SCALE, out=values)
    values[~valid] = 0.0
    return MerlData(
        values=values,
        valid=valid,
        path=path,
        name=path.stem,
        size=n,
        sha256=hashlib.sha256(data).hexdigest(),
    )


def write(path, values, valid=None) -> Path:
    """Write a MERL ``.binary`` file atomically (temporary file in the same folder, then rename).

    Args:
        path: destination.
        values: BRDF in 1/sr, float ``(90, 90, 180, 3)`` with RGB last, or a :class:`MerlData`
            (then ``valid`` defaults to its mask).
        valid: bool ``(90, 90, 180)``; invalid cells are written as −1 in all three channels and
            their values ignored (may be NaN). None: every cell is valid.
    Returns:
        The path written.
    Raises:
        ValueError: wrong shape, non-finite or negative values in valid cells (negative raw
            entries mean "invalid" in the format), or values too large for the format.

    Round trip: ``read(write(p, d))`` reproduces data ``d`` read from a file bit for bit (values
    and mask); other values come back within 1 ulp.
    """
    path = Path(path)
    if isinstance(values, MerlData):
        if valid is None:
            valid = values.valid
        values = values.values
    values = np.asarray(values, dtype=np.float64)
    if values.shape != (*SHAPE, 3):
        raise ValueError(f"write {path}: values must have shape {(*SHAPE, 3)}, got {values.shape}")
    if valid is None:
        valid = np.ones(SHAPE, dtype=bool)
    valid = np.asarray(valid)
    if valid.shape != SHAPE or valid.dtype != np.bool_:
        raise ValueError(
            f"write {path}: valid must be a bool array of shape {SHAPE}, got {valid.dtype} {valid.shape}"
        )
    v = np.where(valid[..., None], values, 0.0)
    if not np.all(np.isfinite(v)):
        raise ValueError(
            f"write {path}: {np.count_nonzero(~np.isfinite(v))} non-finite values in valid cells"
        )
    if np.any(v < 0.0):
        raise ValueError(
            f"write {path}: {np.count_nonzero(v < 0.0)} negative values in valid cells "
            "(negative entries mean 'invalid' in MERL files; pass a mask instead)"
        )
    # raw = values / SCALE. For values read from a file (products raw × SCALE) the quotient gives
    # back a raw value whose product is the same double, so read(write(read(f))) reproduces the
    # data bit for bit (checked in the tests on millions of values); other values return within
    # 1 ulp. The raw numbers themselves return within 1 ulp (x → x·s is not injective).
    with np.errstate(over="ignore"):
        raw = v / SCALE
    if not np.all(np.isfinite(raw)):
        raise ValueError(
            f"write {path}: values too large for the format (raw value overflows float64)"
        )
    raw[~valid] = -1.0
    body = np.ascontiguousarray(np.moveaxis(raw, -1, 0), dtype="<f8")
    header = np.asarray(SHAPE, dtype="<i4")

    return write_atomic(path, [header.tobytes(), memoryview(body).cast("B")])


def from_function(
    fn: Callable,
    convention: str = "lower",
    *,
    valid=None,
    invalid_fraction: float | None = None,
    name: str = "synthetic",
) -> MerlData:
    """Evaluate a BRDF on the MERL grid (synthetic data).

    Args:
        fn: ``fn(wi, wo) -> (..., 3)`` RGB BRDF in 1/sr, for float64 directions ``(90, 90, 180, 3)``
            (NumPy arrays; a JAX function works too). Its values in invalid cells are ignored.
        convention: where in each bin the directions lie, ``"lower"`` or ``"centre"``.
        valid: bool ``(90, 90, 180)`` mask; default :func:`valid_geometric` (both directions above
            the horizon).
        invalid_fraction: if given, the overall invalid fraction to reach (0.242 mimics the real
            files) by also invalidating the valid cells closest to grazing (smallest
            ``min(cos θ_i, cos θ_o)``; deterministic). Must be at least the invalid fraction of
            the mask (0.238 lower, 0.248 centre for the geometric one).
        name: material name.
    Raises:
        ValueError: bad convention, shapes or fraction; non-finite or negative values in valid cells.
    """
    _check_convention(convention)
    wi, wo = _grid_directions(convention)
    values = np.asarray(fn(wi, wo), dtype=np.float64)
    if values.shape != (*SHAPE, 3):
        raise ValueError(f"from_function: fn returned shape {values.shape}, expected {(*SHAPE, 3)}")
    valid = valid_geometric(convention) if valid is None else np.array(valid, dtype=bool)
    if valid.shape != SHAPE:
        raise ValueError(f"from_function: valid must have shape {SHAPE}, got {valid.shape}")
    if invalid_fraction is not None:
        n_invalid = round(float(invalid_fraction) * N_CELLS)
        n_extra = n_invalid - (N_CELLS - np.count_nonzero(valid))
        if not 0.0 <= invalid_fraction <= 1.0 or n_extra < 0:
            raise ValueError(
                f"from_function: invalid_fraction {invalid_fraction} must lie in "
                f"[{1.0 - np.count_nonzero(valid) / N_CELLS:.4f}, 1] (the mask's own invalid fraction)"
            )
        grazing = np.minimum(wi[..., 2], wo[..., 2]).ravel()
        cells = np.flatnonzero(valid)
        drop = cells[np.argsort(grazing[cells], kind="stable")[:n_extra]]
        valid.ravel()[drop] = False
    return MerlData(
        values=np.where(valid[..., None], values, 0.0), valid=valid, path=None, name=name
    )

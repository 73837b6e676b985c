"""Precomputed tables and their C² differentiable interpolation.

A table samples a smooth function on a uniform grid in *table coordinates* (for example
``log10 B`` or ``a/(1+a)``; each axis records its coordinate). It is interpolated by a tensor-product
**uniform cubic B-spline** whose coefficients are solved at load time so that the spline passes
through every grid value, with not-a-knot end conditions (third derivative continuous across the
first and last interior knots). The interpolant is C² (so Levenberg-Marquardt sees continuous
gradients), fourth-order accurate, and needs 4 coefficients per axis per query.

Out-of-domain rule: a query coordinate is clamped to the axis range ``[lo, hi]``; the value is
then the edge value and the derivative along that axis is 0. Callers choose coordinates that
map their whole physical domain into the table (e.g. ``a/(1+a)`` for ``a ∈ [0, ∞)``) or keep
parameters inside by reparametrisation, so clamping is a documented last resort, never a NaN.

Hot paths slice the parameter axes once (:meth:`Spline.slice`, a contraction of the
coefficient tensor) and then do cheap 1-D lookups per sample.

Interpolation order (static ``Spline.order``): 3 (the default, everything above) or 1, the
multilinear interpolation of the authors' tables (coefficients = the grid values, 2 per axis per
query; C⁰, second-order accurate, kinks at the nodes). Order 1 exists to measure what the cubic
spline buys (``python -m benchmarks.run``); the library always builds cubic splines.
:meth:`Table.subsample` keeps every k-th node (a coarser table of the same function, for
resolution studies).

**The table service.** Kernels never load, cache or cast a table themselves: they ask
:func:`spline` for ``(table name, dtype, extra)`` and get one shared :class:`Spline`, built once
(coefficients solved in NumPy float64, then cast to the *canonical* dtype, i.e. float64 becomes
float32 unless ``jax_enable_x64`` is on, so the key is the dtype the arrays really have) and kept
in one registry (the tables of :data:`STORED_FLOAT32` keep float32 coefficients and compute in
float64: :attr:`Spline.compute`). ``extra`` names a further array of the same file that a
kernel interpolates over the table's leading axes (the convolution table's angle map and
``log k``). :func:`clear_caches` empties the registry and the :func:`load_table` cache;
:func:`cached_splines` lists what is built. :func:`interpolation` is a study hook
(``python -m benchmarks.run``): while active, the tables' main splines are built with another
order and/or on a subsampled grid.

File format (``.npz``): ``values`` (float64, grid shape + optional trailing component dims) and
``meta`` (a JSON string with ``name``, ``version``, ``axes`` = list of
``{name, coordinate, lo, hi, n}``, ``components``, ``generator`` settings, ``build_seconds``).
Extra arrays may sit beside them.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "Axis",
    "Spline",
    "Table",
    "load_table",
    "save_table",
    "bspline_coefficients",
    "spline",
    "clear_caches",
    "cached_splines",
    "interpolation",
    "canonical_dtype",
]


@dataclass(frozen=True)
class Axis:
    """One uniform table axis in table coordinates (``coordinate`` says how it maps to physics)."""

    name: str
    lo: float
    hi: float
    n: int
    coordinate: str = ""

    @property
    def step(self) -> float:
        return (self.hi - self.lo) / (self.n - 1)

    def nodes(self) -> np.ndarray:
        return np.linspace(self.lo, self.hi, self.n)


@functools.cache
def _solve_matrix(n: int) -> np.ndarray:
    """Inverse of the (n+2)×(n+2) interpolation system of a uniform cubic B-spline.

    Rows 0..n-1: ``(c_k + 4 c_{k+1} + c_{k+2})/6 = f_k`` (spline value at node k).
    Two not-a-knot rows: the third derivative, ∝ ``−c_j + 3c_{j+1} − 3c_{j+2} + c_{j+3}`` on
    segment j, is equal on segments 0 and 1, and on the last two segments.
    """
    if n < 4:
        raise ValueError(f"a cubic table axis needs at least 4 nodes, got {n}")
    m = np.zeros((n + 2, n + 2))
    for k in range(n):
        m[k, k : k + 3] = (1 / 6, 4 / 6, 1 / 6)
    m[n, 0:5] = (-1, 4, -6, 4, -1)
    m[n + 1, n - 3 : n + 2] = (-1, 4, -6, 4, -1)
    return np.linalg.inv(m)


def bspline_coefficients(values: np.ndarray, n_axes: int) -> np.ndarray:
    """B-spline coefficients (each of the first ``n_axes`` dims grows by 2) interpolating ``values``."""
    c = np.asarray(values, dtype=np.float64)
    for ax in range(n_axes):
        n = c.shape[ax]
        inv = _solve_matrix(n)[:, :n]  # the two not-a-knot right-hand sides are 0
        # One batched product over the (leading, trailing) axes, on the array as it lies: no
        # transposed copies (the convolution table's 4.9 M values: 0.17 s instead of 0.67 s,
        # the same coefficients to 2e-16 relative).
        lead = int(np.prod(c.shape[:ax], dtype=np.int64))
        trail = int(np.prod(c.shape[ax + 1 :], dtype=np.int64))
        c = np.matmul(inv, c.reshape(lead, n, trail)).reshape(
            c.shape[:ax] + (n + 2,) + c.shape[ax + 1 :]
        )
    return c


#: Interpolation orders of :class:`Spline`: cubic B-spline (default) and multilinear.
ORDERS = (3, 1)


def _position(x, lo: float, step: float, n: int):
    """The cell ``i`` (a float, in [0, n − 2]) and the offset ``t`` in it of coordinate x,
    clamped to the axis."""
    u = (jnp.clip(x, lo, lo + step * (n - 1)) - lo) / step
    i = jnp.clip(jnp.floor(u), 0, n - 2)
    return i, u - i


def _weights(x, lo: float, step: float, n: int, order: int = 3):
    """Index of the first coefficient and the ``order + 1`` weights at coordinate x.

    Order 3: the 4 cubic B-spline weights; order 1: the 2 linear (hat-function) weights.
    """
    i, t = _position(x, lo, step, n)
    if order == 1:
        return i.astype(jnp.int32), jnp.stack([1.0 - t, t], axis=-1)
    return i.astype(jnp.int32), _cubic_weights(t)


def _cubic_weights(t):
    """The 4 cubic B-spline weights at offset ``t`` in a cell, stacked on a last axis."""
    t2, t3 = t * t, t * t * t
    return jnp.stack(
        [
            (1.0 - t) ** 3 / 6.0,
            (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0,
            (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0,
            t3 / 6.0,
        ],
        axis=-1,
    )


class Spline(eqx.Module):
    """A tensor-product cubic B-spline over uniform axes (a pytree: coefficients are leaves).

    ``coeffs`` has shape ``(n_0+2, …, n_{d−1}+2, *components)`` (order 3, the default) or
    ``(n_0, …, n_{d−1}, *components)`` (order 1: multilinear, coefficients = grid values).
    """

    coeffs: jax.Array
    lo: tuple[float, ...] = eqx.field(static=True)
    step: tuple[float, ...] = eqx.field(static=True)
    n: tuple[int, ...] = eqx.field(static=True)
    order: int = eqx.field(static=True, default=3)
    #: The dtype the spline computes in, when the coefficients are stored narrower (a large
    #: table's float32 coefficients in float64 code, see :data:`STORED_FLOAT32`); None: theirs.
    compute: str | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if self.order not in ORDERS:
            raise ValueError(f"Spline.order must be one of {ORDERS}, got {self.order!r}")

    @property
    def dtype(self):
        """The dtype of the spline's coordinates, weights and results."""
        return jnp.dtype(self.compute) if self.compute else self.coeffs.dtype

    @property
    def ndim(self) -> int:
        return len(self.n)

    @property
    def width(self) -> int:
        """Coefficients per axis per query (4 cubic, 2 linear)."""
        return self.order + 1

    def slice(self, *coords) -> Spline:
        """Fix the leading ``len(coords)`` axes at scalar coordinates; returns a lower-dim Spline.

        The contraction is exact: the result interpolates the same function restricted to the slice.
        """
        c, dt = self.coeffs, self.dtype
        m = len(coords)
        iw = [
            _weights(jnp.asarray(x, dt), self.lo[k], self.step[k], self.n[k], self.order)
            for k, x in enumerate(coords)
        ]
        # One read of the width^m block the slice needs (slicing one axis at a time read, for
        # the convolution table, 4 whole (p, c, u, t) sub-tables first: 0.93 ms a slice against
        # 0.15 ms), widened to the compute dtype, then contracted axis by axis.
        starts = [i for i, _ in iw] + [jnp.int32(0)] * (c.ndim - m)
        block = jax.lax.dynamic_slice(c, starts, (self.width,) * m + c.shape[m:]).astype(dt)
        for _, w in iw:
            block = jnp.tensordot(w.astype(dt), block, axes=(0, 0))
        return Spline(block, self.lo[m:], self.step[m:], self.n[m:], self.order)

    def value_slope_and_tangents(self, x, *others):
        """A 1-D spline (no components) at ``x``: its value (the same as a call), its derivative
        along ``x``, and the same B-spline weights applied to each array of ``others``
        (coefficients of this spline's shape, e.g. their derivatives along a parameter the
        spline was sliced at).

        For forward rules written by hand (:func:`twoscale.shadowing.lambda_partials`): one set
        of indices, weights and gathered coefficients serves the value, the slope and every
        tangent. ``x`` outside the axis is clamped as in a call, where the slope is 0.
        """
        if self.ndim != 1 or self.coeffs.ndim != 1 or self.order != 3:
            raise ValueError("value_slope_and_tangents needs a 1-D cubic spline without components")
        dt = self.dtype
        x = jnp.asarray(x, dt)
        lo, st, n = self.lo[0], self.step[0], self.n[0]
        i, t = _position(x, lo, st, n)
        i, w = i.astype(jnp.int32), _cubic_weights(t)
        inside = (x > lo) & (x < lo + st * (n - 1))
        # d/dt of the four cubic B-spline weights of _weights, over the step.
        dw = (
            -0.5 * (1.0 - t) ** 2,
            (1.5 * t - 2.0) * t,
            (-1.5 * t + 1.0) * t + 0.5,
            0.5 * t * t,
        )
        taps = [self.coeffs[i + k].astype(dt) for k in range(4)]
        # Summed from zero in the order of __call__: the same value to the last bit.
        value = sum((w[..., k] * taps[k] for k in range(4)), jnp.zeros(x.shape, dt))
        slope = jnp.where(inside, sum(dw[k] * taps[k] for k in range(4)) / st, 0.0)
        tangents = [sum(w[..., k] * o.astype(dt)[i + k] for k in range(4)) for o in others]
        return value, slope, tangents

    def call_shared_first(self, x0, x1):
        """Evaluate a 2-D spline (no components) where ``x0`` is shared by many samples.

        ``x0`` broadcasts against ``x1`` but has far fewer elements (on a grid of half/difference
        angles, the u coordinate depends on the ``θ_d`` bin and channel, ``t`` on every sample). The
        spline is first contracted along axis 0 once per element of ``x0`` (a row of
        coefficients along axis 1 each), then each sample does a 1-D lookup in its row: 4 terms
        per sample (cubic) instead of 16. The same values as ``self(x0, x1)`` up to rounding.
        """
        if self.ndim != 2 or self.coeffs.ndim != 2:
            raise ValueError("call_shared_first needs a 2-D spline without components")
        c = self.coeffs.astype(self.dtype)
        x0 = jnp.asarray(x0, c.dtype)
        x1 = jnp.asarray(x1, c.dtype)
        shape = jnp.broadcast_shapes(x0.shape, x1.shape)
        i0, w0 = _weights(x0.reshape(-1), self.lo[0], self.step[0], self.n[0], self.order)
        rows = sum(w0[:, k, None] * c[i0 + k] for k in range(self.width))  # (R, m)
        row = jnp.broadcast_to(jnp.arange(x0.size, dtype=jnp.int32).reshape(x0.shape), shape)
        i1, w1 = _weights(
            jnp.broadcast_to(x1, shape), self.lo[1], self.step[1], self.n[1], self.order
        )
        return sum(w1[..., k] * rows[row, i1 + k] for k in range(self.width))

    def __call__(self, *coords):
        """Evaluate at broadcast coordinates (one array per axis); trailing components appended."""
        if len(coords) != self.ndim:
            raise ValueError(f"spline has {self.ndim} axes, got {len(coords)} coordinates")
        c, dt = self.coeffs, self.dtype
        coords = jnp.broadcast_arrays(*[jnp.asarray(x, dt) for x in coords])
        shape = coords[0].shape
        iw = [
            _weights(x, lo, st, n, self.order)
            for x, lo, st, n in zip(coords, self.lo, self.step, self.n, strict=True)
        ]
        # Scalar gathers from the flattened coefficients (one flat index per sample, a constant
        # offset per tap, each component from its own contiguous row): they fuse with the
        # elementwise code around them, where gathering index tuples or component slices made
        # XLA materialise every tap. Same terms, same order of summation as before.
        grid = c.shape[: self.ndim]
        comp = c.shape[self.ndim :]
        strides = [int(np.prod(grid[k + 1 :], dtype=np.int64)) for k in range(self.ndim)]
        rows = c.reshape(int(np.prod(grid)), -1).T  # (components, grid cells)
        base = functools.reduce(
            lambda a, b: a + b, [i * s for (i, _), s in zip(iw, strides, strict=True)]
        )
        outs = [jnp.zeros(shape, dt) for _ in range(rows.shape[0])]
        for ks in itertools.product(range(self.width), repeat=self.ndim):
            offset = sum(k * s for k, s in zip(ks, strides, strict=True))
            idx = base + offset
            w = functools.reduce(
                lambda a, b: a * b, [w[..., k] for (_, w), k in zip(iw, ks, strict=True)]
            )
            outs = [
                o + w * row.at[idx].get(mode="promise_in_bounds").astype(dt)
                for o, row in zip(outs, rows, strict=True)
            ]
        if not comp:
            return outs[0]
        return jnp.stack(outs, axis=-1).reshape(shape + comp)


@dataclass(frozen=True, eq=False)
class Table:
    """A loaded table: axes, grid values (NumPy float64), metadata, and its spline per dtype."""

    axes: tuple[Axis, ...]
    values: np.ndarray
    meta: dict
    extras: dict

    @functools.cached_property
    def coeffs(self) -> np.ndarray:
        return bspline_coefficients(self.values, len(self.axes))

    def spline(self, dtype=jnp.float64, order: int = 3) -> Spline:
        """The interpolating spline with coefficients in ``dtype`` (float32 or float64), built anew.

        Kernels use the cached :func:`spline` service instead; this builds for any Table (tests,
        generators, subsampled tables). ``dtype`` is canonicalised (:func:`canonical_dtype`).

        ``order=3`` (default): the C² cubic B-spline; ``order=1``: multilinear interpolation of
        the grid values (for comparisons; see the module docstring).
        """
        dtype = canonical_dtype(dtype)
        if order not in ORDERS:
            raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
        return Spline(
            jnp.asarray(self.coeffs if order == 3 else self.values, dtype=dtype),
            tuple(a.lo for a in self.axes),
            tuple(a.step for a in self.axes),
            tuple(a.n for a in self.axes),
            order,
        )

    def subsample(self, stride: int = 2) -> Table:
        """The table on every ``stride``-th node of each axis (a coarser grid of the same function).

        Each axis keeps nodes ``0, stride, 2·stride, …`` (its upper end moves down to the last
        kept node when ``n − 1`` is not a multiple of ``stride``). Extras are dropped.
        """
        if stride < 1:
            raise ValueError(f"stride must be ≥ 1, got {stride}")
        axes, index = [], []
        for a in self.axes:
            m = (a.n - 1) // stride + 1
            axes.append(Axis(a.name, a.lo, a.lo + a.step * stride * (m - 1), m, a.coordinate))
            index.append(slice(0, stride * (m - 1) + 1, stride))
        meta = {**self.meta, "subsampled": stride}
        return Table(tuple(axes), self.values[tuple(index)], meta, {})

    def __call__(self, *coords):
        """Evaluate at coordinates (dtype follows the coordinates)."""
        dtype = jnp.result_type(*coords, jnp.float32)
        return self.spline(dtype)(*coords)


def save_table(
    path,
    values,
    axes,
    *,
    name,
    version,
    components=(),
    generator=None,
    build_seconds=None,
    extras=None,
) -> None:
    """Write a table file (see the module docstring for the format)."""
    values = np.asarray(values, dtype=np.float64)
    axes = tuple(axes)
    if values.shape[: len(axes)] != tuple(a.n for a in axes):
        raise ValueError(f"values shape {values.shape} does not match axes {[a.n for a in axes]}")
    if not np.all(np.isfinite(values)):
        raise ValueError(f"table {name!r} has non-finite values")
    meta = {
        "name": name,
        "version": version,
        "axes": [a.__dict__ for a in axes],
        "components": list(components),
        "generator": generator or {},
        "build_seconds": build_seconds,
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, values=values, meta=np.array(json.dumps(meta)), **(extras or {}))
    tmp.replace(path)


def read_table(path) -> Table:
    """Read a table file written by :func:`save_table`."""
    with np.load(path, allow_pickle=False) as f:
        meta = json.loads(str(f["meta"]))
        values = np.array(f["values"])
        extras = {k: np.array(f[k]) for k in f.files if k not in ("values", "meta")}
    axes = tuple(Axis(**a) for a in meta["axes"])
    return Table(axes, values, meta, extras)


DATA_DIR = Path(str(resources.files("twoscale") / "data"))


def canonical_dtype(dtype) -> np.dtype:
    """The dtype JAX arrays requested as ``dtype`` get: float64 is float32 unless x64 is on."""
    return np.dtype(jax.dtypes.canonicalize_dtype(dtype))


@functools.cache
def load_table(name: str) -> Table:
    """Load the packaged table ``twoscale/data/<name>.npz`` (cached; :func:`clear_caches`)."""
    path = DATA_DIR / f"{name}.npz"
    if not path.exists():
        raise FileNotFoundError(
            f"table {name!r} not found at {path}; rebuild the tables with `python -m tablegen.build_all`"
        )
    return read_table(path)


# ---------------------------------------------------------------------------------------------
# The table service (see the module docstring): one registry of built splines.

#: Built splines by key ``(name, canonical dtype name, extra, n_axes, order, stride)``.
_SPLINES: dict[tuple, Spline] = {}
#: ``(order, stride)`` of the tables' main splines; changed only inside :func:`interpolation`.
_SETTINGS: tuple[int, int] = (3, 1)


#: Tables whose main spline keeps float32 coefficients also for float64 code (it computes in
#: float64: :attr:`Spline.compute`). The convolution table's coefficients (5.7 M) are constants
#: of every compiled function that slices it; in float64 they made each such function's
#: compiled code and its persistent-cache entry ≈ 48 MB and cost seconds of compilation per
#: function. Its grid values are float32 in the file already, so the coefficients' float32
#: rounding (≈ 6e-8 relative) is far below the table's interpolation error (≈ 1e-4).
STORED_FLOAT32 = frozenset({"convolution"})


def _build(name: str, dtype: np.dtype, extra, n_axes, order: int, stride: int) -> Spline:
    table = load_table(name)
    if extra is None:
        src = table.subsample(stride) if stride > 1 else table
        if name in STORED_FLOAT32 and dtype == np.float64:  # float32 straight from the solve
            sp = src.spline(np.float32, order)
            return Spline(sp.coeffs, sp.lo, sp.step, sp.n, sp.order, "float64")
        return src.spline(dtype, order)
    if extra not in table.extras:
        raise KeyError(f"table {name!r} has no extra array {extra!r} (has {sorted(table.extras)})")
    axes = table.axes[:n_axes]
    return Spline(
        jnp.asarray(bspline_coefficients(table.extras[extra], n_axes), dtype),
        tuple(a.lo for a in axes),
        tuple(a.step for a in axes),
        tuple(a.n for a in axes),
    )


def spline(name: str, dtype=jnp.float64, extra: str | None = None, *, n_axes=None) -> Spline:
    """The shared spline of the packaged table ``name`` in ``dtype`` (built once, then cached).

    The one way kernels get table coefficients: the same key returns the same object, so every
    kernel, slice and jitted function shares one copy per dtype.

    Args:
        name: a table in ``twoscale/data`` (``"smith_lambda"``, ``"renormalisation"``,
            ``"convolution"``).
        dtype: coefficient dtype; canonicalised first (float64 → float32 without x64), and the
            cache is keyed on the canonical dtype, so switching x64 on later never returns a
            float32 spline for a float64 request.
        extra: ``None``: the table's values (order and grid per :func:`interpolation`, by default
            the cubic spline on the full grid). Otherwise the name of an extra array of the file,
            interpolated by a cubic spline over the table's first ``n_axes`` axes (its remaining
            dims are components); extras ignore :func:`interpolation`.
        n_axes: required with ``extra``.
    Returns:
        A :class:`Spline` with concrete coefficients (also when first requested inside a trace).
    """
    dtype = canonical_dtype(dtype)
    if (extra is None) != (n_axes is None):
        raise ValueError("n_axes goes with extra (the extra array's number of spline axes)")
    order, stride = _SETTINGS if extra is None else (3, 1)
    key = (name, dtype.name, extra, n_axes, order, stride)
    out = _SPLINES.get(key)
    if out is None:
        # Concrete arrays even when first requested inside a jit trace (the cache outlives it).
        with jax.ensure_compile_time_eval():
            out = _SPLINES[key] = _build(name, dtype, extra, n_axes, order, stride)
    return out


def cached_splines() -> tuple[tuple, ...]:
    """Keys ``(name, dtype name, extra, n_axes, order, stride)`` of the splines built so far."""
    return tuple(_SPLINES)


def clear_caches() -> None:
    """Forget every built spline and loaded table (the next request reloads the files).

    Functions JAX already compiled keep the coefficients they traced with (they are trace-time
    constants); call ``jax.clear_caches()`` too where that matters (:func:`interpolation` does).
    """
    _SPLINES.clear()
    load_table.cache_clear()


def interpolation_order() -> int:
    """The order the tables' splines are built with now: 3, or what :func:`interpolation` set."""
    return _SETTINGS[0]


@contextlib.contextmanager
def interpolation(order: int = 3, stride: int = 1):
    """Study hook: while active, build the tables' main splines with ``order`` on every
    ``stride``-th node of each axis (:meth:`Table.subsample`).

    For comparisons (``python -m benchmarks.run``: multilinear like the authors' tables, coarser
    grids); the library always uses ``order=3, stride=1``. Affects the values of every table
    (Smith Λ, renormalisation, convolution ``g``), not the convolution's extras (angle map,
    ``log k``). The splines are trace-time constants of jitted functions, so JAX's caches are
    cleared on entry and on exit when the settings change; results computed inside stay valid.
    Nests; not thread-safe.
    """
    global _SETTINGS
    if order not in ORDERS:
        raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
    if stride < 1:
        raise ValueError(f"stride must be ≥ 1, got {stride}")
    previous = _SETTINGS
    if (order, stride) == previous:
        yield
        return
    _SETTINGS = (order, stride)
    jax.clear_caches()
    try:
        yield
    finally:
        _SETTINGS = previous
        jax.clear_caches()

"""Physical parameters of the two-scale model and their map to an unconstrained space [docs/model.md §4].

=========  ======  ====  ==========================================  ================================
field      symbol  unit  valid range (= range of the unconstrained   paper
                         map; inside the precomputed tables)
=========  ======  ====  ==========================================  ================================
beta       β       —     [1e-3, 1]                                   EPD roughness, Eq. 34-35
p          p       —     [0.2, 5]                                    EPD shape, Eq. 34-35
sigma_s    σ_s     µm    [0, 1]                                      nano-scale RMS height, Eq. 16, 25
b          b       µm    [0.01, 350]                                 PSD correlation length, Eq. 16
c          c       —     [1.01, 5]                                   PSD exponent, Eq. 16
eta        η       —     conductor [0.01, 6]; dielectric [1, 4]      index, real part (§3.1), per channel
k          k       —     [0, 10]                                     extinction (conductors), per channel
rho_d      ρ_d     —     [0, 1]                                      diffuse albedo (dielectrics; a conductor's floor), §3.9
e          e       —     [0, 5]                                      MERL apparatus exponent, §3.11
m          m       —     [1, 20]                                     MERL apparatus knee exponent
=========  ======  ====  ==========================================  ================================

``beta, p, sigma_s, b, c, e, m`` are scalars shared by all channels; ``eta, k, rho_d`` hold one
value per channel. Per-channel fields may hold 3 values (at the RGB wavelengths 0.645, 0.526, 0.444 µm),
one value per wavelength of a spectral configuration, or a single value for all channels; with 3
values and a spectral configuration they are upsampled to the wavelengths with
``twoscale.spectral.upsample_rgb`` (see :meth:`TwoScaleParams.channels`).

Unconstrained space: every bounded field maps through a scaled sigmoid, in log space where the
parameter is a scale (β, p, c − 1, b, conductor η, m), linearly otherwise (σ_s, k, ρ_d, e,
dielectric η). Every real vector maps inside the closed valid range above (results are clipped to the range
so that float32 rounding never leaves it), and the ranges lie inside the table domains, so the
optimiser never sees a clamped, zero-gradient table edge. ``σ_s = 0``, ``k = 0`` and ``ρ_d = 0`` are
limits (u → −∞); :meth:`TwoScaleParams.to_unconstrained` maps them, and any value on a bound, to a
finite point ``|u| ≤ 40`` whose image is the bound up to ~e⁻⁴⁰ of the range (σ_s → 4e-18 µm:
``A_s = 1`` exactly in float64).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from twoscale.config import MATERIALS, PARAM_ORDER, ModelConfig

__all__ = ["TwoScaleParams", "Bound", "bounds_for"]

SHARED_FIELDS = ("beta", "p", "sigma_s", "b", "c", "e", "m")
CHANNEL_FIELDS = ("eta", "k", "rho_d")
_U_MAX = 40.0  # |u| of a value on a bound: sigmoid(−40) ≈ 4e-18
_T_MAX = 1.0 / (1.0 + math.exp(-_U_MAX))  # σ(40) (1.0 in float64)


def _array_module(x):
    """NumPy for concrete values (the fit's starts and records: one host computation instead of
    a dispatch per JAX operation, ≈ 10 ms a call), ``jax.numpy`` for traced ones."""
    leaves = jax.tree_util.tree_leaves(x)
    return jnp if any(isinstance(a, jax.core.Tracer) for a in leaves) else np


def _np_sigmoid(u):
    return 0.5 * (1.0 + np.tanh(0.5 * u))


@dataclass(frozen=True)
class Bound:
    """A closed interval ``[lo, hi]`` and its sigmoid map from the real line.

    ``scale="linear"``: ``x = lo + (hi − lo) σ(u)``.
    ``scale="log"``: ``x = offset + exp(l0 + (l1 − l0) σ(u))``, ``l = log(bound − offset)``.
    """

    lo: float
    hi: float
    scale: str = "linear"
    offset: float = 0.0

    def contains(self, x: np.ndarray) -> np.ndarray:
        return (x >= self.lo) & (x <= self.hi)

    def __str__(self) -> str:
        return f"[{self.lo:g}, {self.hi:g}]"

    def forward(self, u):
        """Unconstrained ``u`` → value in ``[lo, hi]`` (clipped: float32 ``exp(log hi)`` may exceed hi)."""
        xp = _array_module(u)
        u = xp.asarray(u)
        s = jax.nn.sigmoid(u) if xp is jnp else _np_sigmoid(u)
        if self.scale == "log":
            l0, l1 = math.log(self.lo - self.offset), math.log(self.hi - self.offset)
            x = self.offset + xp.exp(l0 + (l1 - l0) * s)
        else:
            x = self.lo + (self.hi - self.lo) * s
        return jnp.asarray(xp.clip(x, self.lo, self.hi).astype(u.dtype, copy=False))

    def inverse(self, x):
        """Value → unconstrained ``u``; values on (or beyond) a bound go to ``u = ±40``."""
        xp = _array_module(x)
        x = xp.asarray(x)
        if xp is np and not np.issubdtype(x.dtype, np.floating):
            x = x.astype(jnp.asarray(0.0).dtype)  # Python numbers: JAX's default float
        if self.scale == "log":
            l0, l1 = math.log(self.lo - self.offset), math.log(self.hi - self.offset)
            t = (xp.log(xp.maximum(x - self.offset, 1e-300)) - l0) / (l1 - l0)
        else:
            t = (x - self.lo) / (self.hi - self.lo)
        t = xp.clip(t, 1.0 - _T_MAX, _T_MAX)
        with np.errstate(divide="ignore"):  # t = 0 or 1 (float64 rounds σ(40) to 1): u = ∓40
            u = xp.clip(xp.log(t) - xp.log1p(-t), -_U_MAX, _U_MAX)
        return jnp.asarray(u.astype(x.dtype, copy=False))


_BOUNDS = {
    "beta": Bound(1e-3, 1.0, "log"),
    "p": Bound(0.2, 5.0, "log"),
    "sigma_s": Bound(0.0, 1.0),
    # b's upper end: the convolution table covers u = (b/λ) cos θ_d ≤ 1000, so b ≤ 350 µm keeps
    # every wavelength from 0.35 µm up inside it (RGB: 0.444 µm and up; the spectral default
    # starts at 0.38 µm); ModelConfig accepts no shorter one (config.MIN_WAVELENGTH). On the
    # MERL stand-ins 15 of 60 fits ended at the earlier end, 100 µm: the highlights of
    # phenolics, plastics and chrome want a diffraction lobe as narrow as the EPD's
    # (docs/model.md §4).
    "b": Bound(0.01, 350.0, "log"),
    "c": Bound(1.01, 5.0, "log", offset=1.0),
    "k": Bound(0.0, 10.0),
    "rho_d": Bound(0.0, 1.0),
    "e": Bound(0.0, 5.0),
    # m = 2 is the paper's L(θ) = [1 − (2θ/π)²]^e; larger m keeps L near 1 to a later angle
    # and drops it faster beyond (docs/model.md §3.11).
    "m": Bound(1.0, 20.0, "log"),
}
_ETA_CONDUCTOR = Bound(0.01, 6.0, "log")
_ETA_DIELECTRIC = Bound(1.0, 4.0)

_DESCRIPTION = {
    "beta": "EPD roughness β",
    "p": "EPD shape exponent p",
    "sigma_s": "nano-scale RMS height σ_s in µm",
    "b": "PSD correlation length b in µm",
    "c": "PSD exponent c",
    "eta": "real part of the index of refraction η",
    "k": "extinction coefficient k",
    "rho_d": "diffuse albedo ρ_d",
    "e": "apparatus exponent e",
    "m": "apparatus knee exponent m",
}


def bounds_for(name: str, material: str | None) -> Bound:
    """The valid range of field ``name`` (η depends on whether the material is a conductor)."""
    if name == "eta":
        return _ETA_CONDUCTOR if material in (None, "conductor") else _ETA_DIELECTRIC
    return _BOUNDS[name]


def _arr(x):
    return None if x is None else jnp.asarray(x)


class TwoScaleParams(eqx.Module):
    """Parameters of the two-scale BRDF in physical units (an immutable pytree; see module doc).

    Fields not used by a configuration may be ``None`` (``ModelConfig.param_names`` lists the used
    ones). ``material`` (static) records which material the values were made for; ``None`` means
    "infer": conductor if ``k`` is set, else dielectric.
    """

    beta: jax.Array | None = eqx.field(default=None, converter=_arr)
    p: jax.Array | None = eqx.field(default=None, converter=_arr)
    sigma_s: jax.Array | None = eqx.field(default=None, converter=_arr)
    b: jax.Array | None = eqx.field(default=None, converter=_arr)
    c: jax.Array | None = eqx.field(default=None, converter=_arr)
    eta: jax.Array | None = eqx.field(default=None, converter=_arr)
    k: jax.Array | None = eqx.field(default=None, converter=_arr)
    rho_d: jax.Array | None = eqx.field(default=None, converter=_arr)
    e: jax.Array | None = eqx.field(default=None, converter=_arr)
    m: jax.Array | None = eqx.field(default=None, converter=_arr)
    material: str | None = eqx.field(default=None, static=True)

    # ----------------------------------------------------------------------------- constructors
    @classmethod
    def conductor(cls, beta, p, eta, k, sigma_s=None, b=None, c=None, e=None, m=None, rho_d=None):
        """A conductor: complex index ``η + ik`` per channel; ``rho_d``: the albedo of its
        Lambertian floor (``ModelConfig(conductor_floor=True)`` only)."""
        return cls(beta, p, sigma_s, b, c, eta, k, rho_d, e, m, material="conductor")

    @classmethod
    def plastic(cls, beta, p, eta, rho_d, sigma_s=None, b=None, c=None, e=None, m=None):
        """A dielectric varnish (real η) over a Lambertian layer of albedo ``ρ_d`` (§3.9)."""
        return cls(beta, p, sigma_s, b, c, eta, None, rho_d, e, m, material="plastic")

    @classmethod
    def subsurface(cls, beta, p, eta, rho_d, sigma_s=None, b=None, c=None, e=None, m=None):
        """A dielectric with a subsurface-scattering layer of albedo ``ρ_d`` (§3.9)."""
        return cls(beta, p, sigma_s, b, c, eta, None, rho_d, e, m, material="subsurface")

    # ----------------------------------------------------------------------------- helpers
    @property
    def kind(self) -> str:
        """``material``, or ``"conductor"`` / ``"dielectric"`` inferred from which fields are set."""
        if self.material is not None:
            return self.material
        return "conductor" if self.k is not None else "dielectric"

    def fields(self) -> dict:
        """The set (non-None) parameter fields, in canonical order."""
        return {n: getattr(self, n) for n in PARAM_ORDER if getattr(self, n) is not None}

    def astype(self, dtype) -> TwoScaleParams:
        """The same parameters with every leaf cast to ``dtype`` (e.g. ``jnp.float32``)."""
        return jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), self)

    def replace(self, **changes) -> TwoScaleParams:
        """A copy with some fields replaced (``None`` removes a field)."""
        values = {n: getattr(self, n) for n in (*PARAM_ORDER, "material")}
        unknown = set(changes) - set(values)
        if unknown:
            raise ValueError(f"TwoScaleParams has no field(s) {sorted(unknown)}")
        values.update(changes)
        return TwoScaleParams(**values)

    def for_config(self, config: ModelConfig) -> TwoScaleParams:
        """Keep only the fields ``config`` uses, per-channel fields resampled to its wavelengths.

        Raises ``ValueError`` if a used field is missing.
        """
        used = config.param_names
        missing = [n for n in used if getattr(self, n) is None]
        if missing:
            raise ValueError(
                f"config (material={config.material!r}) needs parameter(s) {missing}, "
                f"which are None in {self.fields().keys()}"
            )
        out = {n: (getattr(self, n) if n in used else None) for n in PARAM_ORDER}
        for n in CHANNEL_FIELDS:
            if out[n] is not None:
                out[n] = self.channels(n, config)
        return TwoScaleParams(**out, material=config.material)

    def channels(self, name: str, config: ModelConfig) -> jax.Array:
        """Per-channel field ``name`` as one value per wavelength of ``config``, shape ``(N,)``.

        Accepted shapes: ``()`` or ``(1,)`` (the same value at every wavelength), ``(N,)`` (one
        value per wavelength), or ``(3,)`` with a spectral configuration (values at the RGB
        wavelengths, upsampled with ``spectral.upsample_rgb``, which is differentiable).
        """
        from twoscale import spectral

        x = jnp.asarray(getattr(self, name))
        n = config.n_wavelengths
        if x.ndim == 0 or x.shape == (1,):
            return jnp.broadcast_to(x.reshape(()), (n,))
        if x.shape == (n,):
            return x
        if x.shape == (3,) and config.is_spectral:
            return spectral.upsample_rgb(x, jnp.asarray(config.wavelengths, x.dtype))
        raise ValueError(
            f"TwoScaleParams.{name} has shape {x.shape}; expected (), (1,), ({n},) "
            f"(one per wavelength of the config){' or (3,) (RGB)' if config.is_spectral else ''}"
        )

    # ----------------------------------------------------------------------------- validation
    def validate(self, config: ModelConfig | None = None) -> TwoScaleParams:
        """Check shapes, finiteness and ranges (concrete values only); returns ``self``.

        With ``config``: also checks that every parameter the configuration uses is present and
        that the material agrees. Raises ``ValueError`` naming the field, its value and its range.
        """
        if self.material is not None and self.material not in MATERIALS:
            raise ValueError(
                f"TwoScaleParams.material = {self.material!r}: expected one of {list(MATERIALS)}"
            )
        material = self.material
        if config is not None:
            if material is not None and material != config.material:
                raise ValueError(
                    f"TwoScaleParams.material = {material!r} but the config's material is "
                    f"{config.material!r}; use params.for_config(config) or matching constructors"
                )
            material = config.material
            missing = [n for n in config.param_names if getattr(self, n) is None]
            if missing:
                raise ValueError(
                    f"config (material={config.material!r}, diffraction={config.diffraction}, "
                    f"apparatus={config.apparatus}) needs parameter(s) {missing}, which are None"
                )
        if material is None:
            material = "conductor" if self.k is not None else "plastic"
        for name, value in self.fields().items():
            if isinstance(value, jax.core.Tracer):
                raise ValueError(
                    "TwoScaleParams.validate needs concrete values; call it outside jit/grad"
                )
            v = np.asarray(value)
            if name in SHARED_FIELDS and v.ndim != 0:
                raise ValueError(f"TwoScaleParams.{name} must be a scalar, got shape {v.shape}")
            if name in CHANNEL_FIELDS and v.ndim > 1:
                raise ValueError(
                    f"TwoScaleParams.{name} must be a scalar or hold one value per channel, "
                    f"got shape {v.shape}"
                )
            bound = bounds_for(name, material)
            bad = ~(np.isfinite(v) & bound.contains(v))
            if np.any(bad):
                raise ValueError(
                    f"TwoScaleParams.{name} = {v.tolist()} is outside the valid range {bound} "
                    f"({_DESCRIPTION[name]}{', ' + material if name == 'eta' else ''})"
                )
        if config is not None:
            for name in CHANNEL_FIELDS:
                if getattr(self, name) is not None:
                    self.channels(name, config)  # raises on a shape the config cannot use
        return self

    # ----------------------------------------------------------------------------- unconstrained
    def to_unconstrained(self) -> TwoScaleParams:
        """The same structure with unconstrained leaves (inverse of :meth:`from_unconstrained`)."""
        out = {n: bounds_for(n, self.kind).inverse(v) for n, v in self.fields().items()}
        return TwoScaleParams(**out, material=self.material)

    @classmethod
    def from_unconstrained(cls, u: TwoScaleParams) -> TwoScaleParams:
        """Map unconstrained leaves into the valid ranges (every real value lands inside)."""
        out = {n: bounds_for(n, u.kind).forward(v) for n, v in u.fields().items()}
        return cls(**out, material=u.material)

    # ----------------------------------------------------------------------------- JSON
    def to_dict(self) -> dict:
        """JSON-friendly dict: ``material`` and the set fields as floats / lists of floats."""
        d = {"material": self.material}
        for n, v in self.fields().items():
            d[n] = np.asarray(v, dtype=np.float64).tolist()
        return d

    @classmethod
    def from_dict(cls, d: dict) -> TwoScaleParams:
        """Inverse of :meth:`to_dict` (values become float64 NumPy-backed arrays)."""
        unknown = set(d) - {*PARAM_ORDER, "material"}
        if unknown:
            raise ValueError(
                f"TwoScaleParams.from_dict: unknown key(s) {sorted(unknown)}; "
                f"expected 'material' and fields of {list(PARAM_ORDER)}"
            )
        values = {
            n: (None if d.get(n) is None else np.asarray(d[n], dtype=np.float64))
            for n in PARAM_ORDER
        }
        return cls(**values, material=d.get("material"))

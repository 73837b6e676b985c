"""A Mitsuba 3 BSDF plugin for the two-scale BRDF (a Python ``mi.BSDF`` subclass calling JAX).

::

    import mitsuba as mi
    import twoscale.mitsuba

    twoscale.mitsuba.register()                     # picks llvm_ad_rgb (or cuda_ad_rgb) if unset
    scene = mi.load_dict({..., "bsdf": {"type": "twoscale", "filename": "params.json"}})
    img = mi.render(scene, spp=64)

    # or from parameters in Python (a loaded mi.BSDF, usable as a scene-dict value):
    bsdf = twoscale.mitsuba.bsdf(twoscale.TwoScaleParams.conductor(...), twoscale.ModelConfig())

**What it computes.** ``eval`` is :func:`twoscale.brdf` ``× cos θ_o`` (Mitsuba's ``eval`` includes
the foreshortening), ``pdf`` is :func:`twoscale.pdf`, ``sample`` draws with
:meth:`twoscale.sampling.Sampler.sample` from ``u = (sample1, sample2.x, sample2.y)`` and returns
the weight ``eval / pdf``. The tables of the sampler are built once per BSDF
(:func:`twoscale.sampling.sampler`). Directions are Mitsuba's local shading frame (``si.wi`` and
``wo`` point away from the surface, normal ``z``), as twoscale's. The BSDF is a glossy reflection,
front side only: everything is 0 when ``wi`` or ``wo`` is at or below the horizon.

**How.** The methods get whole wavefronts of Dr.Jit arrays; they are evaluated, copied to NumPy,
padded to a power of two (at least 256 lanes, so that JAX compiles a few shapes only) and passed
to jitted float32 JAX functions; the results come back as Dr.Jit arrays. This needs concrete
arrays, so :func:`register` switches Dr.Jit's symbolic loops and calls off (the wavefront,
"evaluated" mode; a method called inside a symbolic scope raises a ``RuntimeError`` that says
so). Gradients do not flow through the plugin (the NumPy copy detaches them).

**Fitted records.** ``filename`` is a ``params.json`` of :mod:`twoscale.fit`, read with
:func:`twoscale.fit.record.load_result`; its ``"albedo_table"``, when there, serves
``eval_diffuse_reflectance``. MERL's apparatus factor (``apparatus=True`` in the
records of the MERL protocol) models the gonioreflectometer, not the material: the plugin
switches it off (``apparatus=False``; the parameters ``e`` and ``m`` are then unused) unless the
scene dict says ``"apparatus": True``.

**LLVM.** Mitsuba's ``llvm_*`` variants load ``libLLVM`` at run time. :func:`register` sets
``DRJIT_LIBLLVM_PATH`` (when unset) to the first of :data:`LLVM_CANDIDATES` that exists, and
raises a ``RuntimeError`` naming ``apt-get install libllvm19`` when no LLVM can be loaded.
"""

from __future__ import annotations

import dataclasses
import functools
import os

import jax
import jax.numpy as jnp
import numpy as np

from twoscale import model, sampling
from twoscale.config import ModelConfig
from twoscale.params import TwoScaleParams

__all__ = ["register", "bsdf", "load", "LLVM_CANDIDATES", "PLUGIN_NAME"]

PLUGIN_NAME = "twoscale"

#: Where Debian / Ubuntu's ``libllvm19`` (and a few other versions) put ``libLLVM``.
LLVM_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/llvm-19/lib/libLLVM.so.19.1",
    "/usr/lib/aarch64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
    "/usr/lib/llvm-19/lib/libLLVM-19.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.18.1",
    "/usr/lib/x86_64-linux-gnu/libLLVM-17.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM-15.so",
)

#: Smallest padded wavefront (lanes); larger ones are padded to the next power of two.
MIN_LANES = 256

_LLVM_HELP = (
    "Mitsuba's LLVM backend could not load libLLVM. Install it (Debian/Ubuntu: "
    "`apt-get install libllvm19`) and, if it is not found, set DRJIT_LIBLLVM_PATH to the "
    "libLLVM.so.19.1 that `dpkg -L libllvm19` lists"
)


# ------------------------------------------------------------------------------ set-up
def _set_llvm_path() -> None:
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return
    for path in LLVM_CANDIDATES:
        if os.path.exists(path):
            os.environ["DRJIT_LIBLLVM_PATH"] = path
            return


def _import(variant: str | None = None):
    """Import Mitsuba and set its variant (default: the current one, else cuda_ad_rgb when a
    CUDA device answers, else llvm_ad_rgb); raise a clear error when the backend cannot load."""
    _set_llvm_path()
    import drjit as dr
    import mitsuba as mi

    if variant is None:
        variant = mi.variant()
    if variant is None:
        variant = "cuda_ad_rgb" if dr.has_backend(dr.JitBackend.CUDA) else "llvm_ad_rgb"
    try:
        if mi.variant() != variant:
            mi.set_variant(variant)
        if variant.startswith("llvm"):
            dr.eval(mi.Float([0.0]))
    except ImportError as err:  # Dr.Jit raises ImportError when libLLVM is missing
        if not variant.startswith("llvm"):
            raise
        raise RuntimeError(f"{_LLVM_HELP} ({type(err).__name__}: {err})") from err
    return mi, dr


# ------------------------------------------------------------------------------ JAX kernels
def _value(params, wi, wo, cfg):
    value = model.brdf(params, wi, wo, cfg) * jnp.clip(wo[..., 2], 0.0, None)[..., None]
    above = (wi[..., 2] > 0.0) & (wo[..., 2] > 0.0)
    return jnp.where(above[..., None] & jnp.isfinite(value), value, 0.0)


@functools.partial(jax.jit, static_argnames=("cfg", "what"))
def _eval_pdf(params, smp, wi, wo, cfg, what):
    """``what``: "eval" → value, "pdf" → density, "both" → (value, density)."""
    if what == "eval":
        return _value(params, wi, wo, cfg)
    if what == "pdf":
        return smp.pdf(wi, wo)
    return _value(params, wi, wo, cfg), smp.pdf(wi, wo)


@functools.partial(jax.jit, static_argnames=("cfg",))
def _sample(params, smp, wi, u, cfg):
    wo, pdf = smp.sample(wi, u)
    value = _value(params, wi, wo, cfg)
    ok = (pdf > 0.0) & (wi[..., 2] > 0.0) & (wo[..., 2] > 0.0)
    weight = jnp.where(ok[..., None], value / jnp.where(ok, pdf, 1.0)[..., None], 0.0)
    weight = jnp.where(jnp.isfinite(weight), weight, 0.0)
    return wo, jnp.where(ok, pdf, 0.0), weight


def _lanes(n: int) -> int:
    return max(MIN_LANES, 1 << max(0, n - 1).bit_length())


def _pad(a: np.ndarray, lanes: int) -> np.ndarray:
    """``(n, k)`` → ``(lanes, k)`` float32, the padding a valid upward direction."""
    out = np.zeros((lanes, a.shape[1]), np.float32)
    out[:, -1] = 1.0
    out[: a.shape[0]] = a
    return out


# ------------------------------------------------------------------------------ the material
@dataclasses.dataclass
class _Material:
    """One parameter set ready for the kernels (float32, the config's fields only)."""

    params: TwoScaleParams
    config: ModelConfig
    sampler: sampling.Sampler

    @classmethod
    def build(cls, params: TwoScaleParams, config: ModelConfig | None) -> _Material:
        if config is None:
            config = ModelConfig(material=params.kind if params.kind != "dielectric" else "plastic")
        if config.n_channels != 3:
            raise ValueError(
                f"the Mitsuba plugin renders RGB: the config gives {config.n_channels} channels "
                "(spectral_output='spectrum'); use the RGB output"
            )
        params = params.for_config(config).astype(jnp.float32)
        smp = sampling.sampler(params, config, jnp.float32)
        return cls(params, config, smp)

    @functools.cached_property
    def albedo(self) -> np.ndarray:
        """``(m, 3)``: the directional albedo at ``cos θ_i = (i+1)/m``: a record's own
        ``"albedo_table"`` (``m = 256``) when loaded from one, else built on first use (``m = 64``)."""
        return np.asarray(sampling.albedo_table(self.params, 64, self.config), np.float32)

    def eval_pdf(self, wi: np.ndarray, wo: np.ndarray, what: str = "both"):
        """``(value (n, 3), pdf (n,))``; ``what`` = "eval" or "pdf" computes one (other None)."""
        n = wi.shape[0]
        lanes = _lanes(n)
        out = _eval_pdf(
            self.params, self.sampler, _pad(wi, lanes), _pad(wo, lanes), self.config, what
        )
        v, p = {"eval": (out, None), "pdf": (None, out), "both": out}[what]
        return (None if v is None else np.asarray(v)[:n]), (
            None if p is None else np.asarray(p)[:n]
        )

    def sample(self, wi: np.ndarray, u: np.ndarray):
        n = wi.shape[0]
        lanes = _lanes(n)
        u_pad = np.full((lanes, 3), 0.5, np.float32)
        u_pad[:n] = u
        wo, p, w = _sample(self.params, self.sampler, _pad(wi, lanes), u_pad, self.config)
        return np.asarray(wo)[:n], np.asarray(p)[:n], np.asarray(w)[:n]

    def directional_albedo(self, cos_i: np.ndarray) -> np.ndarray:
        m = self.albedo.shape[0]
        x = (np.arange(m, dtype=np.float32) + 1.0) / m
        out = np.stack([np.interp(cos_i, x, self.albedo[:, c]) for c in range(3)], axis=-1)
        return np.where((cos_i > 0.0)[:, None], out, 0.0).astype(np.float32)


def _material_from_file(filename: str, apparatus: bool = False) -> _Material:
    from twoscale.fit.record import load_result

    result = load_result(filename)
    config = result.model_config
    if not isinstance(config, ModelConfig):
        raise ValueError(f"{filename}: a {result.model!r} fit, not a two-scale one")
    material = _Material.build(result.params, dataclasses.replace(config, apparatus=apparatus))
    table = result.albedo_values()  # the record's own table (256 rows, float64), if any
    if (
        table is not None
        and not apparatus
        and not result.albedo_table.get("apparatus", True)
        and table.shape[1:] == (3,)
        and np.all(np.isfinite(table))
    ):
        material.__dict__["albedo"] = table.astype(np.float32)  # the cached_property's value
    return material


# ------------------------------------------------------------------------------ Mitsuba class
def _columns(dr, x, n: int) -> np.ndarray:
    """A Dr.Jit 3-vector (or width-1 broadcast) → ``(n, 3)`` float32."""
    a = np.asarray(x.numpy(), np.float32).reshape(3, -1).T
    return np.broadcast_to(a, (n, 3)) if a.shape[0] != n else a


@functools.cache
def _bsdf_class(variant: str):
    """The ``mi.BSDF`` subclass for a variant (Mitsuba's classes are per variant)."""
    import drjit as dr
    import mitsuba as mi

    flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide

    class TwoScaleBSDF(mi.BSDF):
        """The two-scale BRDF as a Mitsuba BSDF (see :mod:`twoscale.mitsuba`)."""

        def __init__(self, props, material: _Material | None = None):
            mi.BSDF.__init__(self, props)
            if material is None:
                if "filename" not in props:
                    raise ValueError(
                        "twoscale BSDF: give 'filename' (a params.json of twoscale.fit), or build "
                        "it in Python with twoscale.mitsuba.bsdf(params, config)"
                    )
                resolver = mi.file_resolver() if hasattr(mi, "file_resolver") else None
                if resolver is None:  # Mitsuba < 3.7
                    resolver = mi.Thread.thread().file_resolver()
                filename = str(resolver.resolve(str(props["filename"])))
                apparatus = bool(props.get("apparatus", False))
                material = _material_from_file(filename, apparatus)
                self.filename = filename
            else:
                self.filename = None
            self.material = material
            self.m_flags = flags
            self.m_components = [flags]

        # -------------------------------------------------------------- plumbing
        @staticmethod
        def _width(*xs) -> int:
            widths = [dr.width(x) for x in xs]
            return 0 if 0 in widths else max(widths)

        @staticmethod
        def _check_scope():
            if dr.flag(dr.JitFlag.SymbolicScope):
                raise RuntimeError(
                    "twoscale BSDF called inside a symbolic Dr.Jit scope (a recorded loop or "
                    "call): it needs concrete wavefronts. Call twoscale.mitsuba.register() (which "
                    "switches dr.JitFlag.SymbolicLoops and SymbolicCalls off) before rendering"
                )

        def _eval_pdf_np(self, si, wo, active, what="both"):
            self._check_scope()
            n = self._width(si.wi, wo, active)
            if n == 0:
                return None, 0
            dr.eval(si.wi, wo, active)
            wi_np, wo_np = _columns(dr, si.wi, n), _columns(dr, wo, n)
            act = np.broadcast_to(np.asarray(active.numpy(), bool).reshape(-1), (n,))
            v, p = self.material.eval_pdf(wi_np, wo_np, what)
            if v is not None:
                v = np.ascontiguousarray(np.where(act[:, None], v, 0.0).T, np.float32)
            if p is not None:
                p = np.where(act, p, 0.0).astype(np.float32)
            return (v, p), n

        # -------------------------------------------------------------- BSDF interface
        def eval(self, ctx, si, wo, active=True):
            active = mi.Bool(active)
            if not ctx.is_enabled(mi.BSDFFlags.GlossyReflection):
                return dr.zeros(mi.Color3f, self._width(si.wi, wo, active))
            out, n = self._eval_pdf_np(si, wo, active, "eval")
            if out is None:
                return dr.zeros(mi.Color3f, 0)
            return mi.Color3f(out[0])

        def pdf(self, ctx, si, wo, active=True):
            active = mi.Bool(active)
            if not ctx.is_enabled(mi.BSDFFlags.GlossyReflection):
                return dr.zeros(mi.Float, self._width(si.wi, wo, active))
            out, n = self._eval_pdf_np(si, wo, active, "pdf")
            if out is None:
                return dr.zeros(mi.Float, 0)
            return mi.Float(out[1])

        def eval_pdf(self, ctx, si, wo, active=True):
            active = mi.Bool(active)
            if not ctx.is_enabled(mi.BSDFFlags.GlossyReflection):
                n = self._width(si.wi, wo, active)
                return dr.zeros(mi.Color3f, n), dr.zeros(mi.Float, n)
            out, n = self._eval_pdf_np(si, wo, active)
            if out is None:
                return dr.zeros(mi.Color3f, 0), dr.zeros(mi.Float, 0)
            return mi.Color3f(out[0]), mi.Float(out[1])

        def sample(self, ctx, si, sample1, sample2, active=True):
            self._check_scope()
            active = mi.Bool(active)
            n = self._width(si.wi, sample1, sample2, active)
            bs = dr.zeros(mi.BSDFSample3f, n)
            if n == 0 or not ctx.is_enabled(mi.BSDFFlags.GlossyReflection):
                return bs, dr.zeros(mi.Color3f, n)
            dr.eval(si.wi, sample1, sample2, active)
            wi_np = _columns(dr, si.wi, n)
            s2 = np.asarray(sample2.numpy(), np.float32).reshape(2, -1)
            u = np.empty((n, 3), np.float32)
            u[:, 0] = np.broadcast_to(np.asarray(sample1.numpy(), np.float32).reshape(-1), (n,))
            u[:, 1] = np.broadcast_to(s2[0], (n,))
            u[:, 2] = np.broadcast_to(s2[1], (n,))
            act = np.broadcast_to(np.asarray(active.numpy(), bool).reshape(-1), (n,))
            wo, p, w = self.material.sample(wi_np, u)
            p = np.where(act, p, 0.0).astype(np.float32)
            w = np.where((p > 0.0)[:, None], w, 0.0).astype(np.float32)
            bs.wo = mi.Vector3f(np.ascontiguousarray(wo.T))
            bs.pdf = mi.Float(p)
            bs.eta = mi.Float(dr.full(mi.Float, 1.0, n))
            bs.sampled_type = dr.full(mi.UInt32, int(mi.BSDFFlags.GlossyReflection), n)
            bs.sampled_component = dr.zeros(mi.UInt32, n)
            return bs, mi.Color3f(np.ascontiguousarray(w.T))

        def eval_diffuse_reflectance(self, si, active=True):
            """The directional albedo at ``si.wi`` (all lobes; interpolated in the albedo table)."""
            self._check_scope()
            n = self._width(si.wi, mi.Bool(active))
            if n == 0:
                return dr.zeros(mi.Color3f, 0)
            dr.eval(si.wi)
            cos_i = _columns(dr, si.wi, n)[:, 2]
            return mi.Color3f(np.ascontiguousarray(self.material.directional_albedo(cos_i).T))

        def traverse(self, callback):
            return

        def parameters_changed(self, keys):
            return

        def to_string(self):
            m = self.material
            fields = ", ".join(
                f"{k}={np.round(np.asarray(v, np.float64), 4).tolist()}"
                for k, v in m.params.fields().items()
            )
            return (
                f"TwoScaleBSDF[material={m.config.material}, diffraction={m.config.diffraction}, "
                f"shadowing={m.config.shadowing}, apparatus={m.config.apparatus}, {fields}"
                + (f", filename={self.filename!r}" if self.filename else "")
                + "]"
            )

    return TwoScaleBSDF


# ------------------------------------------------------------------------------ public API
def register(variant: str | None = None) -> str:
    """Register the BSDF type ``"twoscale"`` with Mitsuba 3; returns the variant it is
    registered for.

    ``variant``: the Mitsuba variant to set (default: the current one, else ``cuda_ad_rgb`` when
    a CUDA device is there, else ``llvm_ad_rgb``); an RGB variant (``*_rgb``). Sets
    ``DRJIT_LIBLLVM_PATH`` when unset (:data:`LLVM_CANDIDATES`), and switches Dr.Jit's symbolic
    loops and calls off (the plugin needs concrete wavefronts). Registering again is harmless.
    """
    mi, dr = _import(variant)
    v = mi.variant()
    if not v.endswith("_rgb"):
        raise ValueError(f"the twoscale plugin needs an RGB variant (e.g. llvm_ad_rgb), not {v!r}")
    dr.set_flag(dr.JitFlag.SymbolicLoops, False)
    dr.set_flag(dr.JitFlag.SymbolicCalls, False)
    cls = _bsdf_class(v)
    mi.register_bsdf(PLUGIN_NAME, lambda props: cls(props))
    return v


def bsdf(params: TwoScaleParams, config: ModelConfig | None = None):
    """A loaded Mitsuba BSDF of the two-scale model from Python parameters.

    ``config``: the :class:`~twoscale.ModelConfig` (default: ``ModelConfig`` with the parameters'
    material). Use the result as a scene-dict value (``{"type": "sphere", "bsdf": bsdf(...)}``)
    or call its methods directly. Calls :func:`register` first.
    """
    v = register()
    import mitsuba as mi

    props = mi.Properties(PLUGIN_NAME)
    return _bsdf_class(v)(props, _Material.build(params, config))


def load(filename, apparatus: bool = False):
    """A loaded Mitsuba BSDF from a fitted ``params.json`` (apparatus factor off by default)."""
    register()
    import mitsuba as mi

    return mi.load_dict({"type": PLUGIN_NAME, "filename": str(filename), "apparatus": apparatus})

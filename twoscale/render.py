"""A fitted material rendered in Mitsuba 3 next to the measured data: ``render.png`` of
``python -m twoscale.fit ... --render``.

The scene is the one of :func:`twoscale.plots.sphere_directions`, so that both halves of the
picture see the same lighting: a unit sphere seen by an **orthographic** camera along −z (the
sphere fills the frame), lit by a single **distant (directional) light** of unit irradiance at
``light_deg`` from the view direction, in the x-z plane, and nothing else (no environment, one
bounce: Mitsuba's ``direct`` integrator with emitter sampling only). A pixel's radiance is then
``ρ(i, o) cos θ_i``, exactly what :func:`twoscale.plots.render_spheres` computes from the MERL
table (nearest-bin lookup) for the measured side. The rendered side is the two-scale plugin
(:mod:`twoscale.mitsuba`) with the fitted parameters, MERL's apparatus factor switched off (the
plugin's default: the factor models the gonioreflectometer, not the material), so at grazing
angles, on the rim of the sphere, the measured side can be darker by that factor.

Mitsuba's variant is the plugin's (``llvm_ad_rgb``, or ``cuda_ad_rgb`` when a GPU answers).
:func:`check_available` tells, before any fitting, whether Mitsuba and its LLVM backend load.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import numpy as np

__all__ = ["RenderUnavailable", "check_available", "render_sphere", "write_render"]

#: Defaults of ``render.png``: pixels per side, samples per pixel, light angle (degrees).
SIZE, SPP, LIGHT_DEG = 128, 16, 30.0


class RenderUnavailable(RuntimeError):
    """Mitsuba 3 or its LLVM backend cannot be loaded (the message says how to install it)."""


def check_available() -> str:
    """Import Mitsuba 3 and register the plugin; return the variant.

    Raises :class:`RenderUnavailable` with a one-line message when Mitsuba is not installed or
    its backend (libLLVM) cannot be loaded.
    """
    try:
        import twoscale.mitsuba as tm

        return tm.register()
    except ImportError as err:
        raise RenderUnavailable(
            f"--render needs Mitsuba 3 (pip install -e '.[mitsuba]'): {err}".replace("\n", " ")
        ) from None
    except RuntimeError as err:  # no libLLVM: the plugin's message names apt-get install
        raise RenderUnavailable(f"--render: {err}".replace("\n", " ")) from None


def scene_dict(bsdf, *, size: int = SIZE, spp: int = SPP, light_deg: float = LIGHT_DEG) -> dict:
    """The Mitsuba scene (see the module doc): ``bsdf`` on a unit sphere at the origin."""
    import mitsuba as mi

    a = math.radians(light_deg)
    return {
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
        "sensor": {
            "type": "orthographic",
            "to_world": mi.ScalarTransform4f().look_at(
                origin=[0.0, 0.0, 10.0], target=[0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0]
            ),
            "film": {
                "type": "hdrfilm",
                "width": size,
                "height": size,
                "rfilter": {"type": "box"},
                "pixel_format": "rgb",
            },
            "sampler": {"type": "independent", "sample_count": spp},
        },
        # The light travels towards the sphere: from (sin a, 0, cos a) to the origin.
        "light": {
            "type": "directional",
            "direction": [-math.sin(a), 0.0, -math.cos(a)],
            "irradiance": {"type": "rgb", "value": 1.0},
        },
        "sphere": {"type": "sphere", "center": [0.0, 0.0, 0.0], "radius": 1.0, "bsdf": bsdf},
    }


def render_sphere(
    params,
    config,
    *,
    size: int = SIZE,
    spp: int = SPP,
    light_deg: float = LIGHT_DEG,
    seed: int = 0,
) -> np.ndarray:
    """Linear radiance ``(size, size, 3)`` of the sphere of two-scale ``params`` (a
    :class:`~twoscale.ModelConfig` ``config``, used as given) rendered by Mitsuba 3."""
    import twoscale.mitsuba as tm

    check_available()
    import mitsuba as mi

    scene = mi.load_dict(
        scene_dict(tm.bsdf(params, config), size=size, spp=spp, light_deg=light_deg)
    )
    img = np.asarray(mi.render(scene, seed=seed), np.float64)
    return img[..., :3]


def _panel_images(meas, rendered, mask):
    from twoscale.plots import _tonemap

    ref = meas[mask].max(axis=-1)
    level = np.percentile(ref, 99.5) if ref.size else 0.0
    if not level > 0:  # nothing measured lit: expose for the render instead
        level = np.percentile(rendered[mask].max(axis=-1), 99.5) if mask.any() else 1.0
    scale = 1.0 / level if level > 0 else 1.0
    return _tonemap(meas, scale), _tonemap(rendered, scale)


def write_render(
    result,
    data,
    path,
    *,
    size: int = SIZE,
    spp: int = SPP,
    light_deg: float = LIGHT_DEG,
) -> dict:
    """Write ``path`` (PNG): the measured sphere (MERL lookup) and the fitted material rendered
    in Mitsuba 3, same lighting and exposure (99.5th percentile of the measured sphere).

    ``result``: a two-scale :class:`~twoscale.fit.FitResult`. Returns ``{"seconds", "spp",
    "size", "variant"}`` (the render's time includes building the BSDF and compiling its
    kernels on first use).
    """
    from twoscale.config import ModelConfig
    from twoscale.plots import _save, _subplots, render_spheres

    config = result.model_config
    if not isinstance(config, ModelConfig):
        raise ValueError(f"--render renders two-scale fits, not a {result.model!r} one")
    variant = check_available()
    config = dataclasses.replace(config, apparatus=False)
    t = time.perf_counter()
    rendered = render_sphere(result.params, config, size=size, spp=spp, light_deg=light_deg)
    seconds = time.perf_counter() - t
    if not np.all(np.isfinite(rendered)):
        raise ValueError("the Mitsuba render has NaN/inf pixels")
    meas, _, mask = render_spheres(
        data, lambda wi, wo: np.zeros(np.shape(wi)), size=size, light_deg=light_deg
    )
    left, right = _panel_images(meas, rendered, mask)
    fig, axes = _subplots(1, 2, figsize=(7, 3.8))
    names = ("measured (MERL lookup)", f"fit, Mitsuba 3 ({spp} spp)")
    for ax, img, name in zip(axes, (left, right), names, strict=True):
        ax.imshow(img, interpolation="nearest")
        ax.set_title(name)
        ax.axis("off")
    # Broken after the name by _save when wider than the picture (plots._wrap_title).
    title = (
        f"{getattr(data, 'name', '') or 'data'}: distant light at {light_deg:g}° from the view "
        "(render: no apparatus factor)"
    )
    _save(fig, Path(path), title)
    return {"seconds": seconds, "spp": spp, "size": size, "variant": variant}

"""twoscale: a pure-JAX, differentiable two-scale microfacet BRDF [HP17] with MERL fitting.

The public surface (everything else lives in the submodules, which are public too)::

    import twoscale
    params = twoscale.TwoScaleParams.conductor(beta=0.1, p=1.5, eta=(0.2, 0.5, 1.4),
                                              k=(3.5, 2.5, 1.9), sigma_s=0.01, b=1.5, c=2.2)
    rho = twoscale.brdf(params, wi, wo)                 # (..., 3), 1/sr, without cos θ_o
    parts = twoscale.lobes(params, wi, wo)              # {"specular", "diffraction", ...}
    a = twoscale.albedo(params, cos_theta_i)            # directional albedo
    wo, pdf = twoscale.sample(params, wi, u)            # importance sampling, u: (..., 3) uniforms
    energy = twoscale.albedo_table(params, 256)         # albedo at cos θ_i = (i+1)/256
    table = twoscale.brdf_merl(params)                  # (90, 90, 180, 3) on the MERL grid, fast
    result = twoscale.fit(twoscale.merl.read("gold-metallic-paint.binary"))  # needs float64

Components: :mod:`twoscale.fresnel`, :mod:`twoscale.distribution` (EPD), :mod:`twoscale.shadowing`
(Smith Λ, G), :mod:`twoscale.psd` (K-correlation PSD, renormalisation), :mod:`twoscale.convolution`
(S*D), :mod:`twoscale.sampling` (importance sampling, albedo table),
:mod:`twoscale.tables` (C² spline tables), :mod:`twoscale.geometry`, :mod:`twoscale.merl`
(MERL .binary I/O), :mod:`twoscale.spectral` (n,k presets, spectrum → sRGB),
:mod:`twoscale.baselines` (GGX/Beckmann Cook-Torrance + Lambert), :mod:`twoscale.plots`.

``twoscale.fit`` is both the fitting function (``twoscale.fit(data, ...)``) and the package that
holds the driver, the result record and the command line (``python -m twoscale.fit``).

Float64 is never switched on at import: enable it with
``jax.config.update("jax_enable_x64", True)`` for fitting and for float64 evaluation.

References:
    [HP17] N. Holzschuch, R. Pacanowski, "A Two-Scale Microfacet Reflectance Model Combining
        Reflection and Diffraction", ACM TOG 36(4) 66, 2017.
"""

from twoscale import _xla

if _xla.started_as_cli():
    # `python -m twoscale.fit`: before JAX's import (by the modules below), the CLI's option that
    # JAX reads then: large constants passed to compiled code as arguments (twoscale._xla).
    # Imported as a library, twoscale changes no JAX setting.
    _xla.hoist_large_constants()

from twoscale import (  # noqa: E402
    baselines as baselines,
)
from twoscale import (
    convolution as convolution,
)
from twoscale import (
    distribution as distribution,
)
from twoscale import fit as fit
from twoscale import (
    fresnel as fresnel,
)
from twoscale import (
    geometry as geometry,
)
from twoscale import (
    merl as merl,
)
from twoscale import model as model
from twoscale import (
    psd as psd,
)
from twoscale import sampling as sampling
from twoscale import (
    shadowing as shadowing,
)
from twoscale import (
    spectral as spectral,
)
from twoscale import (
    tables as tables,
)
from twoscale.config import ModelConfig as ModelConfig
from twoscale.fit import FitResult as FitResult
from twoscale.fit import load_result as load_result
from twoscale.merl import MerlData as MerlData
from twoscale.model import albedo as albedo
from twoscale.model import brdf as brdf
from twoscale.model import brdf_grid as brdf_grid
from twoscale.model import brdf_merl as brdf_merl
from twoscale.model import lobes as lobes
from twoscale.params import TwoScaleParams as TwoScaleParams
from twoscale.sampling import albedo_table as albedo_table
from twoscale.sampling import pdf as pdf
from twoscale.sampling import sample as sample

__version__ = "0.1.0"

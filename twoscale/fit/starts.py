"""Initial guesses from the data: specular peak, peak width, diffuse level.

The estimates are deliberately simple and robust (medians and means over bands of the MERL grid,
lower-edge bin angles ``θ_h(i) = (i/90)² π/2``, ``θ_d(j) = j π/180``):

- ``peak``: the mean measured value at ``θ_h = 0`` for ``θ_d ≤ 4°`` (per channel);
- ``floor``: the median value over ``θ_h ∈ [50°, 70°]``, ``θ_d ≤ 30°`` (the diffuse level of a
  dielectric, the far tail of a conductor);
- ``albedo``: the bihemispherical albedo over the valid cells
  (:func:`twoscale.merl.bihemispherical_albedo`): how much light the material reflects in all;
- ``width``: the ``θ_h`` (rad) where the luminance profile above the floor, averaged over
  ``θ_d ≤ 4°`` and all ``φ_d``, falls to ``1/e`` of its peak. For the EPD this is where
  ``(tan²θ_h/β²)^p = 1``, so ``β ≈ tan(width)`` whatever ``p``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from twoscale.merl import axis_angles, bihemispherical_albedo
from twoscale.model import LUMINANCE

_LUMA = np.asarray(LUMINANCE)


@dataclasses.dataclass(frozen=True)
class DataStats:
    """Summary numbers of a measured BRDF used to place the starts (see module doc)."""

    peak: np.ndarray  # (C,) 1/sr
    floor: np.ndarray  # (C,) 1/sr
    width: float  # rad
    albedo: np.ndarray | None = None  # (C,) bihemispherical albedo over the valid cells

    @property
    def beta(self) -> float:
        """EPD roughness whose ``1/e`` half-width matches the measured peak, clipped to [0.003, 0.9]."""
        return float(np.clip(math.tan(min(self.width, 1.4)), 0.003, 0.9))

    def to_dict(self) -> dict:
        return {
            "peak": [float(x) for x in self.peak],
            "floor": [float(x) for x in self.floor],
            "width_rad": float(self.width),
            "albedo": None if self.albedo is None else [float(x) for x in self.albedo],
        }


def _masked_mean(values, valid, axes):
    w = valid.astype(np.float64)
    s = (values * w[..., None]).sum(axis=axes)
    n = w.sum(axis=axes)
    return s / np.maximum(n, 1.0)[..., None], n


def data_stats(values: np.ndarray, valid: np.ndarray) -> DataStats:
    """Estimate peak, floor and peak width from a ``(90, 90, 180, C)`` MERL table."""
    values = np.asarray(values, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool) & np.all(np.isfinite(values), axis=-1)
    n_ch = values.shape[-1]
    theta_h, _, _ = axis_angles("lower")
    luma = _LUMA if n_ch == 3 else np.full(n_ch, 1.0 / n_ch)

    # Profile along θ_h near normal incidence (θ_d ≤ 4°), averaged over φ_d and θ_d.
    near = slice(0, 5)
    prof, count = _masked_mean(values[:, near], valid[:, near], axes=(1, 2))  # (90, C)
    have = count > 0
    if not have.any():  # no valid cell near normal incidence: use every θ_d
        prof, count = _masked_mean(values, valid, axes=(1, 2))
        have = count > 0
    first = int(np.argmax(have))
    peak = prof[first]

    floor = np.minimum(floor_level(values, valid), peak)

    lum = (prof - floor) @ luma
    lum0 = lum[first]
    width = 0.5
    if lum0 > 0:
        target = lum0 / math.e
        for i in range(first + 1, theta_h.size):
            if have[i] and lum[i] <= target:
                # Interpolate in log(lum) between bins i−1 and i.
                a, b = max(lum[i - 1], 1e-300), max(lum[i], 1e-300)
                t = (
                    0.0
                    if a <= target
                    else np.clip(np.log(a / target) / max(np.log(a / b), 1e-12), 0.0, 1.0)
                )
                width = float(theta_h[i - 1] + t * (theta_h[i] - theta_h[i - 1]))
                break
    width = max(width, 0.5 * float(theta_h[1]))
    return DataStats(
        peak=np.maximum(peak, 0.0),
        floor=np.maximum(floor, 0.0),
        width=width,
        albedo=bihemispherical_albedo(values, valid),
    )


def floor_level(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``(C,)``: the median over the valid cells of ``θ_h ∈ [50°, 70°]``, ``θ_d ≤ 30°`` of a
    ``(90, 90, 180, C)`` MERL table (measured or modelled): the level of a dielectric's diffuse
    body, the far tail of a metal's lobe; 0 where the band has no valid cell."""
    theta_h, theta_d, _ = axis_angles("lower")
    band = (theta_h >= np.radians(50)) & (theta_h <= np.radians(70))
    dband = theta_d <= np.radians(30)
    values = np.asarray(values)
    sel = np.asarray(valid)[band][:, dband]
    vals = values[band][:, dband][sel]
    return np.median(vals, axis=0) if vals.size else np.zeros(values.shape[-1])


def conductor_k_for_f0(f0, eta):
    """Extinction ``k`` giving normal-incidence reflectance ``F0`` for a real index ``η``.

    ``F0 = ((η−1)² + k²)/((η+1)² + k²)``  ⇒  ``k² = (F0 (η+1)² − (η−1)²)/(1 − F0)`` (0 if negative).
    """
    f0 = np.clip(np.asarray(f0, dtype=np.float64), 1e-4, 0.995)
    k2 = (f0 * (eta + 1) ** 2 - (eta - 1) ** 2) / (1 - f0)
    return np.sqrt(np.maximum(k2, 0.0))


def dielectric_eta_for_f0(f0):
    """Real index ``η`` with normal-incidence reflectance ``F0``: ``η = (1 + √F0)/(1 − √F0)``."""
    s = np.sqrt(np.clip(np.asarray(f0, dtype=np.float64), 1e-6, 0.5))
    return (1 + s) / (1 - s)

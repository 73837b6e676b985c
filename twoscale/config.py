"""Static model configuration: which material, which lobes, which approximations [docs/model.md §2-3].

A :class:`ModelConfig` is frozen and hashable, so it can be a static argument of ``jax.jit``; every
field is checked when it is built and a bad value raises a ``ValueError`` naming the field.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from twoscale.spectral import RGB_WAVELENGTHS

#: Shortest and longest wavelength (µm) a configuration may use. 0.35 µm: b's upper end, 350 µm,
#: keeps u = (b/λ) cos θ_d inside the convolution table (u ≤ 1000) only from there on; beyond
#: its u axis the table has nothing to give (the lobe held at u = 1000 is up to 2.5× the exact
#: lobe of u = 1500, docs/model.md §4). The visible range, the spectral default (from 0.38 µm)
#: and RGB (0.444–0.645 µm) are inside.
MIN_WAVELENGTH = 0.35
MAX_WAVELENGTH = 2.0

__all__ = ["ModelConfig", "MATERIALS", "PARAM_ORDER"]

MATERIALS = ("conductor", "plastic", "subsurface")
Q_MODES = ("2F", "F", "full")
SHADOWING = ("correlated", "uncorrelated")
#: The angles of the apparatus factor (``ModelConfig.apparatus_angles``).
APPARATUS_ANGLES = ("theta_io", "theta_d")
PATHS = ("tables", "exact")
SPECTRAL_OUTPUTS = ("rgb", "spectrum")
FRESNEL_FORMS = ("exact", "schlick")

# Canonical order of the parameters (as in the paper's list, §4, plus the apparatus factor's
# exponent e and knee exponent m).
PARAM_ORDER = ("beta", "p", "sigma_s", "b", "c", "eta", "k", "rho_d", "e", "m")


def _choice(name: str, value, options) -> None:
    if value not in options:
        raise ValueError(f"ModelConfig.{name} = {value!r}: expected one of {list(options)}")


@dataclass(frozen=True)
class ModelConfig:
    """What the two-scale BRDF evaluates (static; hashable; validated at construction).

    Fields:
        material: ``"conductor"`` (complex index η + ik, no diffuse layer), ``"plastic"`` (varnish
            over a diffuse layer) or ``"subsurface"`` (§3.9). Default ``"conductor"``.
        specular: the rough-specular (Cook-Torrance) lobe scaled by ``A_s`` (§2, line 2).
        diffraction: the diffraction lobe ``(1 − A_s) Q G (S*D)`` (§2, line 3). Off ⇒ ``A_s = 1``
            and the nano-scale parameters ``sigma_s, b, c`` are not used.
        diffuse: the diffuse layer of dielectrics (for conductors, see ``conductor_floor``).
        q_mode: polarisation factor of the diffraction lobe: ``"2F"`` (reference), ``"F"``
            (energy-conserving switch) or ``"full"`` (§3.7).
        shadowing: ``"correlated"`` (height-direction correlated Smith with van Ginneken's factor,
            φ wrapped into [0, π]; reference) or ``"uncorrelated"`` (``G1(i) G1(o)``).
        apparatus: multiply the specular lobe by MERL's ``L(θ_i) L(θ_o)``,
            ``L(θ) = [1 − (2θ/π)^m]^e`` (§3.11); adds ``e`` (m = 2, the paper's form).
        apparatus_knee: with ``apparatus``, also fit the knee exponent ``m`` of ``L`` (adds ``m``;
            the MERL protocol's default, :func:`twoscale.fit.merl_protocol`). Ignored without
            ``apparatus``.
        apparatus_angles: the angles of the apparatus factor: ``"theta_io"``, ``L(θ_i) L(θ_o)``
            (the paper's form; default), or ``"theta_d"``, ``L(θ_d)²``: the same at the mirror
            direction (where θ_i = θ_o = θ_d), off it a function of the half angle between the
            directions only, which leaves the forward grazing cells of rough lobes undimmed
            (measured better on rough MERL stand-ins, §3.11). Ignored without ``apparatus``.
        diffuse_eta2: divide the plastic diffuse layer by ``η̄²`` (radiance compression at the
            varnish, as in Weidlich-Wilkie style layered models). Off (default) is the reference's
            §3.9 form, which has no ``1/η²`` and whose albedo exceeds 1 for bright layers
            (ρ_d = 0.95, η = 1.5: ≈ 1.95); on, the diffuse albedo is at most ``1 − F(θ_i)``.
            Only the plastic diffuse term changes (subsurface keeps §3.9).
        diffuse_fresnel: the plastic diffuse layer seen through the varnish: the Fresnel
            transmissions ``(1 − F_i)(1 − F_o)`` and the inter-reflection ``1/(1 − ρ_d F_dr)``
            (§3.9, the reference; default). Off: a Lambertian body ``ρ_d/π`` under the same
            specular and diffraction lobes, which the varnish's η then no longer darkens towards
            grazing angles (the form MERL's diffuse-dominated materials follow; see §8). Applies
            to the plastic; ignored for the other materials.
        fresnel: the reflectance of a dielectric coat (plastic, subsurface) in the specular and
            diffraction lobes and in the diffuse layer's transmissions: ``"exact"`` (the
            unpolarised Fresnel equations; reference; default) or ``"schlick"`` (Schlick's form
            ``F0 + (1 − F0)(1 − cos θ)⁵`` with the same ``F0(η)``, flatter at mid angles and steeper
            towards grazing; the fitter chooses it where measured data follow it better,
            docs/model.md §8). Conductors keep the exact ``(η, k)`` form (Schlick's would leave
            ``η`` and ``k`` one value per channel to share); the full polarisation factor
            (``q_mode="full"``) needs the exact form.
        path: ``"tables"`` (precomputed C² spline tables; fast) or ``"exact"`` (quadrature).
        wavelengths: wavelengths in µm at which the model is evaluated; the default is the three
            RGB wavelengths (0.645, 0.526, 0.444), one per output channel.
        spectral_output: with any other wavelengths, ``"rgb"`` (default) integrates the spectrum
            to linear sRGB (CIE 1931 observer under ``illuminant``); ``"spectrum"`` returns one
            channel per wavelength.
        illuminant: illuminant of the spectral → RGB conversion (see ``twoscale.spectral``).
        conductor_floor: a conductor with a faint Lambertian floor ``ρ_d/π`` under its lobes
            (adds ``rho_d``; needs ``diffuse``; not in the reference, §3.9). Measured metals
            scatter a little light diffusely (dust, oxide, multiple scattering), which the
            reference's conductor renders black; the fitter adds the floor to a conductor once
            the material type is chosen (docs/model.md §8). Set to False for dielectrics.
    """

    material: str = "conductor"
    specular: bool = True
    diffraction: bool = True
    diffuse: bool = True
    q_mode: str = "2F"
    shadowing: str = "correlated"
    apparatus: bool = False
    apparatus_knee: bool = False
    apparatus_angles: str = "theta_io"
    diffuse_eta2: bool = False
    diffuse_fresnel: bool = True
    fresnel: str = "exact"
    path: str = "tables"
    wavelengths: tuple[float, ...] = field(default=RGB_WAVELENGTHS)
    spectral_output: str = "rgb"
    illuminant: str = "D65"
    conductor_floor: bool = False

    def __post_init__(self):
        _choice("material", self.material, MATERIALS)
        _choice("q_mode", self.q_mode, Q_MODES)
        _choice("shadowing", self.shadowing, SHADOWING)
        _choice("apparatus_angles", self.apparatus_angles, APPARATUS_ANGLES)
        _choice("path", self.path, PATHS)
        _choice("spectral_output", self.spectral_output, SPECTRAL_OUTPUTS)
        _choice("fresnel", self.fresnel, FRESNEL_FORMS)
        if self.fresnel == "schlick":
            if self.material == "conductor":
                raise ValueError(
                    "ModelConfig: fresnel='schlick' is a dielectric coat's form; a conductor keeps "
                    "the exact (η, k) reflectance"
                )
            if self.q_mode == "full":
                raise ValueError(
                    "ModelConfig: q_mode='full' (the full polarisation factor) needs fresnel='exact'"
                )
        for name in (
            "specular",
            "diffraction",
            "diffuse",
            "apparatus",
            "apparatus_knee",
            "diffuse_eta2",
            "diffuse_fresnel",
            "conductor_floor",
        ):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"ModelConfig.{name} = {getattr(self, name)!r}: expected a bool")
        if not self.diffuse_fresnel:
            if self.diffuse_eta2:
                raise ValueError(
                    "ModelConfig: diffuse_eta2 (radiance compression at the varnish) needs "
                    "diffuse_fresnel=True (a Lambertian body has no varnish transmission)"
                )
        if not isinstance(self.illuminant, str):
            raise ValueError(f"ModelConfig.illuminant = {self.illuminant!r}: expected a name")
        try:
            wl = tuple(float(w) for w in self.wavelengths)
        except TypeError as err:
            raise ValueError(
                f"ModelConfig.wavelengths = {self.wavelengths!r}: expected a sequence of floats (µm)"
            ) from err
        if not wl or not all(MIN_WAVELENGTH <= w <= MAX_WAVELENGTH for w in wl):
            raise ValueError(
                f"ModelConfig.wavelengths = {wl}: expected one or more wavelengths in µm within "
                f"[{MIN_WAVELENGTH:g}, {MAX_WAVELENGTH:g}] (the convolution table's u = (b/λ) "
                f"cos θ_d ends at 1000, which b's range up to 350 µm reaches at 0.35 µm)"
            )
        if wl != tuple(RGB_WAVELENGTHS) and any(b <= a for a, b in zip(wl, wl[1:], strict=False)):
            raise ValueError(
                f"ModelConfig.wavelengths = {wl}: spectral wavelengths must be strictly increasing "
                f"(only the RGB default {tuple(RGB_WAVELENGTHS)} runs R, G, B)"
            )
        object.__setattr__(self, "wavelengths", wl)  # normalise to a hashable tuple of floats
        if self.material != "conductor":  # no meaning for a dielectric: one configuration
            object.__setattr__(self, "conductor_floor", False)
        if not (self.specular or self.diffraction or self.has_diffuse):
            raise ValueError(
                "ModelConfig: every lobe is switched off (specular, diffraction and, for dielectrics, "
                "diffuse); switch at least one on"
            )

    @property
    def is_conductor(self) -> bool:
        return self.material == "conductor"

    @property
    def coat_form_selectable(self) -> bool:
        """A dielectric coat whose Fresnel form may be either the exact equations or Schlick's
        (not a conductor, and not the full polarisation factor, which needs the exact form)."""
        return not self.is_conductor and self.q_mode != "full"

    @property
    def has_diffuse(self) -> bool:
        """The diffuse layer is evaluated (dielectrics with ``diffuse=True``; a conductor with
        ``diffuse`` and ``conductor_floor``)."""
        return self.diffuse and (not self.is_conductor or self.conductor_floor)

    @property
    def lambertian_body(self) -> bool:
        """The diffuse layer is ``ρ_d/π`` alone (a conductor's floor; a plastic's body with
        ``diffuse_fresnel=False``): it depends on no Fresnel term, nor on the luminance mean
        ``η̄`` of the channels' η."""
        return self.is_conductor or (self.material == "plastic" and not self.diffuse_fresnel)

    @property
    def is_spectral(self) -> bool:
        """The wavelengths are not the three RGB ones: the model is evaluated spectrally."""
        return self.wavelengths != tuple(RGB_WAVELENGTHS)

    @property
    def n_wavelengths(self) -> int:
        return len(self.wavelengths)

    @property
    def n_channels(self) -> int:
        """Channels returned by ``brdf``: 3 (RGB, or spectral → RGB), or one per wavelength."""
        if self.is_spectral and self.spectral_output == "rgb":
            return 3
        return self.n_wavelengths

    @property
    def param_names(self) -> tuple[str, ...]:
        """Names of the parameters this configuration uses (in :data:`PARAM_ORDER`)."""
        used = set()
        if self.specular or self.diffraction:
            used |= {"beta", "p"}
        if self.diffraction:
            used |= {"sigma_s", "b", "c"}
        used.add("eta")
        if self.is_conductor:
            used.add("k")
        if self.has_diffuse:
            used.add("rho_d")
        if self.apparatus and self.specular:
            used.add("e")
            if self.apparatus_knee:
                used.add("m")
        return tuple(n for n in PARAM_ORDER if n in used)

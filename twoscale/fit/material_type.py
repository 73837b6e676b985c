"""Which models the fit tries and which material type it keeps: the MERL protocol, the
configurations of ``material="auto"``, and the type choice (docs/model.md §8)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from twoscale.baselines import CookTorranceConfig
from twoscale.fit.starts import floor_level
from twoscale.fresnel import dielectric
from twoscale.model import LUMINANCE, PAPER_KNEE, apparatus_factor

MATERIALS = ("conductor", "plastic", "subsurface")


#: Material types tried by ``material="auto"`` (subsurface is only fitted when asked for).
AUTO_MATERIALS = ("conductor", "plastic")

#: The apparatus factor's angles of the MERL protocol (:func:`merl_protocol`): ``"theta_d"``,
#: ``L(θ_d)²``. The whole campaign with each form (60 stand-ins, four models, 2026-12-06,
#: ``campaigns/RESULTS.md``): the two-scale model below GGX + Lambert on 55 with it against 54
#: with the paper's ``L(θ_i) L(θ_o)``, median improvement 31.4 % against 20.7 %, its own log
#: RMSE median 3.2 % lower, the rough materials up to 46 % lower (both models); higher on three
#: (color-changing-paint1 +14.5 % and specular-green-phenolic +5.0 %, whose special cases'
#: Schlick form fell inside the Fresnel choice's 2 % tie with ``L(θ_d)²`` and outside it with
#: the paper's form: +1.5 % and −0.2 % since :data:`FRESNEL_TRY_RTOL`; silver-paint +2.4 %,
#: another minimum). Refining those three ``L(θ_d)²`` fits once more with the paper's form
#: from their solutions lowered their fitted RMS by 0.8 %, 0 % and 0.2 % only (a last-stage
#: probe, checked on 2026-12-07 and left out). With :data:`FRESNEL_TRY_RTOL`: 55 of 60, 30.8 %.
MERL_APPARATUS_ANGLES = "theta_d"


def merl_protocol(
    *,
    diffraction: bool = True,
    apparatus: bool = True,
    diffuse_fresnel=False,
    apparatus_knee: bool = True,
    shadowing: str = "correlated",
    conductor_floor: bool = True,
    apparatus_angles: str = MERL_APPARATUS_ANGLES,
):
    """The model configuration the fitter uses for MERL data unless told otherwise.

    ``ModelConfig(apparatus=True, apparatus_knee=True, apparatus_angles="theta_d",
    diffuse_fresnel=False, conductor_floor=True)`` (material chosen by the fit):

    - MERL's apparatus factor ``L(θ_d)²``, ``L(θ) = [1 − (2θ/π)^m]^e``, on the specular
      lobe, its exponent ``e`` and knee exponent ``m`` fitted (docs/model.md §3.11): MERL's
      values fall off at grazing angles, and without it the shape parameters are bent to fit
      that fall-off. The knee (``apparatus_knee``; none without ``apparatus``) lets the fall-off
      start late and be steep, as the stand-ins' peaks show: they follow the bare model up to
      θ_d ≈ 80° and drop by a factor 50–200 from 84° to 89° (``campaigns/RESULTS.md``);
    - a plastic's body Lambertian (§3.9): MERL's plastics and fabrics do not darken towards
      grazing angles as the varnish's Fresnel transmission makes the reference body do. On the
      Neural-BRDF stand-ins tried (plastic fits of yellow-plastic, red-fabric2, pink-plastic,
      white-fabric) the Lambertian body lowered the log RMSE by 13 %, 23 %, 18 % and 35 %
      (specular-red-phenolic: equal), and only with it do pink-plastic and white-fabric beat
      GGX + Lambert. ``campaigns/RESULTS.md`` has the whole campaign;
    - the factor's angles (``apparatus_angles``, :data:`MERL_APPARATUS_ANGLES`): ``L(θ_d)²``,
      the same as the paper's ``L(θ_i) L(θ_o)`` at the mirror direction but leaving the
      forward grazing cells of rough lobes undimmed, where the stand-ins keep their values;
    - the reference's height-direction correlated shadowing (``shadowing``; §3.3).
      ``"uncorrelated"`` (``G1(i) G1(o)``, more shadowing at grazing angles) fits rough glossy
      stand-ins better (the fitted RMS of the woods and black-oxidized-steel 3–9 % lower), but
      GGX + Lambert's as much or more, sharp lobes not at all and gray-plastic 0.8 % worse:
      the paper's form stays the default (``campaigns/RESULTS.md``, check of 2026-12-06);
    - a conductor with a faint Lambertian floor ``ρ_d/π`` (``conductor_floor``; §3.9), added
      once the fit has chosen the conductor type (the types are compared without it): the
      stand-ins of chrome and tungsten-carbide, rendered black around the highlight by the
      bare conductor, fit 8–12 % better on the fitted metric with it (ρ_d ≈ 0.003–0.006).
    """
    from twoscale.config import ModelConfig

    knee = apparatus and apparatus_knee  # no factor, no knee
    return ModelConfig(
        diffraction=diffraction,
        apparatus=apparatus,
        apparatus_knee=knee,
        diffuse_fresnel=diffuse_fresnel,
        shadowing=shadowing,
        conductor_floor=conductor_floor,
        apparatus_angles=apparatus_angles,
    )


def resolve_configs(config, material) -> list:
    """The model configurations to try (several for ``material='auto'``)."""
    if isinstance(config, CookTorranceConfig):
        if material not in (None, "auto"):
            raise ValueError("material does not apply to the Cook-Torrance baseline")
        return [config]

    if config is None or (isinstance(config, str) and config == "auto"):
        base = merl_protocol()  # see fit(config=...)
        if material is None:
            material = "auto"
    elif isinstance(config, str):
        raise ValueError(
            f"config must be a ModelConfig, a CookTorranceConfig or 'auto', got {config!r}"
        )
    else:
        base = config
    if material is None:
        return [base]
    if material == "auto":
        return [dataclasses.replace(base, material=m) for m in AUTO_MATERIALS]
    if material not in MATERIALS:
        raise ValueError(f"material must be one of {MATERIALS} or 'auto', got {material!r}")
    return [dataclasses.replace(base, material=material)]


#: Schlick's form of a dielectric coat's Fresnel reflectance must lower the diffraction-off fit's
#: RMS by more than this fraction to be chosen over the exact equations (the physical form wins
#: ties; :func:`choose_fresnel`).
FRESNEL_TIE_RTOL = 0.02

#: With the default starts, the full model is fitted with both Fresnel forms (and keeps
#: Schlick's only if that lowers its RMS by more than :data:`FRESNEL_TIE_RTOL`) wherever
#: Schlick's form lowers the diffraction-off special case's RMS by more than this fraction
#: (:func:`schlick_worth_trying`). Why less than the tie: the special case's gain predicts the
#: full model's poorly. On the 14 of the 60 stand-ins whose full model was fitted with both forms
#: (campaign of 2026-12-07) the full model's gain was −0.2× to 3.5× the special case's, median
#: 0.9× (specular-white-phenolic 2.4 % → 8.5 %, fruitwood-241 7.5 % → 1.1 %), and two materials
#: whose special case gained just under 2 % (color-changing-paint1 1.4 %,
#: specular-green-phenolic 2.0 %) fit 13 % and 5 % better with Schlick's form where the full
#: model was fitted with both (their fits with the paper's apparatus factor).
FRESNEL_TRY_RTOL = 0.005


FRESNEL_MODES = ("auto", "exact", "schlick")


def fresnel_choice_applies(config) -> bool:
    """Can ``fresnel="auto"`` choose this configuration's Fresnel form? (A two-scale dielectric
    with the exact form and without the full polarisation factor.)"""
    return (
        not isinstance(config, CookTorranceConfig)
        and config.coat_form_selectable
        and config.fresnel == "exact"
    )


def resolve_fresnel(configs: list, fresnel: str | None, protocol: bool) -> tuple[list, str | None]:
    """Apply ``fit(fresnel=...)`` to the configurations; returns ``(configs, mode)`` with ``mode``
    ``"auto"`` when the fit is to choose the form, else ``None``.

    ``None`` (default): ``"auto"`` under the MERL protocol (``config=None``), else each
    configuration's own form. ``"exact"`` / ``"schlick"``: that form for every dielectric type.
    """
    if fresnel is None:
        fresnel = "auto" if protocol else None
    if fresnel is None:
        return configs, None
    if fresnel not in FRESNEL_MODES:
        raise ValueError(f"fresnel must be one of {FRESNEL_MODES} or None, got {fresnel!r}")
    if any(isinstance(c, CookTorranceConfig) for c in configs):
        if protocol:
            return configs, None
        raise ValueError("fresnel does not apply to the Cook-Torrance baseline")
    if fresnel == "auto":
        return configs, "auto"
    return [c if c.is_conductor else dataclasses.replace(c, fresnel=fresnel) for c in configs], None


def schlick_worth_trying(rms_exact: float, rms_schlick: float) -> bool:
    """Should the full model be fitted with Schlick's form too? Where Schlick's form lowered the
    diffraction-off special case's RMS (the same cells) by more than
    :data:`FRESNEL_TRY_RTOL`, or the exact form gave no finite fit."""
    if not math.isfinite(rms_schlick):
        return False
    return not math.isfinite(rms_exact) or rms_schlick < (1.0 - FRESNEL_TRY_RTOL) * rms_exact


def choose_fresnel(rms_exact: float, rms_schlick: float) -> tuple[str, str]:
    """``("exact" | "schlick", reason)`` from the diffraction-off fits' RMS with each form (on
    the same cells): Schlick's form only when it is lower by more than :data:`FRESNEL_TIE_RTOL`."""
    if not math.isfinite(rms_schlick):
        return "exact", "Schlick's form gave no finite fit"
    if not math.isfinite(rms_exact) or rms_schlick < (1.0 - FRESNEL_TIE_RTOL) * rms_exact:
        return "schlick", (
            f"Schlick's form fits the diffraction-off model better "
            f"(RMS {rms_schlick:.5g} vs {rms_exact:.5g} exact)"
        )
    return "exact", (
        f"the exact form fits as well within {FRESNEL_TIE_RTOL:.0%} or better "
        f"(RMS {rms_exact:.5g} vs {rms_schlick:.5g} Schlick)"
    )


#: Two material types whose best RMS differ by less than this fraction fit equally well; the
#: physically consistent one is chosen (:func:`choose_type`).
TYPE_TIE_RTOL = 0.02


#: A conductor fit whose extinction stays below this in every channel is no metal: every metal of
#: the refractiveindex.info tables in shared/data (Ag, Al, Au, Be, Co, Cr, Cu, Fe, Mo, Ni, Pd,
#: Pt, Ta, Ti, V, W, Zn) has k ≥ 1.68 between 444 and 645 nm (the lowest: gold at 444 nm).
DIELECTRIC_K = 1.5


#: A plastic fit whose diffuse albedo is below this in every channel has no diffuse layer: a metal.
METAL_RHO_D = 0.01


#: A measured diffuse body counts when its Lambertian albedo ``π ρ_floor`` (luminance of the
#: floor level, :func:`~twoscale.fit.starts.floor_level`) is at least this fraction of all the
#: light the material reflects (its measured bihemispherical albedo): twice the faint scatter
#: under a bare metal's highlight, which is at most 5 % on the metal stand-ins (chrome and
#: chrome-steel 0.0 %, tungsten-carbide 1 %, nickel 2 %, hematite 3 %, aluminium 5 %). Until
#: 2026-12-05 this was 0.5, and a body carrying 22-38 % of the light did not count: a mixture of
#: aluminium and light-brown fabric rendered as a black sphere with a highlight (its conductor fit
#: 2.9 % lower in log RMS, reproducing 2 % of the measured floor) and dark-blue-paint as a rough
#: metal darkening towards the rim (its conductor made the body with a flat diffraction lobe,
#: σ_s = 1 µm, b = 0.013 µm). On the 60 stand-ins any value from 0.06 to 0.38 makes the same
#: choices (the conductors' shares: gold-metallic-paint 5.6 %, then dark-blue-paint 38 %).
BODY_SHARE = 0.1


#: The most light the faint scatter under a bare metal's highlight carries (its share of the
#: measured albedo; aluminium's 4.8 % is the most among the metal stand-ins). A bodiless material
#: whose floor carries more, and whose conductor fit leaves that floor out, is not typed by its
#: highlight (:func:`choose_type`): a conductor of a 50/50 mixture of aluminium and alum-bronze
#: (9 % of its light in a warm floor) rendered black with a bluish glow where the measured sphere
#: is warm brown, as the plastic fit (3.3 % lower in RMS) renders it.
FAINT_SHARE = 0.05


#: A conductor fit that reproduces less than this fraction of a counting body leaves it out: the
#: log metric weighs a dim body little against a bright highlight, so such a fit can have the
#: lower RMS and still render as a black object with a highlight. The plastic wins.
MISSING_BODY = 0.5


#: The highest refractive index of the dielectrics a plastic-type material's interface is made
#: of: the resins, binders and fibres of MERL's plastics, paints, phenolics, acrylics, rubbers and
#: fabrics (acrylic 1.49, polyethylene and rubber ≈ 1.51, nylon and PVC ≈ 1.53-1.54,
#: polycarbonate and polystyrene 1.59, PET 1.64, phenolic resins up to ≈ 1.7).
ETA_COAT_MAX = 1.7


#: Where the data shows no diffuse body, its highlight's albedo against what a dielectric
#: interface can reflect (:func:`dielectric_albedo_bound`) decides the type when the two types'
#: RMS are within this fraction; beyond it the lower RMS wins. Likewise a body that the
#: conductor's lobes make as the plastic's layer does gives the plastic unless the conductor's
#: RMS is lower by more than this (:func:`choose_type`).
EVIDENCE_RTOL = 0.1


def _within_evidence(rms, other) -> bool:
    """Is ``rms`` at most :data:`EVIDENCE_RTOL` above ``other`` (no evidence against it)?"""
    return rms <= (1.0 + EVIDENCE_RTOL) * other


def dielectric_albedo_bound(fall_off=None, eta: float = ETA_COAT_MAX, n: int = 2048) -> float:
    """The bihemispherical albedo of a smooth dielectric interface of index ``eta`` seen through
    MERL's apparatus fall-off (``L(θ)²`` at the mirror direction, in either of its forms):
    ``2 ∫ F(θ) L(θ)² cos θ sin θ dθ`` over
    ``[0, π/2]`` (a mirror reflects θ_i into θ_o = θ_i). ``fall_off``: ``(e, m)`` of
    ``L(θ) = [1 − (2θ/π)^m]^e`` (docs/model.md §3.11), or ``None`` for none. A rough interface
    of the same index reflects less (its facets shadow each other), so this bounds every
    dielectric highlight: 0.092 at η = 1.5 and 0.120 at 1.7 without fall-off."""
    theta = (np.arange(n) + 0.5) * (0.5 * math.pi / n)  # midpoint rule
    cos = np.cos(theta)
    f = np.asarray(dielectric(cos, eta), dtype=np.float64)
    if fall_off is not None:
        e, m = fall_off
        f = f * np.asarray(apparatus_factor(cos, float(e), float(m)), dtype=np.float64) ** 2
    return float(np.sum(2.0 * f * cos * np.sin(theta)) * (0.5 * math.pi / n))


def body_share(floor, albedo) -> tuple[float, float, float]:
    """``(body albedo π ρ_floor, measured albedo, body's share of it)`` in luminance, from the
    data's floor level and bihemispherical albedo per channel: what the body rules of
    :func:`choose_type` and :func:`type_from_body` weigh against :data:`BODY_SHARE`."""
    w = np.asarray(LUMINANCE)
    body = math.pi * float(np.asarray(floor) @ w)
    total = float(np.asarray(albedo) @ w)
    return body, total, body / max(total, 1e-300)


def choose_type(best: dict, body: dict | None = None) -> tuple[str, str]:
    """Pick a material type from ``{type: (rms, params)}``; returns ``(type, reason)``.

    ``body``: ``{"measured": (C,), type: (C,), ..., "albedo": (C,), "fall_off": (e, m) | None}``:
    the floor level (:func:`~twoscale.fit.starts.floor_level`) of the data and of each type's
    fit, the data's bihemispherical albedo, and the apparatus fall-off of the plastic fit (none
    when absent).

    A measured diffuse body that is more than the faint scatter under a metal's highlight (its
    albedo ``π ρ_floor`` at least :data:`BODY_SHARE` of the data's albedo) makes the plastic
    win whatever the RMS when the conductor fit leaves it out (its floor below
    :data:`MISSING_BODY` of the measured one and the plastic's closer: it would render black
    with a highlight), and when the plastic fit reproduces it (its floor at least
    :data:`MISSING_BODY` of the measured one), unless the conductor's RMS is lower by more than
    :data:`EVIDENCE_RTOL`: a conductor has no diffuse layer, and its fit of such a material
    makes the body with its lobes (on the 60 stand-ins of 2026-12-04: a wide EPD, β ≈ 0.6, or a
    flat diffraction lobe, σ_s ≈ 1 µm and b ≈ 0.01–0.05 µm, on every material with such a
    body), which renders a rough metal; but where those lobes fit clearly better, the floor is
    a rough metal's tail (the model's own conductor with β = 0.3, p = 0.5 puts 39 % of its
    light there; its plastic fit's RMS was 6.5× its conductor's). On the 60 stand-ins and 24
    held-out mixtures (2026-12-07) every material this rule gives the plastic has a conductor
    RMS at least 2.8 % above the plastic's: the guard changes none of them.
    Where the data has no such body, its highlight carries the light: brighter (albedo less the
    body's) than a smooth dielectric interface of index :data:`ETA_COAT_MAX` reflects through the
    plastic fit's apparatus fall-off (:func:`dielectric_albedo_bound`), it is a metal's and the
    conductor wins (not when a floor beyond :data:`FAINT_SHARE` of the light is one the
    conductor fit leaves out), else the plastic, unless the other type's RMS is lower by more
    than :data:`EVIDENCE_RTOL`. Otherwise the lower RMS wins, unless the two are within
    :data:`TYPE_TIE_RTOL`: then a plastic fit without a diffuse layer (``ρ_d < METAL_RHO_D`` in
    every channel) is a metal in disguise (conductor wins), and otherwise a conductor fit with
    ``k < DIELECTRIC_K`` in every channel is a dielectric in disguise (plastic wins).
    """
    order = sorted(best, key=lambda t: best[t][0])
    winner = order[0]
    if len(order) < 2 or {"conductor", "plastic"} - set(best):
        return winner, "lower RMS"
    rms_c, p_c = best["conductor"]
    rms_p, p_p = best["plastic"]
    if body is not None:
        w = np.asarray(LUMINANCE)
        measured = float(np.asarray(body["measured"]) @ w)
        frac_c = float(np.asarray(body["conductor"]) @ w) / max(measured, 1e-300)
        frac_p = float(np.asarray(body["plastic"]) @ w) / max(measured, 1e-300)
        body_albedo, albedo, share = body_share(body["measured"], body["albedo"])
        if share >= BODY_SHARE:
            if frac_c < MISSING_BODY and abs(math.log(max(frac_p, 1e-300))) < abs(
                math.log(max(frac_c, 1e-300))
            ):
                return "plastic", (
                    f"the conductor fit leaves the measured diffuse body out (its floor is "
                    f"{frac_c:.0%} of the measured one, whose albedo π ρ = {body_albedo:.3g} "
                    f"is {share:.0%} of the measured albedo; plastic: {frac_p:.0%})"
                )
            if frac_p >= MISSING_BODY:
                if not _within_evidence(rms_p, rms_c):
                    # The lobes make the floor and fit clearly better: a rough metal's tail.
                    return "conductor", (
                        f"the measured floor carries {share:.0%} of the light (albedo π ρ = "
                        f"{body_albedo:.3g}), and the conductor's lobes make it ({frac_c:.0%} "
                        f"of the measured one) with an RMS {rms_p / rms_c:.3g}× lower than "
                        f"the plastic's (more than {EVIDENCE_RTOL:.0%}): a rough metal's "
                        "lobe, not a diffuse body"
                    )
                return "plastic", (
                    f"the measured diffuse body carries {share:.0%} of the light (albedo π ρ = "
                    f"{body_albedo:.3g}): a conductor has no diffuse layer, its fit makes the "
                    f"floor ({frac_c:.0%} of the measured one) with its lobes; the plastic's "
                    f"diffuse layer gives {frac_p:.0%}"
                )
        else:
            # No body: the highlight carries (nearly) all the light. Brighter than any dielectric
            # interface reflects through the same fall-off, it is a metal's; else a dielectric's.
            highlight = albedo - body_albedo
            bound = dielectric_albedo_bound(body.get("fall_off"))
            kind = "conductor" if highlight > bound else "plastic"
            other = "plastic" if kind == "conductor" else "conductor"
            # A floor beyond a bare metal's faint scatter that the conductor fit leaves out would
            # render black: then the highlight does not decide (the RMS does, below).
            dark = kind == "conductor" and share > FAINT_SHARE and frac_c < MISSING_BODY
            if not dark and _within_evidence(best[kind][0], best[other][0]):
                side = "more" if kind == "conductor" else "no more"
                return kind, (
                    f"no diffuse body ({share:.0%} of the light); the highlight's albedo "
                    f"{highlight:.3g} is {side} than a dielectric interface reflects "
                    f"(η ≤ {ETA_COAT_MAX}: {bound:.3g}); RMS within {EVIDENCE_RTOL:.0%}"
                )
    if abs(rms_c - rms_p) > TYPE_TIE_RTOL * min(rms_c, rms_p):
        return winner, "lower RMS"
    k = np.asarray(p_c.k)
    rho_d = float(np.max(np.asarray(p_p.rho_d)))
    # A plastic fit without a body in any channel has nothing a conductor lacks: the bare
    # interface of a metal (checked first: such a conductor fit may also have a low k).
    if rho_d < METAL_RHO_D:
        return "conductor", (
            f"RMS within {TYPE_TIE_RTOL:.0%}; the plastic fit has no diffuse layer "
            f"(ρ_d ≤ {rho_d:.3g} in every channel)"
        )
    if np.all(k < DIELECTRIC_K):
        return (
            "plastic",
            f"RMS within {TYPE_TIE_RTOL:.0%}; the conductor fit has k < {DIELECTRIC_K}",
        )
    return winner, f"RMS within {TYPE_TIE_RTOL:.0%}; lower RMS"


def type_from_body(stats) -> tuple[str, str] | None:
    """The material type the data's diffuse body decides without fitting the other type, or
    ``None``: ``("plastic", reason)`` when the measured body (albedo ``π ρ_floor``, luminance)
    carries at least :data:`BODY_SHARE` of the light the material reflects (``stats``: a
    :class:`~twoscale.fit.starts.DataStats` with its albedo).

    :func:`choose_type`'s body rule gives such a material to the plastic unless the plastic fit
    fails to make the body while the conductor's lobes make it, or those lobes fit clearly
    better (a rough metal's tail); ``starts="few"`` (``--preview``) takes the plastic for
    granted and fits it alone. On the 60 stand-ins the default fits chose the plastic for all
    48 with such a body (``campaigns/RESULTS.md``); a rough conductor of the model itself
    (β = 0.3, p = 0.5, 39 % of its light in its tail) is a conductor for the default fits and a
    plastic for the preview (log RMSE 0.0100 against 0.00155, 2026-12-07)."""
    if stats.albedo is None:
        return None
    body, albedo, share = body_share(stats.floor, stats.albedo)
    if not (albedo > 0.0 and share >= BODY_SHARE):
        return None
    return "plastic", (
        f"the measured diffuse body carries {share:.0%} of the light (albedo π ρ = "
        f"{body:.3g}; at least {BODY_SHARE:.0%}): the body rule's type, the conductor not "
        "fitted (starts='few')"
    )


def fall_off_of(params, config) -> tuple[float, float] | None:
    """``(e, m)`` of a fit's apparatus fall-off ``L(θ) = [1 − (2θ/π)^m]^e`` (m = 2 without the
    fitted knee), or ``None`` when its configuration has no apparatus factor."""
    if not config.apparatus:
        return None
    m = params.m if config.apparatus_knee else PAPER_KNEE
    return float(np.max(params.e)), float(np.max(m))


def faint_floor(stats) -> bool:
    """Whether the data's floor carries at most the faint scatter under a bare metal's highlight
    (:data:`FAINT_SHARE` of its measured albedo): where :func:`type_from_highlight` applies."""
    if stats.albedo is None:
        return False
    _body, albedo, share = body_share(stats.floor, stats.albedo)
    return albedo > 0.0 and share <= FAINT_SHARE


def _highlight_against_bound(stats, fall_off) -> tuple[float, float, float]:
    """``(highlight albedo, dielectric bound, body share)``: the data's albedo less its body's,
    against :func:`dielectric_albedo_bound` through ``fall_off``."""
    body, albedo, share = body_share(stats.floor, stats.albedo)
    return albedo - body, dielectric_albedo_bound(fall_off), share


def highlight_suggests_conductor(stats, fall_off) -> bool:
    """Whether a bodiless material's highlight (:func:`faint_floor`) is brighter than a smooth
    dielectric interface reflects through ``fall_off``: :func:`type_from_highlight`'s test of
    the highlight, made on the data before any fit with the fall-off the fits start from.

    The preview uses it to guess which type's full model to compile while the special cases
    fit (the fitted fall-off, not known yet, decides the type): a wrong guess costs only the
    compilation of the other type's model after the decision, what every bodiless preview
    paid before. On the bodiless stand-ins and mixtures measured (2026-12-06) it guessed the
    preview's type on 17 of 18 (blue-metallic-paint2 guessed a conductor, decided a plastic).
    """
    if not faint_floor(stats):
        return False
    highlight, bound, _share = _highlight_against_bound(stats, fall_off)
    return highlight > bound


def type_from_highlight(stats, rms: dict, fall_off) -> tuple[str, str] | None:
    """``("conductor", reason)`` where :func:`choose_type`'s highlight rule gives a material
    without a diffuse body to the conductor by fits of the diffraction-off special case, else
    ``None``: what ``starts="few"`` (``--preview``) decides before fitting the full model of
    one type only.

    It applies where the data's floor carries at most the faint scatter under a bare metal's
    highlight (:data:`FAINT_SHARE` of the measured albedo; there :func:`choose_type` does not
    ask whether the conductor's fit makes the floor): the highlight's albedo (the data's less
    the body's) brighter than a smooth dielectric interface of index :data:`ETA_COAT_MAX`
    reflects through ``fall_off`` (the plastic special case's, :func:`fall_off_of`), and the
    conductor's RMS ``rms["conductor"]`` (type metric) at most :data:`EVIDENCE_RTOL` above the
    plastic's. Only the conductor is decided so: on the bodiless stand-ins measured
    (2026-12-06) the special cases' fall-off started later than the full model's, a larger
    bound (chrome's 0.079 against 0.022, hematite's 0.062 against 0.021), so a highlight above
    it was above the full fit's too, while a dimmer one may still be a metal's (hematite's
    0.043): :func:`preview_type` then falls back on the special cases' RMS.
    """
    if not faint_floor(stats) or {"conductor", "plastic"} - set(rms):
        return None
    highlight, bound, share = _highlight_against_bound(stats, fall_off)
    if highlight <= bound or not _within_evidence(rms["conductor"], rms["plastic"]):
        return None
    return "conductor", (
        f"no diffuse body ({share:.0%} of the light); the highlight's albedo {highlight:.3g} is "
        f"more than a dielectric interface reflects (η ≤ {ETA_COAT_MAX}: {bound:.3g}); the "
        f"diffraction-off fits' RMS within {EVIDENCE_RTOL:.0%} (starts='few': the plastic's "
        "full model not fitted)"
    )


def preview_type(stats, rms: dict, fall_off) -> tuple[str, str] | None:
    """The material type ``starts="few"`` (``--preview``) fits alone for data without a diffuse
    body (its floor at most :data:`FAINT_SHARE` of the light), from the fits of the
    diffraction-off special cases (``rms``: ``{type: RMS}`` on the type metric): the conductor
    where :func:`type_from_highlight` decides it, else the type whose special case fits with
    the lower RMS (the plastic on a tie). ``None`` where the floor carries more (the data's body
    decides those, :func:`type_from_body`), without the data's albedo, or without both types.

    The fallback is a preview's shortcut, not :func:`choose_type`: the full fits' rules may
    choose the other type (measured on the five bodiless stand-ins the highlight leaves open:
    the same type and fit as the full fits on four; hematite, which the campaign accepts as
    either type, a plastic at log RMSE 0.1440 where the full fits choose a conductor at 0.1422).
    """
    if not faint_floor(stats) or {"conductor", "plastic"} - set(rms):
        return None
    decided = type_from_highlight(stats, rms, fall_off)
    if decided is not None:
        return decided
    winner = "plastic" if rms["plastic"] <= rms["conductor"] else "conductor"
    other = "conductor" if winner == "plastic" else "plastic"
    _body, _albedo, share = body_share(stats.floor, stats.albedo)
    return winner, (
        f"no diffuse body ({share:.0%} of the light) and a highlight that does not decide; "
        f"the diffraction-off fits' lower RMS ({rms[winner]:.4g} against the {other}'s "
        f"{rms[other]:.4g}; starts='few': the {other}'s full model not fitted)"
    )


def body_levels(best: dict, groups: dict, prep) -> dict:
    """What :func:`choose_type` weighs a diffuse body with: the floor levels
    (:func:`~twoscale.fit.starts.floor_level`) of the data and of each type's best fit (the model
    on the MERL grid; ``groups``: ``{type: its group}``), the data's bihemispherical albedo, and
    the plastic fit's apparatus fall-off ``(e, m)`` (None without the factor or a plastic fit)."""
    out = {"measured": prep.stats.floor, "albedo": prep.stats.albedo, "fall_off": None}
    if "plastic" in best:
        out["fall_off"] = fall_off_of(best["plastic"][1], groups["plastic"].adapter.config)
    for mat, (_rms, params) in best.items():
        grid = np.asarray(groups[mat].adapter.evaluate_grid(params, "lower"))
        out[mat] = floor_level(grid, prep.valid_grid)
    return out

"""PNG pictures of a fit (matplotlib, Agg backend): slices, lobes, spheres.

- :func:`plot_slices`: measured vs fitted ``ρ(θ_h)`` at a few ``θ_d`` (``φ_d = 90°``), log scale;
- :func:`plot_lobes`: the lobes in the plane of incidence for a few ``θ_i`` (measured dots);
- :func:`plot_spheres`: a sphere under a point light, measured (MERL table lookup, nearest bin)
  and fitted (the model), side by side with the same exposure;
- :func:`plot_gallery_tile`: one small picture (slices and spheres) comparing several models.

Each takes a ``model`` callable ``model(wi, wo) -> (..., 3)`` (NumPy in, NumPy out); build one
with :func:`model_function`.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np

_CHANNEL_COLOURS = ("tab:red", "tab:green", "tab:blue")


def _subplots(*args, **kwargs):
    """A new figure and its axes, outside pyplot's state machine.

    ``matplotlib.figure.Figure`` renders to PNG with the Agg canvas by itself: no backend is
    selected (a notebook's inline backend keeps working) and no figure is left open.
    """
    from matplotlib.figure import Figure

    figsize = kwargs.pop("figsize", None)
    fig = Figure(figsize=figsize)
    return fig, fig.subplots(*args, **kwargs)


#: Margins in inches (left, right, bottom, top) and the space between panels (a fraction of a
#: panel's width) of the fit's pictures with log-scaled panels in a row (slices, lobes) and of
#: the spheres: what ``tight_layout`` computed for them on two materials (2026-12-06), widened a
#: little for longer tick labels (and, for the spheres, a gap between the two titles). Fixed,
#: they save ``tight_layout``'s measuring pass (a draw of every text): 0.45 s of the three
#: pictures' 1.1 s warm, 1.3 s of 4.3 s in a CLI run (its profile).
ROW_OF_LOG_PANELS = (0.85, 0.15, 0.6, 0.7, 0.06)
SPHERES = (0.15, 0.15, 0.15, 0.6, 0.05)


#: Inches a character of a figure title takes on average (matplotlib's default 12-point sans
#: serif; measured on the spheres' titles): a longer title is broken in two (:func:`_wrap_title`).
TITLE_CHAR_WIDTH = 0.09
#: Inches each further line of a title adds to a fixed top margin.
TITLE_LINE_HEIGHT = 0.22


def _wrap_title(title: str, width_in: float) -> str:
    """``title`` on two lines, broken after its first ``": "`` (else at the last space that
    fits), when it is wider than the figure (a mixture's name made the spheres' overflow)."""
    limit = int(width_in / TITLE_CHAR_WIDTH)
    if len(title) <= limit or "\n" in title:
        return title
    cut = title.find(": ")
    if 0 < cut < limit:
        return title[: cut + 1] + "\n" + title[cut + 2 :]
    cut = title.rfind(" ", 0, limit)
    return title if cut <= 0 else title[:cut] + "\n" + title[cut + 1 :]


def _save(fig, path, title: str = "", margins=None) -> Path:
    """Title (if any; broken in two when wider than the figure), the layout (``margins``:
    ``(left, right, bottom, top)`` in inches and the space between panels, else
    ``tight_layout``), write the PNG at 100 dpi."""
    w, h = fig.get_size_inches()
    title = _wrap_title(title, w) if title else title
    if title:
        fig.suptitle(title)
    if margins is None:
        fig.tight_layout()
    else:
        left, right, bottom, top, wspace = margins
        top += TITLE_LINE_HEIGHT * title.count("\n")
        fig.subplots_adjust(
            left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h, wspace=wspace
        )
    fig.savefig(path, dpi=100)
    return Path(path)


def model_function(adapter, params, *, lobes: bool = False):
    """``f(wi, wo) -> ndarray (..., C)`` evaluating a fitted model (NumPy in and out).

    Evaluation goes through :func:`twoscale.fit.evaluation.evaluate_at` (one compiled function per
    model configuration, shared with the fit). With ``lobes=True`` (two-scale model only) the
    function returns ``{lobe: (..., C)}``.
    """
    from twoscale.fit.adapters import LOBES, lobes_of
    from twoscale.fit.evaluation import evaluate_at

    n_ch = adapter.config.n_channels

    def call(wi, wo):
        wi = np.asarray(wi, dtype=np.float64)
        shape = wi.shape[:-1]
        if lobes:
            vals = evaluate_at(adapter.evaluate_lobes, params, wi, wo, len(LOBES) * n_ch)
            vals = vals.reshape(shape + (len(LOBES), n_ch))
            return {n: vals[..., LOBES.index(n), :] for n in lobes_of(adapter.config)}
        return evaluate_at(adapter.evaluate, params, wi, wo, n_ch).reshape(shape + (n_ch,))

    return call


def _dirs(theta_h, theta_d, phi_d):
    """NumPy ``(wi, wo)`` of half/difference angles (``φ_h = 0``; docs/model.md §7.3)."""
    from twoscale.geometry import _dirs_from_half_diff

    return _dirs_from_half_diff(np, *np.broadcast_arrays(theta_h, theta_d, phi_d))


def _half_diff(wi, wo):
    """NumPy ``(θ_h, θ_d, φ_d)`` of direction pairs (docs/model.md §7.3; plotting only).

    ``h = (i+o)/|i+o|``, ``d = R_y(−θ_h) R_z(−φ_h) i``. The JAX version is
    :func:`twoscale.geometry.half_diff_from_dirs`; this one avoids compiling eager JAX ops.
    """
    s = wi + wo
    h = s / np.maximum(np.linalg.norm(s, axis=-1, keepdims=True), 1e-300)
    theta_h = np.arctan2(np.hypot(h[..., 0], h[..., 1]), h[..., 2])
    phi_h = np.arctan2(h[..., 1], h[..., 0])
    c, s_ = np.cos(phi_h), np.sin(phi_h)
    vx = c * wi[..., 0] + s_ * wi[..., 1]
    vy = -s_ * wi[..., 0] + c * wi[..., 1]
    ct, st = np.cos(theta_h), np.sin(theta_h)
    dx = ct * vx - st * wi[..., 2]
    dz = st * vx + ct * wi[..., 2]
    return theta_h, np.arctan2(np.hypot(dx, vy), dz), np.arctan2(vy, dx)


def merl_lookup(data, wi, wo):
    """Measured values at arbitrary directions: the MERL bin containing each pair (nearest-bin).

    Returns ``(values (..., 3), valid (...))``; invalid bins and directions below the horizon
    give 0 and ``valid = False``.
    """
    from twoscale import merl

    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    ih, jd, kp = merl.angles_to_bin(*_half_diff(wi, wo))
    vals = np.asarray(data.values)[ih, jd, kp]
    ok = np.asarray(data.valid)[ih, jd, kp] & (wi[..., 2] > 0) & (wo[..., 2] > 0)
    return np.where(ok[..., None], vals, 0.0), ok


def plot_slices(
    data, model, path, *, theta_d_deg=(0, 20, 45, 70, 85), phi_d_deg: int = 90, title=""
):
    """Measured (dots) and fitted (lines) ``ρ`` against ``θ_h`` at fixed ``θ_d``, ``φ_d``; log
    scale.

    The last default slice, θ_d = 85°, is where MERL's grazing fall-off (the apparatus factor,
    docs/model.md §3.11) shapes the mirror peak and where most of a fit's log error lives.
    """
    from twoscale import merl

    fig, axes = _subplots(1, len(theta_d_deg), figsize=(4 * len(theta_d_deg), 3.6), sharey=True)
    axes = np.atleast_1d(axes)
    ih = np.arange(merl.N_THETA_H)
    y_lo, y_hi = math.inf, 0.0
    for ax, td in zip(axes, theta_d_deg, strict=True):
        jd = int(round(td))
        kp = int(round(phi_d_deg))
        th, tdr, pdr = merl.bin_to_angles(ih, np.full_like(ih, jd), np.full_like(ih, kp))
        wi, wo = _dirs(th, tdr, pdr)
        meas = np.asarray(data.values)[ih, jd, kp]
        ok = np.asarray(data.valid)[ih, jd, kp] & (wi[:, 2] > 0) & (wo[:, 2] > 0)
        fine_h = np.linspace(0.0, 89.0 / 90.0, 400) ** 2 * (np.pi / 2)  # the grid's θ_h range
        fwi, fwo = _dirs(fine_h, np.full_like(fine_h, tdr[0]), np.full_like(fine_h, pdr[0]))
        above = (fwi[:, 2] > 0) & (fwo[:, 2] > 0)
        pred = model(fwi, fwo)
        for c, colour in enumerate(_CHANNEL_COLOURS):
            ax.plot(np.degrees(th[ok]), np.maximum(meas[ok, c], 1e-6), ".", ms=3, color=colour)
            ax.plot(
                np.degrees(fine_h[above]), np.maximum(pred[above, c], 1e-6), "-", lw=1, color=colour
            )
        ax.set_yscale("log")
        if ok.any():
            y_lo = min(y_lo, max(float(meas[ok].min()), 1e-6))
            y_hi = max(y_hi, float(meas[ok].max()))
        ax.set_xlabel("θ_h (deg)")
        ax.set_title(f"θ_d = {td}°, φ_d = {phi_d_deg}°")
        ax.grid(True, which="both", alpha=0.2)
    if y_hi > 0:  # the measured range sets the scale (the model may soar at grazing angles)
        axes[0].set_ylim(y_lo / 3, y_hi * 3)
    axes[0].set_ylabel("ρ (1/sr)   dots: measured, lines: fit")
    return _save(fig, path, title, ROW_OF_LOG_PANELS)


def _plane_dirs(theta_i_deg, n=361):
    """Directions in the plane of incidence: ``wi`` at ``θ_i``, ``wo`` at signed angle ``t``.

    ``wo = (−sin t, 0, cos t)``, so ``t = θ_i`` is the mirror direction.
    """
    ti = math.radians(theta_i_deg)
    t = np.radians(np.linspace(-89.5, 89.5, n))
    wi = np.broadcast_to(np.array([math.sin(ti), 0.0, math.cos(ti)]), (n, 3))
    wo = np.stack([-np.sin(t), np.zeros_like(t), np.cos(t)], axis=-1)
    return np.degrees(t), wi, wo


def plot_lobes(model, path, *, data=None, lobe_model=None, theta_i_deg=(0, 30, 60), title=""):
    """The BRDF in the plane of incidence (green channel), total and per lobe, log scale.

    Args:
        model: ``model(wi, wo) -> (..., 3)``.
        lobe_model: optional ``f(wi, wo) -> {lobe: (..., 3)}`` (two-scale model).
        data: optional MERL data, drawn as dots (nearest-bin lookup).
    """
    fig, axes = _subplots(1, len(theta_i_deg), figsize=(4 * len(theta_i_deg), 3.6), sharey=True)
    axes = np.atleast_1d(axes)
    styles = {"specular": "--", "diffraction": ":", "diffuse": "-."}
    for ax, ti in zip(axes, theta_i_deg, strict=True):
        t, wi, wo = _plane_dirs(ti)
        total = model(wi, wo)[:, 1]
        ax.plot(t, np.maximum(total, 1e-6), "-", color="k", lw=1.5, label="fit (total)")
        if lobe_model is not None:
            for name, vals in lobe_model(wi, wo).items():
                ax.plot(
                    t,
                    np.maximum(vals[:, 1], 1e-6),
                    styles.get(name, "-"),
                    lw=1,
                    label=name,
                )
        if data is not None:
            meas, ok = merl_lookup(data, wi, wo)
            ax.plot(
                t[ok], np.maximum(meas[ok, 1], 1e-6), ".", ms=3, color="tab:green", label="measured"
            )
        ax.axvline(ti, color="grey", lw=0.5)
        ax.set_yscale("log")
        ax.set_xlabel("θ_o (deg), mirror direction at +θ_i")
        ax.set_title(f"θ_i = {ti}°")
        ax.grid(True, which="both", alpha=0.2)
    axes[0].set_ylabel("ρ green (1/sr)")
    axes[0].legend(fontsize=7)
    return _save(fig, path, title, ROW_OF_LOG_PANELS)


def sphere_directions(size: int = 160, light_deg: float = 30.0):
    """Per-pixel local ``(wi, wo)`` of an orthographic sphere lit by a distant point light.

    The camera looks along −z; the light lies in the x-z plane at ``light_deg`` from the view
    direction. Returns ``(wi, wo, mask)`` with ``wi, wo`` of shape ``(size, size, 3)`` in each
    pixel's tangent frame (normal = z) and ``mask`` the pixels on the sphere.
    """
    y, x = np.mgrid[1 : -1 : size * 1j, -1 : 1 : size * 1j]
    r2 = x * x + y * y
    mask = r2 < 1.0
    n = np.stack([x, y, np.sqrt(np.clip(1.0 - r2, 0.0, 1.0))], axis=-1)
    view = np.array([0.0, 0.0, 1.0])
    a = math.radians(light_deg)
    light = np.array([math.sin(a), 0.0, math.cos(a)])
    # Tangent frame: t ⊥ n (from the view direction, or x where n ≈ view), b = n × t.
    ref = np.where(np.abs(n[..., 2:3]) < 0.999, view, np.array([1.0, 0.0, 0.0]))
    t = np.cross(ref, n)
    t /= np.linalg.norm(t, axis=-1, keepdims=True)
    b = np.cross(n, t)

    def local(v):
        return np.stack([np.sum(v * t, -1), np.sum(v * b, -1), np.sum(v * n, -1)], axis=-1)

    wi = local(np.broadcast_to(light, n.shape))
    wo = local(np.broadcast_to(view, n.shape))
    return wi, wo, mask


def _tonemap(rgb, scale):
    x = np.clip(rgb * scale, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def render_spheres(data, model, *, size: int = 160, light_deg: float = 30.0):
    """Linear radiance images ``(measured, fitted)``, each ``(size, size, 3)`` (``ρ cos θ_i``)."""
    wi, wo, mask = sphere_directions(size, light_deg)
    lit = mask & (wi[..., 2] > 0) & (wo[..., 2] > 0)
    flat = lit.reshape(-1)
    wi_f, wo_f = wi.reshape(-1, 3)[flat], wo.reshape(-1, 3)[flat]
    cos_i = wi_f[:, 2:3]
    meas, _ = merl_lookup(data, wi_f, wo_f)
    fit = model(wi_f, wo_f)
    out = []
    for vals in (meas, fit):
        img = np.zeros((size * size, 3))
        img[flat] = np.maximum(vals, 0.0) * cos_i
        out.append(img.reshape(size, size, 3))
    return out[0], out[1], mask


def plot_spheres(data, model, path, *, size: int = 160, light_deg: float = 30.0, title=""):
    """Measured (MERL lookup) and fitted spheres side by side, same exposure (99.5th percentile)."""
    meas, fit, mask = render_spheres(data, model, size=size, light_deg=light_deg)
    ref = meas[mask].max(axis=-1)
    level = np.percentile(ref, 99.5) if ref.size else 1.0
    scale = 1.0 / level if level > 0 else 1.0
    fig, axes = _subplots(1, 2, figsize=(7, 3.8))
    for ax, img, name in zip(axes, (meas, fit), ("measured (MERL lookup)", "fit"), strict=True):
        ax.imshow(_tonemap(img, scale), interpolation="nearest")
        ax.set_title(name)
        ax.axis("off")
    return _save(
        fig, path, title or f"point light at {light_deg:g}° from the view direction", SPHERES
    )


def write_fit_pictures(result, data, out_dir, *, adapter=None) -> list[Path]:
    """Write ``slices.png``, ``lobes.png`` and ``spheres.png`` for a :class:`FitResult`."""
    from twoscale.fit.adapters import adapter_for, config_from_dict

    out_dir = Path(out_dir)
    adapter = adapter or adapter_for(config_from_dict(result.config))
    if adapter.name == "two-scale":
        # The total as the sum of the lobes: one compiled evaluation serves every picture
        # (each compiled function costs ≈ 2 s on an empty compilation cache).
        lobe_model = model_function(adapter, result.params, lobes=True)

        def model(wi, wo):
            return sum(lobe_model(wi, wo).values())

    else:
        model, lobe_model = model_function(adapter, result.params), None
    kind = f" ({result.material})" if result.material != result.model else ""
    title = f"{getattr(data, 'name', '') or 'data'}: {result.model}{kind}, log RMSE {result.rmse_log:.3g}"
    return [
        plot_slices(data, model, out_dir / "slices.png", title=title),
        plot_lobes(model, out_dir / "lobes.png", data=data, lobe_model=lobe_model, title=title),
        plot_spheres(data, model, out_dir / "spheres.png", title=title),
    ]


def _param_entries(params) -> dict:
    """``{name: list of floats}`` of a parameter object (``to_dict()``) or a dict; skips ``None``
    and non-numeric entries (``material``)."""
    d = params if isinstance(params, dict) else params.to_dict()
    out = {}
    for name, value in d.items():
        if value is None or isinstance(value, str):
            continue
        out[name] = [float(v) for v in np.atleast_1d(np.asarray(value, dtype=np.float64))]
    return out


def recovery_table(params, truth, std_errors=None) -> list[dict]:
    """Fitted against true parameters, one row per scalar (per channel for η, k, ρ_d, f0).

    Args:
        params, truth: parameter objects with ``to_dict()`` (``TwoScaleParams`` or a baseline's)
            or the dicts themselves; only names present in both are compared.
        std_errors: optional ``{name: float | list | None}`` (``FitResult.std_errors``).
    Returns:
        Rows ``{"name", "true", "fit", "se", "rel", "pull"}``: ``rel = (fit − true)/|true|``
        (``nan`` where ``true = 0``), ``pull = (fit − true)/se`` (``nan`` without a positive
        standard error, e.g. a fixed parameter). Channels are suffixed ``[R]``, ``[G]``, ``[B]``
        when there are three, ``[i]`` otherwise.
    """
    fit_d, true_d = _param_entries(params), _param_entries(truth)
    se_d = {}
    for name, value in (std_errors or {}).items():
        if value is not None:
            se_d[name] = [float(v) for v in np.atleast_1d(np.asarray(value, dtype=np.float64))]
    rows = []
    for name, fit_v in fit_d.items():
        true_v = true_d.get(name)
        if true_v is None:
            continue
        true_v = true_v * len(fit_v) if len(true_v) == 1 else true_v  # one value for all channels
        se_v = se_d.get(name, [math.nan] * len(fit_v))
        se_v = se_v * len(fit_v) if len(se_v) == 1 else se_v
        for i, (f, t, s) in enumerate(zip(fit_v, true_v, se_v, strict=True)):
            suffix = "" if len(fit_v) == 1 else f"[{'RGB'[i]}]" if len(fit_v) == 3 else f"[{i}]"
            rows.append(
                {
                    "name": name + suffix,
                    "true": t,
                    "fit": f,
                    "se": s,
                    "rel": (f - t) / abs(t) if t != 0 else math.nan,
                    "pull": (f - t) / s if s > 0 else math.nan,  # nan > 0 is False
                }
            )
    return rows


def plot_recovery(params, truth, path, *, std_errors=None, title=""):
    """Fitted against true parameters (synthetic data): relative difference and pull per scalar.

    Left: ``(fit − true)/|true|`` in % with ±1 standard error bars; right: the pull
    ``(fit − true)/se`` with the ±2 band. Rows from :func:`recovery_table`; entries without a true
    value ≠ 0 (left) or a standard error (right) are left out of that panel.
    """
    rows = recovery_table(params, truth, std_errors)
    names = [r["name"] for r in rows]
    y = np.arange(len(rows))[::-1]
    rel = np.array([100.0 * r["rel"] for r in rows])
    err = np.array([100.0 * r["se"] / abs(r["true"]) if r["true"] else math.nan for r in rows])
    pull = np.array([r["pull"] for r in rows])
    fig, (ax1, ax2) = _subplots(1, 2, figsize=(9, 0.3 * len(rows) + 1.6), sharey=True, squeeze=True)
    ok = np.isfinite(rel)
    ax1.errorbar(rel[ok], y[ok], xerr=np.where(np.isfinite(err[ok]), err[ok], 0.0), fmt="o", ms=4)
    ax1.axvline(0.0, color="grey", lw=0.8)
    ax1.set_xlabel("(fit − true) / |true|  (%), bars: ±1 standard error")
    ax1.set_yticks(y, names)
    ok = np.isfinite(pull)
    ax2.axvspan(-2.0, 2.0, color="tab:green", alpha=0.12, lw=0)
    ax2.plot(pull[ok], y[ok], "o", ms=4, color="tab:orange")
    ax2.axvline(0.0, color="grey", lw=0.8)
    ax2.set_xlabel("pull (fit − true) / standard error")
    for ax in (ax1, ax2):
        ax.grid(True, axis="x", alpha=0.3)
    return _save(fig, path, title)


def plot_gallery_tile(
    data,
    models: dict,
    path,
    *,
    theta_d_deg=(5, 30, 60, 85),
    phi_d_deg: int = 90,
    sphere_size: int = 96,
    light_deg: float = 30.0,
    title: str = "",
    dpi: int = 65,
):
    """One small picture of a fit for a gallery: ``θ_h`` slices above, spheres below.

    Top row: measured ``ρ(θ_h)`` (dots) and each model (lines: solid for the first, dashed,
    dotted, … for the next) at a few ``θ_d`` (``φ_d = phi_d_deg``), log scale, RGB channels, the
    measured range setting the scale. Bottom row: the measured sphere (MERL lookup) and one sphere
    per model under the same point light and exposure (99.5th percentile of the measured image).

    Args:
        data: a :class:`twoscale.merl.MerlData`.
        models: ``{label: model(wi, wo) -> (..., 3)}`` in drawing order (:func:`model_function`).
        dpi: resolution of the PNG (the default keeps a tile near 40-60 kB).
    """
    from matplotlib.lines import Line2D
    from PIL import Image

    from twoscale import merl

    labels = list(models)
    n_col = max(len(theta_d_deg), 1 + len(labels))
    fig, axes = _subplots(2, n_col, figsize=(2.4 * n_col, 4.8), squeeze=False)
    styles = ("-", "--", ":", "-.")
    ih = np.arange(merl.N_THETA_H)
    kp = int(round(phi_d_deg))
    fine_h = np.linspace(0.0, 89.0 / 90.0, 200) ** 2 * (np.pi / 2)  # the grid's θ_h range
    y_lo, y_hi = math.inf, 0.0
    for ax, td in zip(axes[0], theta_d_deg, strict=False):
        jd = int(round(td))
        th, tdr, pdr = merl.bin_to_angles(ih, np.full_like(ih, jd), np.full_like(ih, kp))
        wi, wo = _dirs(th, tdr, pdr)
        meas = np.asarray(data.values)[ih, jd, kp]
        ok = np.asarray(data.valid)[ih, jd, kp] & (wi[:, 2] > 0) & (wo[:, 2] > 0)
        fwi, fwo = _dirs(fine_h, np.full_like(fine_h, tdr[0]), np.full_like(fine_h, pdr[0]))
        above = (fwi[:, 2] > 0) & (fwo[:, 2] > 0)
        preds = [model(fwi, fwo) for model in models.values()]
        for c, colour in enumerate(_CHANNEL_COLOURS):
            ax.plot(np.degrees(th[ok]), np.maximum(meas[ok, c], 1e-6), ".", ms=2, color=colour)
            for pred, style in zip(preds, styles, strict=False):
                y = np.maximum(pred[above, c], 1e-6)
                ax.plot(np.degrees(fine_h[above]), y, style, lw=1, color=colour)
        if ok.any():
            y_lo = min(y_lo, max(float(meas[ok].min()), 1e-6))
            y_hi = max(y_hi, float(meas[ok].max()))
        ax.set_yscale("log")
        ax.set_title(f"θ_d = {td}°, φ_d = {phi_d_deg}°", fontsize=8)
        ax.set_xlabel("θ_h (deg)", fontsize=8, labelpad=1)
        ax.tick_params(labelsize=7, pad=1)
        ax.grid(True, which="both", alpha=0.2)
    for ax in axes[0, len(theta_d_deg) :]:
        ax.axis("off")
    if y_hi > 0:  # the measured range sets the scale (a model may soar at grazing angles)
        for ax in axes[0, : len(theta_d_deg)]:
            ax.set_ylim(y_lo / 3, y_hi * 3)
    axes[0, 0].set_ylabel("ρ (1/sr)", fontsize=8)
    handles = [Line2D([], [], ls="", marker=".", color="k", label="measured")] + [
        Line2D([], [], ls=style, color="k", lw=1, label=label)
        for label, style in zip(labels, styles, strict=False)
    ]
    axes[0, 0].legend(handles=handles, fontsize=7, loc="upper right")

    # Without a model, a zero one still gives the measured sphere.
    sphere_models = list(models.values()) or [lambda wi, wo: np.zeros(np.shape(wi))]
    renders = [
        render_spheres(data, m, size=sphere_size, light_deg=light_deg) for m in sphere_models
    ]
    meas_img, _, mask = renders[0]
    images = [meas_img] + [fit_img for _, fit_img, _ in renders[: len(labels)]]
    ref = meas_img[mask].max(axis=-1)
    level = np.percentile(ref, 99.5) if ref.size else 1.0
    scale = 1.0 / level if level > 0 else 1.0
    names = ["measured"] + labels
    for ax, img, name in zip(axes[1], images, names, strict=False):
        ax.imshow(_tonemap(img, scale), interpolation="nearest")
        ax.set_title(name, fontsize=9)
    for ax in axes[1]:
        ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    # Opaque RGB (no alpha channel), optimised: about 15 % smaller than matplotlib's RGBA PNG.
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    buf.seek(0)
    with Image.open(buf) as img:
        img.convert("RGB").save(path, format="PNG", optimize=True)
    return Path(path)

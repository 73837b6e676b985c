"""The fit result record: what was fitted, how well, how, and with which software.

``params.json`` is :meth:`FitResult.to_dict` as JSON. Its ``"params"`` entry is the parameters'
own ``to_dict()``, so it loads back with ``TwoScaleParams.from_dict(record["params"])`` (or the
baseline's ``from_dict``); :func:`load_result` rebuilds the whole :class:`FitResult`.

A two-scale fit's ``params.json`` may also hold the **directional-albedo table** of the fitted
material (written by ``python -m twoscale.fit`` unless ``--no-albedo``; :func:`albedo_table_entry`)::

    "albedo_table": {
        "n": 256,                            # rows
        "cos_theta_i": "(i+1)/n",            # row i is at cos θ_i = (i+1)/n, i = 0 … n−1
        "apparatus": false,                  # the material, without MERL's apparatus factor
        "channels": ["R", "G", "B"],         # columns (one per wavelength in µm if spectral)
        "quadrature": {"n_theta": 8, "n_phi": 16},
        "values": [[a_R, a_G, a_B], ...],    # n rows: a(θ_i) = ∫ ρ cos θ_o dω_o
        "lobes_at_normal": {                 # the last row (cos θ_i = 1) split by lobe
            "cos_theta_i": 1.0,
            "specular": [...], "diffraction": [...], "diffuse": [...]   # 0 for a lobe off
        }
    }

Row ``n−1`` is normal incidence, row 0 the most grazing (the convention of
:func:`twoscale.albedo_table`, which renderers use for energy compensation). It is computed in
float64 with ``n_phi = 16`` nodes in φ_h instead of :func:`twoscale.albedo`'s 32: on seven test
materials (β from 0.001 to 0.6, conductors, plastics, strong diffraction) this differs from the
default quadrature by at most 2e-5 and costs half as much. Records without the entry (older ones,
baselines, ``--no-albedo``) load with ``FitResult.albedo_table = None``;
:meth:`FitResult.albedo_values` gives the table as an ``(n, C)`` array. The summary prints the
light per lobe at normal incidence, and says when the diffraction lobe carries less than
:data:`NEGLIGIBLE_LOBE` of it in every channel: ``σ_s ≈ 0``, and ``b`` and ``c`` then shape
nothing the data can see (their standard errors are as large as their ranges).
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import json
import math
import platform
from pathlib import Path
from typing import Any

from twoscale._atomic import write_text_atomic

FORMAT = "twoscale-fit/1"

#: Rows of the directional-albedo table written into ``params.json``.
ALBEDO_ROWS = 256
#: Quadrature of the table (:func:`twoscale.albedo`'s ``n_theta``, ``n_phi``); see the module doc.
ALBEDO_QUADRATURE = (8, 16)

_PACKAGES = ("twoscale", "jax", "jaxlib", "optimistix", "equinox", "lineax", "numpy", "scipy")


def package_versions() -> dict[str, str]:
    """Versions of Python and of the packages a fit depends on."""
    out = {"python": platform.python_version()}
    for name in _PACKAGES:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def _jsonable(x):
    """Plain-Python copy of ``x`` (NumPy/JAX scalars and arrays to floats and lists; NaN to None)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, bool | str) or x is None:
        return x
    if isinstance(x, int):
        return x
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    try:
        import numpy as np

        arr = np.asarray(x)
        if arr.dtype == bool:
            return arr.tolist()
        if arr.dtype.kind in "iu":
            return arr.tolist()
        if arr.dtype.kind == "f":
            return _jsonable(arr.tolist())
    except Exception:  # noqa: BLE001 - anything not array-like is stringified below
        pass
    return str(x)


@dataclasses.dataclass
class FitResult:
    """Outcome of :func:`twoscale.fit.fit`.

    Attributes:
        params: fitted parameters (``TwoScaleParams`` or a baseline's params), physical units.
        model: ``"two-scale"`` or the baseline's name.
        config: the model configuration as a dict (``{"model": ..., "material": ..., ...}``).
        metric: ``"blend"``, ``"log"``, ``"scaled-log"`` or ``"linear"`` (the fitted metric).
        rmse_linear, rmse_log: RMSE of both cosine-weighted metrics over all valid cells and channels.
        per_channel: ``{"rmse_linear": [C], "rmse_log": [C], "rmse_log_scaled": [C]}``.
        rmse_log_scaled: RMSE of the scaled log metric over all valid cells and channels (with
            ``log_scale``, the per-channel scale ``s_c`` of docs/model.md §8, whatever the fitted
            metric); None in records written before it existed.
        rmse_fit: RMSE of the fitted metric on the fitted cells (after any angle cut).
        n_valid, n_fit: number of valid cells, of fitted cells.
        converged: the last stage ended by a convergence test (the solver's own, the
            standard-error test, or an RMS that stopped falling), not at the step limit;
            ``status`` says which.
        steps: solver steps of the last stage; ``stages`` has the per-stage, per-start details.
        wall_time: seconds for the whole fit (compilation included).
        std_errors: standard errors in physical units, ``None`` for fixed parameters
            (``σ² (JᵀJ)⁺`` at the solution, mapped by the bijection's Jacobian).
        covariance: how the errors were obtained (rank, rank deficiency, σ², note).
        settings, versions, data: provenance.
        type_selection: how the material type was chosen (``material="auto"``): each type's RMS
            (``"rms"``) and best parameters on that stage (``"params"``, ``to_dict()`` form: the
            type not chosen can be read back with ``TwoScaleParams.from_dict``), the winner and
            why; with ``"from_data": True`` (``starts="few"``) the type was decided before the
            full models' stages (``"stage"`` 0) and the other type's full model was not fitted:
            by the data's diffuse body (``"rms"`` empty), or for a bodiless material by the
            diffraction-off special cases' highlight (their RMS and parameters).
        fresnel_selection: how a dielectric coat's Fresnel form was chosen (``fresnel="auto"``):
            the diffraction-off fits' RMS with the exact and with Schlick's form, the winner and
            why (None when not chosen).
        rmse_80: ``{"log", "scaled_log", "linear", "n_cells"}``: the same RMSEs on the valid
            cells with ``θ_i, θ_o ≤ 80°`` (None when there is none).
        warnings: one line per problem of an otherwise usable fit (a parameter at a bound, a
            rank-deficient Jacobian, the step limit reached); printed by the CLI.
        albedo_table: the directional-albedo table of the fitted material (the module doc gives
            its layout), or None; :meth:`albedo_values` as an array.
    """

    params: Any
    model: str
    config: dict
    metric: str
    rmse_linear: float
    rmse_log: float
    per_channel: dict
    rmse_fit: float
    n_valid: int
    n_fit: int
    converged: bool
    status: str
    steps: int
    wall_time: float
    std_errors: dict
    covariance: dict
    settings: dict
    versions: dict
    data: dict
    stages: list = dataclasses.field(default_factory=list)
    type_selection: dict | None = None
    fresnel_selection: dict | None = None
    params_dict: dict | None = None
    rmse_80: dict | None = None
    warnings: list = dataclasses.field(default_factory=list)
    albedo_table: dict | None = None
    rmse_log_scaled: float | None = None
    log_scale: list | None = None

    @property
    def material(self) -> str:
        return str(self.config.get("material", self.model))

    @property
    def model_config(self):
        """The fitted model's configuration as an object: a :class:`twoscale.ModelConfig` (the
        two-scale model) or a :class:`~twoscale.baselines.CookTorranceConfig` (a baseline), ready
        for ``twoscale.brdf(result.params, wi, wo, result.model_config)``."""
        from twoscale.fit.adapters import config_from_dict

        return config_from_dict(self.config)

    def evaluate(self, wi, wo):
        """The fitted BRDF (1/sr, without the cosine) at unit directions ``wi``, ``wo``
        (``(..., 3)``, normal = z; broadcast); ``(..., C)``."""
        from twoscale.fit.adapters import adapter_for

        return adapter_for(self.model_config).evaluate(self.params, wi, wo)

    def evaluate_merl(self, convention: str = "lower"):
        """The fitted BRDF on the whole MERL grid, ``(90, 90, 180, C)`` in 1/sr (``convention``:
        ``"lower"`` bin edges, as the fit's cells, or ``"centre"``)."""
        from twoscale.fit.adapters import adapter_for

        return adapter_for(self.model_config).evaluate_grid(self.params, convention)

    def albedo_values(self):
        """The stored directional-albedo table as a float64 ``(n, C)`` array (row ``i`` at
        ``cos θ_i = (i+1)/n``), or None when the record has none."""
        if self.albedo_table is None:
            return None
        import numpy as np

        vals = [[math.nan if v is None else v for v in row] for row in self.albedo_table["values"]]
        return np.asarray(vals, dtype=np.float64)

    def to_dict(self) -> dict:
        params = self.params_dict
        if params is None:
            params = self.params.to_dict()
        return _jsonable(
            {
                "format": FORMAT,
                "model": self.model,
                "config": self.config,
                "params": params,
                "std_errors": self.std_errors,
                "metrics": {
                    "metric": self.metric,
                    "rmse_linear": self.rmse_linear,
                    "rmse_log": self.rmse_log,
                    "rmse_log_scaled": self.rmse_log_scaled,
                    "log_scale": self.log_scale,
                    "per_channel": self.per_channel,
                    "rmse_fit": self.rmse_fit,
                    "n_valid": self.n_valid,
                    "n_fit": self.n_fit,
                    "within_80_deg": self.rmse_80,
                },
                "convergence": {
                    "converged": self.converged,
                    "status": self.status,
                    "steps": self.steps,
                },
                "covariance": self.covariance,
                "wall_time_s": self.wall_time,
                "settings": self.settings,
                "versions": self.versions,
                "data": self.data,
                "stages": self.stages,
                "type_selection": self.type_selection,
                "fresnel_selection": self.fresnel_selection,
                "warnings": list(self.warnings),
            }
            | ({} if self.albedo_table is None else {"albedo_table": self.albedo_table})
        )

    def to_json(self, indent: int = 2) -> str:
        return json.dumps(self.to_dict(), indent=indent, allow_nan=False)

    def save(self, path) -> Path:
        """Write ``params.json`` atomically (temporary file in the same folder, then ``os.replace``)."""
        return write_text_atomic(path, self.to_json() + "\n")

    def summary(self) -> str:
        """A few human-readable lines: model, errors, convergence, parameters ± errors."""
        lines = [
            f"model {self.model} ({self.material}), metric {self.metric}, "
            f"{self.n_fit} of {self.n_valid} valid cells fitted",
            f"RMSE (all valid cells): log {self.rmse_log:.4g}, "
            + (
                f"scaled log {self.rmse_log_scaled:.4g}, "
                if self.rmse_log_scaled is not None
                else ""
            )
            + f"linear {self.rmse_linear:.4g}"
            + (
                f"; θ_i, θ_o ≤ 80°: log {self.rmse_80['log']:.4g}, "
                f"linear {self.rmse_80['linear']:.4g}"
                if self.rmse_80
                else ""
            ),
            f"{'converged' if self.converged else 'NOT converged'} ({self.status or 'ok'}), "
            f"{self.steps} steps, {self.wall_time:.1f} s",
        ]
        ts = self.type_selection
        if ts and ts.get("from_data"):
            lines.append(f"type {ts['chosen']}: {ts['reason']}")
        elif ts and len(ts.get("rms", {})) > 1:
            others = ", ".join(f"{m} {r:.4g}" for m, r in ts["rms"].items() if m != ts["chosen"])
            kept = " (its parameters: type_selection in params.json)" if "params" in ts else ""
            lines.append(
                f"type {ts['chosen']}: {ts['metric']} RMS {ts['rms'][ts['chosen']]:.4g} against "
                f"{others} on stage {ts['stage']}, {ts['reason']}{kept}"
            )
        params = self.params_dict if self.params_dict is not None else self.params.to_dict()
        for name, value in params.items():
            if value is None:
                continue
            se = self.std_errors.get(name)
            lines.append(f"  {name:8s} = {_fmt(value)}" + (f"  ± {_fmt(se)}" if se else ""))
        lines += _lobe_lines(self.albedo_table, self.model_config)
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def _lobe_lines(albedo_table, config) -> list[str]:
    """The summary's lines on the light each lobe carries at normal incidence (from the albedo
    table's ``"lobes_at_normal"``, when it has one; the lobes ``config`` switches on), and a
    note when the diffraction lobe is too faint to matter: ``σ_s ≈ 0`` then leaves its ``b``
    and ``c`` undetermined."""
    import numpy as np

    from twoscale.fit.adapters import lobes_of

    lobes = (albedo_table or {}).get("lobes_at_normal")
    if not lobes:
        return []
    used = {n: [float(x) for x in lobes[n]] for n in lobes_of(config)}
    parts = "; ".join(f"{n} {_fmt(v)}" for n, v in used.items())
    out = [f"  light per lobe at normal incidence (directional albedo per channel): {parts}"]
    total = np.sum([v for v in used.values()], axis=0)
    faint = used.get("diffraction")
    if faint is not None and np.all(np.asarray(faint) <= NEGLIGIBLE_LOBE * total):
        out.append(
            f"  the diffraction lobe carries < {NEGLIGIBLE_LOBE:.1%} of the light in every "
            "channel (σ_s ≈ 0): b and c are not determined by these data (see their errors)"
        )
    return out


def _fmt(v) -> str:
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if v is None:
        return "—"
    if isinstance(v, float | int):
        return f"{v:.4g}"
    return str(v)


def result_from_dict(d: dict) -> FitResult:
    """Rebuild a :class:`FitResult` from :meth:`FitResult.to_dict` output."""
    from twoscale.fit.adapters import adapter_for, config_from_dict

    if d.get("format") != FORMAT:
        raise ValueError(f"not a twoscale fit record (format {d.get('format')!r}, want {FORMAT!r})")
    adapter = adapter_for(config_from_dict(d["config"]))
    params = adapter.params_from_dict(d["params"])
    m = d["metrics"]
    conv = d["convergence"]

    def num(x):
        return float("nan") if x is None else float(x)

    return FitResult(
        params=params,
        model=d["model"],
        config=d["config"],
        metric=m["metric"],
        rmse_linear=num(m["rmse_linear"]),
        rmse_log=num(m["rmse_log"]),
        per_channel=m["per_channel"],
        rmse_log_scaled=None if m.get("rmse_log_scaled") is None else num(m["rmse_log_scaled"]),
        log_scale=m.get("log_scale"),
        rmse_fit=num(m["rmse_fit"]),
        n_valid=int(m["n_valid"]),
        n_fit=int(m["n_fit"]),
        converged=bool(conv["converged"]),
        status=conv["status"],
        steps=int(conv["steps"]),
        wall_time=num(d["wall_time_s"]),
        std_errors=d["std_errors"],
        covariance=d["covariance"],
        settings=d["settings"],
        versions=d["versions"],
        data=d["data"],
        stages=d.get("stages", []),
        type_selection=d.get("type_selection"),
        fresnel_selection=d.get("fresnel_selection"),
        params_dict=d["params"],
        rmse_80=m.get("within_80_deg"),
        warnings=list(d.get("warnings", [])),
        albedo_table=d.get("albedo_table"),
    )


#: A lobe carrying less than this share of the light at normal incidence in every channel is
#: called negligible in the summary (its own parameters then hardly touch the fit).
NEGLIGIBLE_LOBE = 1e-3


def albedo_table_entry(params, config, n: int = ALBEDO_ROWS, evaluate_lobes=None) -> dict:
    """The ``"albedo_table"`` entry of ``params.json`` (layout in the module doc) for two-scale
    parameters and their :class:`~twoscale.ModelConfig`.

    The table is the material's: MERL's apparatus factor is switched off. By default one jitted
    call of :func:`twoscale.albedo` on all ``n`` incidences at once (float64 when
    ``jax_enable_x64`` is on, as in the CLI), ``n_theta, n_phi =`` :data:`ALBEDO_QUADRATURE`.

    ``evaluate_lobes(wi, wo) -> (N, L, C)`` (NumPy directions ``(N, 3)`` in, the lobes of
    :data:`~twoscale.fit.adapters.LOBES` apart out), if given, is the BRDF used at the same
    quadrature nodes instead: the CLI passes the evaluation its pictures already compiled
    (:func:`twoscale.fit.evaluation.material_evaluator`), which saves compiling
    :func:`twoscale.albedo` (≈ 3 s on an empty compilation cache). Same sum, same nodes; the
    entry then also holds ``"lobes_at_normal"``, each lobe's directional albedo at
    ``cos θ_i = 1`` (the table's last row split by lobe), which the summary prints.
    """
    import jax
    import jax.numpy as jnp
    import numpy as np

    from twoscale import model

    cfg = dataclasses.replace(config, apparatus=False)
    p = params.for_config(cfg)
    dtype = jnp.result_type(float)  # float64 under jax_enable_x64
    cos_i = jnp.asarray((np.arange(n) + 1.0) / n, dtype)
    per_lobe = None
    if evaluate_lobes is None:
        values = np.asarray(model.albedo(p, cos_i, cfg, *ALBEDO_QUADRATURE), np.float64)
    else:
        from twoscale.fit.adapters import LOBES

        nodes = jax.jit(model.albedo_nodes, static_argnums=(1, 2))
        wi, wo, jac = (np.asarray(a) for a in nodes(cos_i[:, None], *ALBEDO_QUADRATURE))
        wi = np.broadcast_to(wi, wo.shape)
        rho = np.asarray(evaluate_lobes(wi.reshape(-1, 3), wo.reshape(-1, 3)), np.float64)
        rho = rho.reshape(*jac.shape, len(LOBES), -1)
        lobe_values = np.sum(rho * jac[..., None, None], axis=(-4, -3))  # (n, L, C)
        values = lobe_values.sum(axis=-2)
        per_lobe = {"cos_theta_i": 1.0} | dict(zip(LOBES, lobe_values[-1], strict=True))
    if not cfg.is_spectral or cfg.spectral_output == "rgb":
        channels = ["R", "G", "B"]
    else:
        channels = [f"{w:g} um" for w in cfg.wavelengths]
    return _jsonable(
        {
            "n": n,
            "cos_theta_i": "(i+1)/n",
            "apparatus": False,
            "channels": channels,
            "quadrature": dict(zip(("n_theta", "n_phi"), ALBEDO_QUADRATURE, strict=True)),
            "values": values,
        }
        | ({} if per_lobe is None else {"lobes_at_normal": per_lobe})
    )


def load_result(path) -> FitResult:
    """Load a ``params.json`` written by the CLI or :meth:`FitResult.save`."""
    with open(path, encoding="utf-8") as f:
        return result_from_dict(json.load(f))

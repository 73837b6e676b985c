"""Which angles should MERL's grazing fall-off depend on? A check on fitted records.

    python -m campaigns.fall_off_form DATA.binary RECORD.json [RECORD.json ...]
        [--cells 150000] [--seed 0]

The paper multiplies the specular lobe by the apparatus factor ``L(θ_i) L(θ_o)``,
``L(θ) = [1 − (2θ/π)^m]^e`` (docs/model.md §3.11); the MERL protocol uses ``L(θ_d)²``. This
script asks whether the same factor of another angle fits the data better, without refitting a whole model: it holds every parameter of
a fit (a two-scale or GGX/Beckmann + Lambert record written by ``python -m twoscale.fit``) except
``e`` and ``m``, splits the model into its specular lobe (which the factor multiplies) and the
rest, and refits ``(e, m)`` alone, within the models' ranges (e ∈ [0, 5], m ∈ [1, 20]), on the
plain log metric ``log(1 + ρ cos θ_i)`` over a random subsample of valid cells, for each form:

- ``theta_io``: ``L(θ_i) L(θ_o)``, the paper's form;
- ``theta_d``: ``L(θ_d)²`` (the same at the mirror direction, where ``θ_i = θ_o = θ_d``; off it,
  a function of the half angle between the directions only);
- ``none``: no factor.

It prints the log RMSE of each on all the subsample's cells, on those with θ_i or θ_o above 80°
and on the others. The other parameters were fitted with the record's form, so the comparison
favours it; a form that still fits better is worth a model of its own.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys

import numpy as np

#: The forms compared (see the module doc).
FORMS = ("theta_io", "theta_d", "none")

#: The models' ranges of the apparatus exponent and knee (twoscale.params, twoscale.baselines).
E_RANGE = (0.0, 5.0)
M_RANGE = (1.0, 20.0)


def split_lobes(params, config, wi, wo):
    """``(specular, rest)``, each ``(N, C)``, of a fitted model without its apparatus factor."""
    import jax
    import jax.numpy as jnp

    from twoscale.baselines import CookTorranceConfig, CookTorranceParams, cook_torrance
    from twoscale.model import lobes

    bare = dataclasses.replace(config, apparatus=False, apparatus_knee=False)
    wi, wo = jnp.asarray(wi), jnp.asarray(wo)
    if isinstance(config, CookTorranceConfig):
        p = CookTorranceParams(params.alpha, params.f0, params.rho_d)
        total = np.asarray(jax.jit(lambda a, b: cook_torrance(p, a, b, bare))(wi, wo))
        rest = np.broadcast_to(np.asarray(p.rho_d) / math.pi, total.shape)
        return total - rest, rest
    p = params.replace(e=None, m=None).for_config(bare)
    out = jax.jit(lambda a, b: lobes(p, a, b, bare))(wi, wo)
    rest = sum(np.asarray(v) for k, v in out.items() if k != "specular")
    return np.asarray(out["specular"]), np.asarray(rest)


def compare_forms(data, params, config, n_cells: int = 150_000, seed: int = 0) -> dict:
    """``{form: {"e", "m", "rmse_log", "rmse_grazing", "rmse_other"}}`` (see the module doc)."""
    from scipy.optimize import least_squares

    from twoscale.merl import grid_directions
    from twoscale.model import apparatus_weight

    wi, wo = (np.asarray(a).reshape(-1, 3) for a in grid_directions("lower"))
    valid = np.asarray(data.valid).reshape(-1)
    valid = valid & (wi[:, 2] > 0.0) & (wo[:, 2] > 0.0)
    idx = np.flatnonzero(valid)
    rng = np.random.default_rng(seed)
    idx = rng.choice(idx, min(n_cells, idx.size), replace=False)
    wi, wo = wi[idx], wo[idx]
    rho = np.asarray(data.values).reshape(-1, np.asarray(data.values).shape[-1])[idx]
    spec, rest = split_lobes(params, config, wi, wo)
    cos_i = wi[:, 2:3]
    h = wi + wo
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    cos_d = np.clip(np.sum(wi * h, axis=1), 0.0, 1.0)
    cos_80 = math.cos(math.radians(80))
    grazing = (wi[:, 2] < cos_80) | (wo[:, 2] < cos_80)

    def residuals(x, form):
        if form == "none":
            factor = np.ones(len(cos_d))
        else:
            factor = np.asarray(apparatus_weight(wi[:, 2], wo[:, 2], cos_d, *x, form))
        pred = factor[:, None] * spec + rest
        return (np.log1p(pred * cos_i) - np.log1p(rho * cos_i)).ravel()

    e0 = float(np.max(params.e)) if getattr(params, "e", None) is not None else 0.5
    m0 = float(np.max(params.m)) if getattr(params, "m", None) is not None else 2.0
    x0 = [min(max(e0, E_RANGE[0]), E_RANGE[1]), min(max(m0, M_RANGE[0]), M_RANGE[1])]
    out = {}
    for form in FORMS:
        if form == "none":
            x, r = (math.nan, math.nan), residuals((0.0, 2.0), form)
        else:
            bounds = ([E_RANGE[0], M_RANGE[0]], [E_RANGE[1], M_RANGE[1]])
            sol = least_squares(residuals, x0, args=(form,), bounds=bounds)
            x, r = tuple(float(v) for v in sol.x), sol.fun
        r = r.reshape(-1, rho.shape[-1])
        out[form] = {
            "e": x[0],
            "m": x[1],
            "rmse_log": float(np.sqrt(np.mean(r**2))),
            "rmse_grazing": float(np.sqrt(np.mean(r[grazing] ** 2))),
            "rmse_other": float(np.sqrt(np.mean(r[~grazing] ** 2))),
        }
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", help="the MERL .binary file the records were fitted to")
    ap.add_argument("records", nargs="+", help="params.json of fits of that file")
    ap.add_argument("--cells", type=int, default=150_000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    from twoscale import merl
    from twoscale.fit import load_result
    from twoscale.fit.adapters import config_from_dict

    data = merl.read(args.data)
    for path in args.records:
        res = load_result(path)
        table = compare_forms(data, res.params, config_from_dict(res.config), args.cells, args.seed)
        print(f"{data.name}: {res.model} ({res.material}), its fit's log RMSE {res.rmse_log:.4g}")
        for form, row in table.items():
            print(
                f"  {form:9s} e = {row['e']:.3f}, m = {row['m']:.3f}: log RMSE "
                f"{row['rmse_log']:.4f} (θ > 80°: {row['rmse_grazing']:.4f}, "
                f"others: {row['rmse_other']:.4f})"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())

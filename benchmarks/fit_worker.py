"""One benchmark fit in its own process (so its peak RSS can be read): prints one JSON line.

    python -m benchmarks.fit_worker --schedule default|preview|tiny [--repeats N]
        [--material synthetic|<nbrdf name>] [--order 3] [--stride 1] [--wavelengths N]

Runs the fit ``repeats + 1`` times: the first (compile + run) and the median of the warm ones are
reported, with the RMSE of the last and the process's peak resident set size.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import time

import jax


def synthetic_material(config=None):
    """The synthetic conductor of the benchmarks (model data, 1 % noise, realistic mask)."""
    import twoscale
    from twoscale.fit.synthetic import synthetic

    return synthetic(TRUE_PARAMS(), config or twoscale.ModelConfig(), noise=0.01, seed=1)


def TRUE_PARAMS():  # noqa: N802 - a constant that needs the library imported
    import twoscale

    return twoscale.TwoScaleParams.conductor(
        beta=0.1, p=1.5, eta=(0.2, 0.5, 1.4), k=(3.5, 2.5, 1.9), sigma_s=0.01, b=1.5, c=2.2
    )


def nbrdf_material(name: str):
    from campaigns import nbrdf

    return nbrdf.render(nbrdf.load_weights()[name], name)


TINY_SCHEDULE = "tiny"


def schedule_for(name: str):
    from twoscale.fit.schedule import Stage

    if name == TINY_SCHEDULE:
        return [Stage(n_cells=1024, keep=1, max_steps=3)]
    return name


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.fit_worker")
    ap.add_argument("--schedule", default="default")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--material", default="synthetic")
    ap.add_argument("--order", type=int, default=3)
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--wavelengths", type=int, default=0, help="0: RGB")
    ap.add_argument(
        "--config",
        default="conductor",
        choices=("conductor", "auto", "protocol"),
        help="conductor: the reference model, a conductor; auto: the reference model, the type "
        "chosen by the fit; protocol: the MERL protocol as the CLI fits it (type chosen)",
    )
    args = ap.parse_args(argv)
    if args.config == "protocol" and args.wavelengths:
        # The MERL protocol is an RGB configuration chosen by the fit; a spectral one is not
        # part of it, and silently fitting RGB would mislabel the timing.
        ap.error("--wavelengths needs --config conductor or auto (the protocol is RGB)")
    jax.config.update("jax_enable_x64", True)
    import twoscale
    from benchmarks.variants import table_variant

    cfg = twoscale.ModelConfig()
    if args.wavelengths:
        cfg = twoscale.ModelConfig(
            wavelengths=tuple(twoscale.spectral.spectral_wavelengths(args.wavelengths))
        )
    data = synthetic_material() if args.material == "synthetic" else nbrdf_material(args.material)
    material = "conductor" if args.config == "conductor" else "auto"
    if args.config == "protocol":
        cfg = None  # twoscale.fit's default: the MERL protocol (merl_protocol)
    times, result = [], None
    with table_variant(args.order, args.stride):
        for _ in range(args.repeats + 1):
            t0 = time.perf_counter()
            result = twoscale.fit(
                data, config=cfg, material=material, schedule=schedule_for(args.schedule)
            )
            times.append(time.perf_counter() - t0)
    warm = times[1:] or times
    out = {
        "first": times[0],
        "median": statistics.median(warm),
        "compile": max(times[0] - statistics.median(warm), 0.0),
        "runs": times,
        "rmse_log": result.rmse_log,
        "rmse_linear": result.rmse_linear,
        "n_fit": result.n_fit,
        "converged": result.converged,
        "steps": result.steps,
        "material": result.params.material,
        # Linux: kilobytes.
        "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())

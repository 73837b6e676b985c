"""Command line: fit the two-scale model (or a baseline) to a MERL ``.binary`` file.

    python -m twoscale.fit material.binary [--out DIR] [--metric blend|log|scaled-log|linear]
        [--material auto|conductor|plastic|subsurface] [--max-theta DEG] [--preview]
        [--full] [--no-apparatus] [--no-apparatus-knee] [--diffuse-fresnel]
        [--fresnel auto|exact|schlick] [--shadowing correlated|uncorrelated]
        [--apparatus-angles theta_d|theta_io]
        [--no-conductor-floor]
        [--no-compile-cache] [--no-albedo] [--render]
    python -m twoscale.fit --example            # synthetic material, no data needed

MERL protocol (default): the apparatus factor ``L(θ_d)²``, ``L(θ) = [1 − (2θ/π)^m]^e``, on the
specular lobe, with ``e`` and ``m`` fitted (MERL's measured values fall off at grazing angles;
without it the model is forced to fit that fall-off with its shape parameters).
``--no-apparatus-knee`` keeps the paper's ``m = 2``; ``--no-apparatus`` fits the bare model.
The baselines (``--baseline``) follow the same switches. A plastic's body is Lambertian
(``ρ_d/π``, :func:`twoscale.fit.merl_protocol` says why); ``--diffuse-fresnel`` uses the
reference's varnish-transmitted body instead. A dielectric coat's Fresnel reflectance takes the
form that fits the data better, the exact equations or Schlick's form (``--fresnel auto``: first
on the diffraction-off special case, then on the full model; the exact form wins ties;
``params.json`` records the comparisons under ``"fresnel_selection"``); ``--fresnel exact`` or
``schlick`` fixes it. ``--shadowing uncorrelated`` replaces the reference's height-direction
correlated shadowing by ``G1(i) G1(o)`` (for the baselines too): more shadowing at grazing angles,
which rough glossy materials such as MERL's woods fit better (3–9 % lower RMS on the stand-ins
tried; sharp highlights do not change). The apparatus factor is ``L(θ_d)²`` (for the baselines
too): the same as the paper's ``L(θ_i) L(θ_o)`` at the mirror direction, but it leaves the forward
grazing cells of rough lobes undimmed, where the stand-ins keep their values (over the 60
stand-ins the two-scale model's median improvement on GGX + Lambert 31.4 % against 20.7 %, the
rough ones up to 46 % better with both models; ``campaigns/RESULTS.md``);
``--apparatus-angles theta_io`` fits the paper's form. A conductor gets a faint Lambertian floor
``ρ_d/π`` once the fit has chosen that type (measured metals scatter a little light diffusely, which the bare
conductor renders black); ``--no-conductor-floor`` keeps the reference's conductor.

Compiled code is kept in JAX's persistent compilation cache, in ``$TWOSCALE_CACHE_DIR`` or
``$XDG_CACHE_HOME/twoscale/jax`` (default ``~/.cache/twoscale/jax``), so a second run, on any
file, skips most of the compilation; ``--no-compile-cache`` (or ``TWOSCALE_COMPILE_CACHE=0``)
switches it off. XLA compiles with its older CPU loop emitters, about a third faster to compile
at nearly the same speed (:mod:`twoscale._xla` has the measurements), unless ``XLA_FLAGS`` already
sets ``xla_cpu_use_fusion_emitters`` or ``TWOSCALE_FAST_COMPILE=0``; and large constants (the
convolution table) are passed to compiled code as arguments instead of being compiled into it
(``JAX_USE_SIMPLIFIED_JAXPR_CONSTANTS``, set by ``twoscale/__init__.py`` before JAX's import when
the process is this command; ``TWOSCALE_HOIST_CONSTANTS=0`` keeps JAX's default). NumPy's huge-page advice
for large arrays is switched off, whose page faults can stall on Linux (a warm run 38 → 31 s;
:mod:`twoscale._hugepages`), unless ``NUMPY_MADVISE_HUGEPAGE`` is set.

Writes ``DIR/params.json`` (the fit record; loads back with ``twoscale.fit.load_result``) and
``DIR/slices.png``, ``DIR/lobes.png``, ``DIR/spheres.png`` (not with ``--no-plots``); prints a
summary on stdout and a progress line per start on stderr. Everything is written to a temporary
folder first and moved into place at the end, so a failed run leaves no partial output.

A two-scale fit's ``params.json`` also holds the material's **directional-albedo table**
(``"albedo_table"``: 256 rows at ``cos θ_i = (i+1)/256``, one column per channel, MERL's apparatus
factor off; the layout is in :mod:`twoscale.fit.record`), for a renderer's energy compensation,
and the light each lobe carries at normal incidence, which the summary prints (with a note when
the diffraction lobe is too faint for its ``b`` and ``c`` to be determined).
Measured with ``--example --preview`` on 2 CPU cores shared with other jobs: 6.7-7.1 s on a first
run (≈ 1 s of it evaluation, the rest tracing and compiling), 1.4-6.5 s once the compilation cache
holds it; ``--no-albedo`` leaves it out. Baselines have none.

``--render`` also writes ``DIR/render.png``: the fitted material rendered in Mitsuba 3 with the
:mod:`twoscale.mitsuba` plugin (a sphere, orthographic view, one distant light at 30° from the
view, 128×128 pixels, 16 samples per pixel, apparatus factor off) next to the measured sphere
under the same light (:mod:`twoscale.render`); even with ``--no-plots``. It needs Mitsuba 3 and
its LLVM backend (``pip install -e ".[mitsuba]"``, ``apt-get install libllvm19``): without them
the CLI stops before fitting, exit status 2. Measured as above: 11-21 s on a first run
(compiling the plugin's kernels), 3.3-9.7 s with the compilation cache. A render that fails after
the fit leaves the other outputs and prints a ``warning:`` line.

Exit status: 0 success, also for a usable fit with a problem (a parameter at the end of its range,
a rank-deficient Jacobian, the step limit reached, data whose albedo is above 1.5,
``twoscale.fit.evaluation.ALBEDO_IMPLAUSIBLE``, a fitted diffuse floor more than 3× off the
measured one where the body is visible, ``floor_warnings``): one ``warning:`` line each on stderr,
and the same lines in ``params.json`` (``"warnings"``); 2 bad input (unreadable file, not a MERL
file, no valid cell, every valid cell 0, bad option); 3 the fit failed (no start gave a finite fit,
or no start made any progress); 1 unexpected internal error. Errors are one line on stderr, without
a traceback (``TWOSCALE_DEBUG=1`` shows it).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from twoscale._atomic import current_umask
from twoscale._hugepages import avoid_hugepage_stalls
from twoscale._xla import prefer_fast_compile
from twoscale.fit.residuals import DEFAULT_METRIC, METRICS
from twoscale.fit.synthetic import EXAMPLE  # the --example material

EXIT_OK, EXIT_INTERNAL, EXIT_INPUT, EXIT_FIT = 0, 1, 2, 3


class InputError(Exception):
    """Bad input: exit status 2."""


class FitFailed(Exception):
    """The fit failed (no finite fit, no progress): exit status 3."""


def _parser() -> argparse.ArgumentParser:
    from twoscale.config import APPARATUS_ANGLES
    from twoscale.fit.material_type import MERL_APPARATUS_ANGLES

    ap = argparse.ArgumentParser(
        prog="python -m twoscale.fit",
        description="Fit the two-scale microfacet BRDF to a MERL .binary file.",
    )
    ap.add_argument("material", nargs="?", help="MERL .binary file")
    ap.add_argument("--out", help="output folder (default: ./<name>-fit, or ./example-out)")
    ap.add_argument(
        "--metric",
        choices=METRICS,
        default=DEFAULT_METRIC,
        help=f"fitted metric (default {DEFAULT_METRIC}: the scaled and the plain log residuals "
        "of every cell; docs/model.md §8)",
    )
    ap.add_argument(
        "--material",
        dest="material_type",
        choices=("auto", "conductor", "plastic", "subsurface"),
        default="auto",
        help="material type (auto: conductor and plastic, keep the better fit)",
    )
    ap.add_argument("--max-theta", type=float, help="fit only θ_i, θ_o ≤ this angle (degrees)")
    sched = ap.add_mutually_exclusive_group()
    sched.add_argument(
        "--preview",
        action="store_true",
        help="faster: fewer starts (starts='few'), no last refinement; with --material auto a "
        "diffuse body in the data makes the type plastic without fitting the conductor",
    )
    sched.add_argument(
        "--full", action="store_true", help="last refinement on every valid cell (slower)"
    )
    ap.add_argument("--example", action="store_true", help="fit a synthetic material (no data)")
    ap.add_argument("--no-diffraction", action="store_true", help="specular lobe (+ diffuse) only")
    ap.add_argument(
        "--apparatus",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="MERL's grazing fall-off (L(θ_d)², see --apparatus-angles) on the specular lobe, "
        "exponent e fitted "
        "(default: on; --no-apparatus for the bare model)",
    )
    ap.add_argument(
        "--apparatus-knee",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="with --apparatus, also fit the knee exponent m of L(θ) = [1 − (2θ/π)^m]^e "
        "(default: on; --no-apparatus-knee keeps the paper's m = 2)",
    )
    ap.add_argument(
        "--diffuse-fresnel",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="a plastic's body seen through the varnish's Fresnel transmission, as in the "
        "reference (default: off, a Lambertian body: MERL's plastics and fabrics fit better)",
    )
    ap.add_argument(
        "--conductor-floor",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="a conductor's faint Lambertian floor rho_d/pi, added once the fit has chosen the "
        "conductor type (default: on; --no-conductor-floor keeps the reference's conductor)",
    )
    ap.add_argument(
        "--apparatus-angles",
        choices=APPARATUS_ANGLES,
        default=MERL_APPARATUS_ANGLES,
        help="the angles of the apparatus factor: L(θ_d)² (theta_d, default), which leaves the "
        "forward grazing cells of rough lobes undimmed (rough materials fit better, "
        "campaigns/RESULTS.md), or the paper's L(θ_i) L(θ_o) (theta_io); for --baseline too",
    )
    ap.add_argument(
        "--shadowing",
        choices=("correlated", "uncorrelated"),
        default="correlated",
        help="shadowing-masking: the reference's height-direction correlated Smith term "
        "(default) or G1(i) G1(o), which shadows more at grazing angles (rough glossy "
        "materials fit better); for --baseline too",
    )
    ap.add_argument(
        "--fresnel",
        choices=("auto", "exact", "schlick"),
        default="auto",
        help="a dielectric coat's Fresnel form (default: auto, the better fit of the two; the "
        "exact equations win ties)",
    )
    ap.add_argument(
        "--compile-cache",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="keep compiled code between runs (JAX persistent cache; default: on)",
    )
    ap.add_argument(
        "--baseline",
        choices=("ggx", "beckmann"),
        help="fit the Cook-Torrance + Lambert baseline instead of the two-scale model",
    )
    ap.add_argument(
        "--fix",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="hold a parameter fixed, e.g. --fix p=1 or --fix eta=1.5,1.5,1.5 (repeatable; "
        "inside the parameter's valid range; with --material auto, k or rho_d fits only the "
        "type that has it)",
    )
    ap.add_argument("--solver", choices=("lm", "dogleg"), default="lm")
    ap.add_argument("--seed", type=int, default=0, help="seed of the subsampling")
    ap.add_argument(
        "--no-plots",
        action="store_true",
        help="no slices/lobes/spheres pictures (--render still writes render.png)",
    )
    ap.add_argument(
        "--no-albedo",
        action="store_true",
        help="leave the directional-albedo table out of params.json (saves 1.5-7 s)",
    )
    ap.add_argument(
        "--render",
        action="store_true",
        help="also write render.png: the fit rendered in Mitsuba 3 next to the measured sphere "
        "(needs Mitsuba 3 and libLLVM)",
    )
    ap.add_argument("--quiet", action="store_true", help="no progress lines")
    ap.add_argument(
        "--allow-unconverged",
        action="store_true",
        help="kept for old scripts: an unconverged fit is now always written, with a warning",
    )
    return ap


def cache_dir() -> Path:
    """Folder of the persistent compilation cache (see the module doc)."""
    if os.environ.get("TWOSCALE_CACHE_DIR"):
        return Path(os.environ["TWOSCALE_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "twoscale" / "jax"


def enable_compile_cache(log) -> Path | None:
    """Point JAX's persistent compilation cache at :func:`cache_dir` (None if it cannot be used)."""
    import jax

    path = cache_dir()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        log(f"compilation cache off: cannot create {path} ({err.strerror or err})")
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    # Every compiled function, the small ones too: the pictures and the albedo table make dozens
    # of them (≈ 1.5 s of a warm run when they were compiled again each time).
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return path


def _parse_fixed(items) -> dict:
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise InputError(f"--fix expects NAME=VALUE, got {item!r}")
        try:
            vals = [float(v) for v in value.split(",")]
        except ValueError:
            raise InputError(f"--fix {name}: not a number: {value!r}") from None
        if name.strip() in out:
            raise InputError(f"--fix {name.strip()} given twice")
        out[name.strip()] = vals[0] if len(vals) == 1 else vals
    return out


def _example_data():
    """The ``--example`` material: the model itself (with the apparatus factor, as MERL data) +
    1 % noise + a realistic invalid mask."""
    from twoscale.config import ModelConfig
    from twoscale.fit.material_type import MERL_APPARATUS_ANGLES
    from twoscale.fit.synthetic import synthetic
    from twoscale.params import TwoScaleParams

    e = EXAMPLE
    params = TwoScaleParams.conductor(
        e["beta"], e["p"], e["eta"], e["k"], sigma_s=e["sigma_s"], b=e["b"], c=e["c"], e=e["e"]
    )
    config = ModelConfig(
        material="conductor", apparatus=True, apparatus_angles=MERL_APPARATUS_ANGLES
    )
    data = synthetic(params, config, noise=0.01, seed=1, name="example")
    return data, params


def _load(path: str):
    from twoscale import merl

    try:
        data = merl.read(path)
    except FileNotFoundError:
        raise InputError(f"cannot read {path}: no such file") from None
    except IsADirectoryError:
        raise InputError(f"cannot read {path}: it is a folder") from None
    except merl.MerlFormatError as err:
        raise InputError(str(err)) from None
    except OSError as err:
        raise InputError(f"cannot read {path}: {err.strerror or err}") from None
    if not data.valid.any():
        raise InputError(f"{path}: every cell is marked invalid (nothing to fit)")
    return data


def _write_outputs(
    out: Path, result, data, plots: bool, log, render: bool = False, before_params=None
) -> list[str]:
    """Write everything into a temporary sibling folder, then move it into place;
    ``before_params()`` (if given) is called before ``params.json`` is written."""
    from twoscale.fit.record import write_text_atomic

    out = out.resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.tmp-"))
    os.chmod(
        tmp, 0o777 & ~current_umask()
    )  # mkdtemp makes it 0o700; the output is an ordinary folder
    try:
        if plots:
            from twoscale.plots import write_fit_pictures

            t = time.perf_counter()
            write_fit_pictures(result, data, tmp)
            log(f"pictures written ({time.perf_counter() - t:.1f} s)")
        if render:
            _write_render(result, data, tmp / "render.png", log)
        if before_params is not None:
            before_params()
        write_text_atomic(tmp / "params.json", result.to_json() + "\n")
        names = sorted(p.name for p in tmp.iterdir())
        if not out.exists():
            os.replace(tmp, out)  # atomic: the folder appears complete
        else:
            if not out.is_dir():
                raise InputError(f"--out {out} exists and is not a folder")
            # params.json last, so a complete params.json means complete pictures.
            for name in sorted(names, key=lambda n: n == "params.json"):
                os.replace(tmp / name, out / name)
            tmp.rmdir()
        return names
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _check_render(args) -> None:
    """``--render``: fail now, before fitting, if Mitsuba or its LLVM backend cannot load."""
    if args.baseline:
        raise InputError("--render renders the two-scale model, not a --baseline fit")
    from twoscale.render import RenderUnavailable, check_available

    try:
        check_available()
    except RenderUnavailable as err:
        raise InputError(str(err)) from None


def _albedo(result, log) -> None:
    """Put the directional-albedo table into ``result`` (a warning instead if it fails)."""
    from twoscale.config import ModelConfig
    from twoscale.fit.adapters import adapter_for
    from twoscale.fit.evaluation import material_evaluator
    from twoscale.fit.record import albedo_table_entry

    config = result.model_config
    if not isinstance(config, ModelConfig):
        return  # a baseline
    t = time.perf_counter()
    try:
        # Through the lobe evaluation the pictures use (compiled by the fit while its last
        # stage ran): no compiled function of its own.
        evaluate = material_evaluator(adapter_for(config), result.params)
        result.albedo_table = albedo_table_entry(result.params, config, evaluate_lobes=evaluate)
    except Exception as err:  # noqa: BLE001 - the fit is kept; the table is an extra
        if os.environ.get("TWOSCALE_DEBUG"):
            raise
        result.warnings.append(f"albedo table not computed: {type(err).__name__}: {err}")
        return
    log(f"albedo table computed ({time.perf_counter() - t:.1f} s)")


def _write_render(result, data, path: Path, log) -> None:
    """``render.png`` (a warning line instead if the render fails: the fit is kept)."""
    from twoscale.render import write_render

    t = time.perf_counter()
    try:
        info = write_render(result, data, path)
    except Exception as err:  # noqa: BLE001 - the fit and its other outputs are kept
        if os.environ.get("TWOSCALE_DEBUG"):
            raise
        print(f"warning: render.png not written: {type(err).__name__}: {err}", file=sys.stderr)
        return
    log(
        f"render written ({time.perf_counter() - t:.1f} s; Mitsuba {info['variant']}, "
        f"{info['size']}x{info['size']}, {info['spp']} spp: {info['seconds']:.1f} s)"
    )


def _run(args, log) -> int:
    if args.example == bool(args.material):
        raise InputError("give a MERL .binary file, or --example (not both)")
    if args.max_theta is not None and not 0 < args.max_theta <= 90:
        raise InputError(f"--max-theta must be in (0, 90] degrees, got {args.max_theta}")
    fixed = _parse_fixed(args.fix)

    import jax

    jax.config.update("jax_enable_x64", True)
    if args.compile_cache and os.environ.get("TWOSCALE_COMPILE_CACHE", "1") != "0":
        where = enable_compile_cache(log)
        if where is not None:
            log(f"compilation cache: {where}")
    if args.render:
        _check_render(args)
    from twoscale.baselines import CookTorranceConfig
    from twoscale.fit.driver import FitError, fit
    from twoscale.fit.material_type import merl_protocol

    t0 = time.perf_counter()
    truth = None
    if args.example:
        log("making the synthetic example material (two-scale conductor, 1 % noise)")
        data, truth = _example_data()
        out = Path(args.out or "example-out")
    else:
        data = _load(args.material)
        out = Path(args.out or f"{data.name}-fit")
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a folder")

    material = None if args.baseline else args.material_type
    if args.baseline:
        config = CookTorranceConfig(
            args.baseline,
            apparatus=args.apparatus,
            apparatus_knee=args.apparatus and args.apparatus_knee,
            shadowing=args.shadowing,
            apparatus_angles=args.apparatus_angles,
        )
    else:
        config = merl_protocol(
            diffraction=not args.no_diffraction,
            apparatus=args.apparatus,
            apparatus_knee=args.apparatus_knee,
            diffuse_fresnel=args.diffuse_fresnel,
            shadowing=args.shadowing,
            apparatus_angles=args.apparatus_angles,
            # The example's truth is a bare conductor: no floor to find.
            conductor_floor=args.conductor_floor and not args.example,
        )
    if args.example and args.material_type == "auto":
        material = "conductor"  # known for the example: keeps it fast
    try:
        result = fit(
            data,
            config=config,
            material=material,
            metric=args.metric,
            max_theta_deg=args.max_theta,
            fixed=fixed,
            schedule="preview" if args.preview else "full" if args.full else "default",
            starts="few" if args.preview else "default",
            solver=args.solver,
            seed=args.seed,
            fresnel=None if args.baseline else args.fresnel,
            progress=log,
        )
    except FitError as err:
        raise FitFailed(str(err)) from None
    except ValueError as err:
        raise InputError(str(err)) from None
    # The albedo table (for params.json) is computed while the pictures are drawn: its
    # compiled quadrature runs without Python's lock, the pictures are mostly Python.
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        job = None if args.no_albedo else pool.submit(_albedo, result, log)
        names = _write_outputs(
            out,
            result,
            data,
            not args.no_plots,
            log,
            args.render,
            before_params=None if job is None else job.result,
        )
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    print(result.summary())
    if truth is not None:
        print("example truth: " + ", ".join(f"{k}={v}" for k, v in truth.to_dict().items()))
    print(f"wrote {', '.join(names)} to {out}/ ({time.perf_counter() - t0:.1f} s in all)")
    return EXIT_OK


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    start = time.perf_counter()
    # Before JAX's first computation: XLA's faster-compiling CPU emitters (twoscale._xla).
    prefer_fast_compile()
    # Before the large host arrays: no huge-page advice, whose page faults may stall
    # (twoscale._hugepages).
    avoid_hugepage_stalls()

    def log(msg: str) -> None:
        if not args.quiet:
            print(f"[{time.perf_counter() - start:6.1f} s] {msg}", file=sys.stderr, flush=True)

    try:
        return _run(args, log)
    except InputError as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_INPUT
    except FitFailed as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_FIT
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # noqa: BLE001 - one line, no traceback, unless debugging
        if os.environ.get("TWOSCALE_DEBUG"):
            raise
        print(f"error: internal error: {type(err).__name__}: {err}", file=sys.stderr)
        return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())

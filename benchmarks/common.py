"""Timing, machine description and Markdown tables shared by the benchmarks."""

from __future__ import annotations

import os
import platform
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import jax

RESULTS = Path(__file__).resolve().parent / "results"


def loadavg() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "n/a"


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def machine() -> dict:
    dev = jax.devices()[0]
    return {
        "cpu": cpu_model(),
        "cores": len(os.sched_getaffinity(0))
        if hasattr(os, "sched_getaffinity")
        else os.cpu_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "device": f"{dev.platform}: {getattr(dev, 'device_kind', dev)}",
        "x64": bool(jax.config.jax_enable_x64),
    }


def block(x):
    return jax.block_until_ready(x)


def timed(fn: Callable, repeats: int = 5) -> dict:
    """First call (compile + run) and the median of ``repeats`` warm calls, in seconds.

    ``compile`` is the first call minus the warm median (tracing + XLA compilation).
    """
    t0 = time.perf_counter()
    out = block(fn())
    first = time.perf_counter() - t0
    runs = []
    for _ in range(max(repeats, 1)):
        t0 = time.perf_counter()
        block(fn())
        runs.append(time.perf_counter() - t0)
    med = statistics.median(runs)
    return {
        "first": first,
        "median": med,
        "compile": max(first - med, 0.0),
        "runs": runs,
        "out": out,
    }


def fmt_time(s: float | None) -> str:
    if s is None:
        return "—"
    if s < 1e-3:
        return f"{s * 1e6:.0f} µs"
    if s < 1.0:
        return f"{s * 1e3:.1f} ms"
    return f"{s:.2f} s"


def fmt(x, digits: int = 3) -> str:
    if x is None:
        return "—"
    if isinstance(x, str):
        return x
    if x == 0:
        return "0"
    return f"{x:.{digits}g}"


def table(headers: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "| " + " | ".join("---" for _ in headers) + " |"]
    for r in rows:
        lines.append("| " + " | ".join(str(c) for c in r) + " |")
    return "\n".join(lines)


def header(title: str, mach: dict, load_start: str, load_end: str, quick: bool, notes=()) -> str:
    # Only the load before the run says whether other work shared the machine: the load at the
    # end includes this run's own work on every core.
    loaded = load_start != "n/a" and float(load_start.split()[0]) > 1.5
    lines = [
        f"# {title}",
        "",
        f"Command: `python -m benchmarks.run{' --quick' if quick else ''}` "
        f"({'quick: reduced sizes, not the reference figures' if quick else 'full run'}).",
        "",
        f"- Machine: {mach['cpu']}, {mach['cores']} cores; Python {mach['python']}; "
        f"JAX {mach['jax']}, backend `{mach['backend']}` ({mach['device']}); x64 {mach['x64']}.",
        f"- Load average (1, 5, 15 min) at start: {load_start}; at end: {load_end} (the end "
        "includes this run's own work)."
        + (" **Taken under load: timings are inflated.**" if loaded else ""),
        f"- Date: {time.strftime('%Y-%m-%d %H:%M:%S %Z')}.",
        "- Each time is the median of repeated warm runs; compile time (first call minus the "
        "warm median) is reported separately.",
    ]
    lines += [f"- {n}" for n in notes]
    return "\n".join(lines) + "\n"


def write(name: str, text: str, out_dir: Path | None = None) -> Path:
    out = Path(out_dir or RESULTS)
    out.mkdir(parents=True, exist_ok=True)
    path = out / name
    path.write_text(text)
    return path


def run_worker(args: list[str], timeout: float = 1800) -> dict:
    """Run ``python -m benchmarks.fit_worker ARGS`` in a fresh process and return its JSON.

    The worker reports its own peak resident set size (``getrusage(RUSAGE_SELF).ru_maxrss`` at
    exit, so XLA's allocations count; tracemalloc would miss them) as ``peak_rss_bytes``.
    """
    import json

    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.fit_worker", *args],
        capture_output=True,
        env=env,
        cwd=root,
        text=True,
        timeout=timeout,
    )
    if proc.returncode:
        raise RuntimeError(f"fit worker failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    line = [x for x in proc.stdout.splitlines() if x.startswith("{")][-1]
    return json.loads(line)

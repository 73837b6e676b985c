"""One run of the fit's CLI in a subprocess, as a user types it (the campaigns' end-to-end
figures: exit status, wall time, and the ``params.json`` it wrote)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

#: The checkout the campaigns belong to: its ``twoscale`` is the one the subprocess runs.
ROOT = Path(__file__).resolve().parents[1]


@dataclass
class CliRun:
    returncode: int
    wall: float  # seconds, process start to exit
    stderr: str
    result: object | None  # the FitResult read back from params.json (None unless exit 0)


def run_cli(path, out, extra=()) -> CliRun:
    """``python -m twoscale.fit PATH --out OUT --quiet *extra`` with this checkout's ``twoscale``
    first on the path; the result is read back from ``OUT/params.json`` when it exits 0."""
    from twoscale.fit import load_result

    args = [sys.executable, "-m", "twoscale.fit", str(path), "--out", str(out), "--quiet"]
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(
            p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p
        ),
    }
    t = time.perf_counter()
    proc = subprocess.run([*args, *extra], capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t
    result = load_result(Path(out) / "params.json") if proc.returncode == 0 else None
    return CliRun(proc.returncode, wall, proc.stderr, result)

"""Rebuild every precomputed table into ``twoscale/data/``: ``python -m tablegen.build_all``.

Each generator is deterministic float64 code; its settings, grids and build time are stored in the
table file. Pass table names to rebuild only those (``python -m tablegen.build_all smith renorm``).
"""

from __future__ import annotations

import importlib
import sys
import time
from pathlib import Path

GENERATORS = {
    "smith": "tablegen.build_smith",
    "renorm": "tablegen.build_renorm",
    "convolution": "tablegen.build_convolution",
    "spectral_presets": "tablegen.build_spectral_presets",
}
OUT_DIR = Path(__file__).resolve().parents[1] / "twoscale" / "data"


def main(argv: list[str]) -> int:
    names = argv or list(GENERATORS)
    unknown = [n for n in names if n not in GENERATORS]
    if unknown:
        print(f"unknown table(s) {unknown}; choose from {list(GENERATORS)}", file=sys.stderr)
        return 2
    for name in names:
        t0 = time.perf_counter()
        path = importlib.import_module(GENERATORS[name]).build(OUT_DIR)
        size = Path(path).stat().st_size
        print(f"{name:18s} -> {path}  ({size / 1e6:.2f} MB, {time.perf_counter() - t0:.1f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

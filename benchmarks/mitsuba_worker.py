"""Mitsuba 3 ``roughconductor`` evaluation timing in its own process (prints one JSON line).

A separate process because Dr.Jit's LLVM backend can abort the interpreter (e.g. an LLVM too old
for the intrinsics it emits: "LLVM ERROR: Cannot select ... fmaximum" with LLVM 15); the
benchmark then skips the Mitsuba rows with that message.

    python -m benchmarks.mitsuba_worker STRIDE REPEATS
"""

from __future__ import annotations

import json
import sys


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    stride, repeats = int(argv[0]), int(argv[1])
    from benchmarks.run import _grid, _mitsuba_eval

    wi, wo = _grid(stride)
    t, note = _mitsuba_eval(wi, wo, repeats)
    if t is None:
        print(json.dumps({"error": note}))
        return 0
    print(json.dumps({"timings": t, "note": note}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

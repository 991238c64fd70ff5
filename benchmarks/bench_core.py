"""The core's speed in one run: reachability (literal vs fitted) and collision (LP vs closed form).

Runs ``bench_reach.py`` and ``bench_collision.py`` one after the other so their ratios are
measured under the same machine load. Usage: ``python benchmarks/bench_core.py [--quick]``
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_collision  # noqa: E402
import bench_reach  # noqa: E402

if __name__ == "__main__":
    bench_reach.main()
    print()
    bench_collision.main()

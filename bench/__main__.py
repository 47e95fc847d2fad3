"""Run every benchmark: ``python -m bench`` (from the repository root)."""

from __future__ import annotations

import importlib
import sys

MODULES = ["bench.bench_io", "bench.bench_rls", "bench.bench_observer", "bench.bench_reep"]


def main() -> None:
    only = sys.argv[1:]
    for name in MODULES:
        if only and not any(o in name for o in only):
            continue
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            print(f"skip {name}: {exc}")
            continue
        print(f"== {name}")
        module.main()
    print("results in bench.json")


if __name__ == "__main__":
    main()

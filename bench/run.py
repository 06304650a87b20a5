"""Run every benchmark in bench/: each ``bench/*_bench.py`` module's ``main()``, in name order.

``python bench/run.py`` (or ``make bench``). Extra arguments are passed to no benchmark; each
uses its own defaults. Exits non-zero if a benchmark raised or returned non-zero.
"""

from __future__ import annotations

import importlib.util
import sys
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _load(path: Path):  # noqa: ANN202 - a module
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    sys.modules[spec.name] = module  # dataclasses and pickling look the module up by name
    spec.loader.exec_module(module)
    return module


def main(argv: list[str] | None = None) -> int:
    """Run each benchmark with its defaults, in turn; return 1 if any failed."""
    failed = []
    for path in sorted(HERE.glob("*_bench.py")):
        print(f"=== {path.name} ===", flush=True)
        start = time.perf_counter()
        try:
            code = _load(path).main([])
        except Exception:  # noqa: BLE001 - report and go on with the next benchmark
            traceback.print_exc()
            code = 1
        print(f"=== {path.name}: {'ok' if not code else f'exit {code}'} ({time.perf_counter() - start:.1f} s) ===\n",
              flush=True)
        if code:
            failed.append(path.name)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

"""Run every benchmark: ``python benchmarks/run.py [name ...]``.

Each ``benchmarks/bench_*.py`` exposes ``main()`` and prints one line per case:
``BENCH <case> ours_s=<s> ref_s=<s> ratio=<ref/ours> [key=value ...]``.
"""

import importlib.util
import os
import sys
import time
import traceback
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the CLI: small dense solves
HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))


def main(argv=None) -> int:
    only = set(argv if argv is not None else sys.argv[1:])
    failed = []
    for path in sorted(HERE.glob("bench_*.py")):
        name = path.stem[len("bench_"):]
        if only and name not in only and path.stem not in only:
            continue
        spec = importlib.util.spec_from_file_location(path.stem, path)
        mod = importlib.util.module_from_spec(spec)
        t0 = time.perf_counter()
        print(f"# {path.name}", flush=True)
        try:
            spec.loader.exec_module(mod)
            mod.main()
        except Exception:
            traceback.print_exc()
            failed.append(path.name)
        print(f"# {path.name} took {time.perf_counter() - t0:.1f}s", flush=True)
    if failed:
        print(f"# failed: {failed}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

"""Run every benchmark (``make bench``): each ``bench_*.py`` here, then the paper's experiments.

Each writes its JSON and PNG into ``OUT/<name>/``; ``OUT/index.json`` lists what ran, the
exit codes and the wall time. ``--quick`` passes ``--quick`` to the paper's experiments.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    jobs = [(script.stem, [sys.executable, str(script), "--out", str(args.out / script.stem)])
            for script in sorted(HERE.glob("bench_*.py"))]
    jobs.append(("paper_experiments", [sys.executable, "-m", "FevarPlannerLib.cli", "benchmark",
                                       "--out", str(args.out / "paper_experiments")] + (["--quick"] if args.quick else [])))
    index = []
    for name, command in jobs:
        print(f"== {name}", flush=True)
        started = time.perf_counter()
        code = subprocess.call(command)
        index.append({"name": name, "returncode": code, "wall_s": round(time.perf_counter() - started, 1)})
    (args.out / "index.json").write_text(json.dumps(index, indent=1))
    failed = [job["name"] for job in index if job["returncode"] != 0]
    print("failed: " + ", ".join(failed) if failed else "all benchmarks ran")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())

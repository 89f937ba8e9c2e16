"""``der bench NAME [args...]``: run one of the benchmark scripts in the source tree's ``bench/``.

Benchmarks are scripts, not tests: each runs ours and the peers in one process and ends with
one JSON line. They live outside the installed package, so this works from a source checkout.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parent.parent / "bench"


def available() -> list[str]:
    return sorted(p.stem for p in BENCH_DIR.glob("*.py")) if BENCH_DIR.is_dir() else []


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", nargs="?", help="benchmark to run: " + (", ".join(available()) or "(none found)"))
    parser.add_argument("args", nargs=argparse.REMAINDER, help="arguments passed to the script (e.g. --quick)")


def run(args: argparse.Namespace) -> int:
    names = available()
    if not names:
        print(f"der bench: no bench/ directory next to the package ({BENCH_DIR}); run from a source checkout",
              file=sys.stderr)
        return 2
    if args.name is None:
        print("available benchmarks: " + ", ".join(names))
        return 0
    if args.name not in names:
        print(f"der bench: unknown benchmark {args.name!r}; expected one of {', '.join(names)}", file=sys.stderr)
        return 2
    return subprocess.call([sys.executable, str(BENCH_DIR / f"{args.name}.py"), *args.args])

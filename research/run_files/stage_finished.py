"""Copy the small files of finished suite runs into research/run_files (for committing).

    python research/run_files/stage_finished.py runs/t3urban/urban research/run_files/table3/urban

A run directory ``<src>/<method>/seed<k>/`` is finished when its ``summary.json`` says it trained
all its steps without interruption and its ``evaluation.json`` (the final greedy evaluation)
exists; unfinished runs are skipped and listed. The checkpoint and TensorBoard files stay behind.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import yaml

FILES = ("summary.json", "episodes.csv", "evaluation.json", "evaluations.csv", "config.yaml", "command.txt")


def finished(run: Path) -> bool:
    try:
        summary = json.loads((run / "summary.json").read_text())
        total = yaml.safe_load((run / "config.yaml").read_text())["train"]["total_steps"]
    except (OSError, ValueError, KeyError, TypeError):
        return False
    return summary.get("steps") == total and not summary.get("interrupted") and (run / "evaluation.json").exists()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("src", type=Path, help="network folder of a suite's --out, e.g. runs/t3urban/urban")
    parser.add_argument("dst", type=Path, help="where the files go, e.g. research/run_files/table3/urban")
    args = parser.parse_args(argv)
    if not args.src.is_dir():
        parser.error(f"src {args.src} is not a directory")
    staged, pending = [], []
    for run in sorted(p for p in args.src.glob("*/seed*") if p.is_dir()):
        rel = run.relative_to(args.src)
        if not finished(run):
            pending.append(str(rel))
            continue
        out = args.dst / rel
        out.mkdir(parents=True, exist_ok=True)
        for name in FILES:
            if (run / name).exists():
                shutil.copy2(run / name, out / name)
        staged.append(str(rel))
    print(f"staged {len(staged)} finished runs into {args.dst}")
    if pending:
        print(f"not finished ({len(pending)}): {', '.join(pending)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

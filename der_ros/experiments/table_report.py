"""Pieces of the results files (``results/table*.md``) that every table writes the same way."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

__all__ = ["run_details", "total_training_time", "write_markdown"]


def run_details(
    command: str,
    seeds: Sequence[int],
    steps: int | Mapping[str, int],
    wall_s: float,
    info: Mapping[str, str],
    per_seed: Sequence[str],
    seeds_per: str | None = None,
) -> list[str]:
    """The closing sections of a results file: ``## Runs`` and ``## Per seed``.

    ``## Runs`` lists the command, the seeds, the environment steps per run, the suite's wall
    time and ``info`` (versions, machine); ``steps`` is one number, or one per group (e.g.
    network) as ``{group: steps}``; ``seeds_per`` (e.g. ``"method"``) adds ``(<n> per
    <seeds_per>)`` to the seeds line. ``per_seed`` is the Markdown table, header rows included.
    """
    seeds_line = f"- seeds: {', '.join(str(s) for s in seeds)}"
    if seeds_per:
        seeds_line += f" ({len(seeds)} per {seeds_per})"
    if isinstance(steps, Mapping):
        steps_lines = [f"- environment steps per run ({group}): {n}" for group, n in steps.items()]
    else:
        steps_lines = [f"- environment steps per run: {steps}"]
    return [
        "## Runs",
        "",
        f"- command: `{command}`",
        seeds_line,
        *steps_lines,
        f"- training time: {wall_s / 60:.1f} min (sum of the runs' own wall times; the same on a rerun that skips them)",
        *[f"- {k}: {v}" for k, v in info.items()],
        "",
        "## Per seed",
        "",
        *per_seed,
        "",
    ]


def write_markdown(path: Path, lines: Sequence[str]) -> Path:
    """Write ``lines`` joined by newlines to ``path`` atomically (temp file, then rename); returns ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text("\n".join(lines))
    tmp.replace(path)
    return path


def total_training_time(results: object) -> float:
    """Sum of ``summary["wall_time_s"]`` over every run result in nested dicts/lists of RunResults.

    Unlike the suite's elapsed time, this survives a rerun that only rebuilds the report.
    """
    if isinstance(results, Mapping):
        return sum(total_training_time(v) for v in results.values())
    if isinstance(results, (list, tuple)):
        return sum(total_training_time(v) for v in results)
    summary = getattr(results, "summary", None)
    return float(summary.get("wall_time_s", 0.0)) if isinstance(summary, Mapping) else 0.0

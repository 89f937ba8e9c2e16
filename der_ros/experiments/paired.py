"""Episode-by-episode comparison of learned runs with a scripted baseline on the same traffic.

Why
---
The tables compare a learned method's rates (IQM over training seeds) with a baseline's rates on
the same evaluation episodes. Two rates that differ by a few episodes in a thousand say nothing about
*where* they differ: whether the agent's caused collisions are in traffic the baseline also cannot
handle, or whether the agent gets through where the baseline waits into the time limit. Every
training seed is evaluated on the same seeded episodes as the baselines (``train.eval_seed_base``),
so the episodes pair up one to one and those questions have counted answers.

Only episodes that begin a seeded stream pair up: their traffic is identical for both policies. An
unseeded follow-up episode (urban keeps its traffic running for ``eval_episodes_per_seed`` episodes)
starts from whatever the policy's earlier episodes left behind, so it is left out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from der_ros.train.evaluation import EvalResult

__all__ = ["PairedCounts", "paired_counts"]


@dataclass(frozen=True)
class PairedCounts:
    """Counts over every (run, episode) pair of learned runs against one baseline."""

    runs: int  #: learned runs compared
    pairs: int  #: episode pairs on identical traffic, over all runs
    only_method: int  #: pairs in which the learned policy succeeds and the baseline does not
    only_baseline: int  #: pairs in which the baseline succeeds and the learned policy does not
    method_caused: int  #: collisions the learned policy caused, over the pairs
    method_caused_situations: int  #: distinct evaluation episodes (seeds) among those collisions
    method_caused_baseline_succeeds: int  #: those of the caused collisions where the baseline succeeds
    baseline_caused: int  #: collisions the baseline caused, over the same pairs (counted again for every run)


def _caused(outcome: str, caused: bool) -> bool:
    return outcome == "collision" and caused


def paired_counts(runs: Sequence[EvalResult], baseline: EvalResult) -> PairedCounts | None:
    """Pair each run's seeded evaluation episodes with the baseline's episode of the same seed.

    None if no episode pairs up (e.g. the runs were evaluated on other seeds than the baseline).
    """
    base = {e.seed: e for e in baseline.episodes if e.seed is not None}
    pairs = only_m = only_b = m_caused = m_caused_b_ok = b_caused = 0
    situations: set[int] = set()
    for run in runs:
        for e in run.episodes:
            if e.seed is None or e.seed not in base:
                continue
            b = base[e.seed]
            pairs += 1
            m_ok, b_ok = e.outcome == "success", b.outcome == "success"
            only_m += m_ok and not b_ok
            only_b += b_ok and not m_ok
            b_caused += _caused(b.outcome, b.caused)
            if _caused(e.outcome, e.caused):
                m_caused += 1
                m_caused_b_ok += b_ok
                situations.add(e.seed)
    if not pairs:
        return None
    return PairedCounts(runs=len(runs), pairs=pairs, only_method=only_m, only_baseline=only_b, method_caused=m_caused,
                        method_caused_situations=len(situations), method_caused_baseline_succeeds=m_caused_b_ok,
                        baseline_caused=b_caused)  # fmt: skip

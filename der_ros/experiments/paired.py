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

Counting pairs overstates the evidence: every training seed is evaluated on the same seeds, so one
hard traffic situation can give ten pairs. The unit that is independent is the situation (the
evaluation seed). For each one, the method's success rate over its runs minus the baseline's
success (0 or 1) is a paired difference, and so is the baseline's caused-collision rate minus the
method's (positive where the method causes fewer). A paired permutation test of their mean
(:func:`der_ros.experiments.stats.paired_permutation_p`) says whether the difference in the rates
is more than chance. It weighs each situation by how much the two differ there: a situation the
rule never gets through and the agent always does counts for more than one where one of ten runs
fails.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from der_ros.experiments.stats import paired_permutation_p
from der_ros.train.eval_result import EvalResult

__all__ = ["PairedCounts", "paired_counts"]


@dataclass(frozen=True)
class PairedCounts:
    """Counts over every (run, episode) pair of learned runs against one baseline, and the differences per situation."""

    runs: int  #: learned runs compared
    pairs: int  #: episode pairs on identical traffic, over all runs
    only_method: int  #: pairs in which the learned policy succeeds and the baseline does not
    only_baseline: int  #: pairs in which the baseline succeeds and the learned policy does not
    method_caused: int  #: collisions the learned policy caused, over the pairs
    method_caused_situations: int  #: distinct evaluation episodes (seeds) among those collisions
    method_caused_baseline_succeeds: int  #: those of the caused collisions where the baseline succeeds
    baseline_caused: int  #: collisions the baseline caused, over the same pairs (counted again for every run)
    success_diffs: tuple[float, ...]  #: per situation: the method's success rate over its runs minus the baseline's
    caused_diffs: tuple[float, ...]  #: per situation: the baseline's caused-collision rate minus the method's

    @property
    def situations(self) -> int:
        """Distinct evaluation seeds among the pairs."""
        return len(self.success_diffs)

    @property
    def success_better(self) -> int:
        """Situations where the method's success rate is above the baseline's."""
        return sum(d > 0 for d in self.success_diffs)

    @property
    def success_worse(self) -> int:
        """Situations where it is below."""
        return sum(d < 0 for d in self.success_diffs)

    @property
    def caused_fewer(self) -> int:
        """Situations where the method's caused-collision rate is below the baseline's."""
        return sum(d > 0 for d in self.caused_diffs)

    @property
    def caused_more(self) -> int:
        """Situations where it is above."""
        return sum(d < 0 for d in self.caused_diffs)

    @property
    def success_p(self) -> float:
        """Permutation test over situations that the mean success difference is zero (two-sided)."""
        return paired_permutation_p(self.success_diffs)

    @property
    def caused_p(self) -> float:
        """Permutation test over situations that the mean caused-collision difference is zero."""
        return paired_permutation_p(self.caused_diffs)


def _caused(outcome: str, caused: bool) -> bool:
    return outcome == "collision" and caused


def paired_counts(runs: Sequence[EvalResult], baseline: EvalResult) -> PairedCounts | None:
    """Pair each run's seeded evaluation episodes with the baseline's episode of the same seed.

    None if no episode pairs up (e.g. the runs were evaluated on other seeds than the baseline).
    """
    base = {e.seed: e for e in baseline.episodes if e.seed is not None}
    pairs = only_m = only_b = m_caused_b_ok = b_caused = 0
    # per evaluation seed (traffic situation): [episodes, method successes, method caused collisions]
    by_seed: dict[int, list[int]] = {}
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
            m_caused = _caused(e.outcome, e.caused)
            m_caused_b_ok += m_caused and b_ok
            tally = by_seed.setdefault(e.seed, [0, 0, 0])
            tally[0] += 1
            tally[1] += m_ok
            tally[2] += m_caused
    if not pairs:
        return None
    success_diffs, caused_diffs = [], []
    for seed in sorted(by_seed):
        n, ok, caused = by_seed[seed]
        b = base[seed]
        success_diffs.append(ok / n - (b.outcome == "success"))
        caused_diffs.append(_caused(b.outcome, b.caused) - caused / n)
    return PairedCounts(runs=len(runs), pairs=pairs, only_method=only_m, only_baseline=only_b,
                        method_caused=sum(t[2] for t in by_seed.values()),
                        method_caused_situations=sum(t[2] > 0 for t in by_seed.values()),
                        method_caused_baseline_succeeds=m_caused_b_ok, baseline_caused=b_caused,
                        success_diffs=tuple(success_diffs), caused_diffs=tuple(caused_diffs))  # fmt: skip

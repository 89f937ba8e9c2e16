"""Sample efficiency of the learned methods, from each run's greedy evaluation curve (issue 44, point 5).

The final score says where a method ends, not how fast it got there. Two measures per run, both read
from ``evaluations.csv`` (the greedy evaluations at step 0, every ``eval_interval`` steps, and the final
one at the budget, on more episodes; docs/evaluation.md, "Sample efficiency"):

* **success AUC**: the area under the run's greedy success curve, trapezoid over the evaluation steps,
  divided by the span from the first to the last evaluation step, so it lies in [0, 1] (1: every
  evaluation succeeded in every episode, from step 0 on). NaN with fewer than two evaluations.
* **steps to 90%**: the first evaluation step at which the run's success reaches
  ``REACH_FRACTION`` (90%) of the *best method's final success*: the largest IQM over seeds of the
  final greedy success among the learned methods of the run's group (shielded methods against the best
  shielded one, the others against the best unshielded one, as the comparisons pair them). A run that
  never reaches it is **censored at its budget** (its last evaluation step) and flagged "not reached";
  the IQM over seeds then counts it at the budget, a lower bound, so the count of runs not reached is
  always reported beside it. Undefined (NaN) when the best final success is 0 (every run would "reach"
  it at step 0). It is the first crossing, as the issue words it: a run that falls back after reaching it
  keeps its crossing step (the AUC and the final success show the fall).

Per method the report gives the IQM over seeds with its stratified-bootstrap 95% CI (rliable), and for
every DER lambda the probability of improvement over DQN and over PER, on the final success and on the
AUC, with the verdict that follows from its CI (:func:`der_ros.experiments.aggregate.verdict`), and the
probability that it reaches 90% in fewer steps (a run that never does ranked behind every run that does).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from der_ros.experiments.aggregate import (
    MIN_SEEDS_FOR_VERDICT,
    Interval,
    evaluation_curve,
    iqm,
    iqm_interval,
    probability_of_improvement,
    verdict,
)
from der_ros.experiments.suite import SHIELD_SUFFIX

__all__ = [
    "REACH_FRACTION",
    "Reach",
    "success_auc",
    "steps_to_reach",
    "reach_thresholds",
    "der_comparisons",
    "efficiency_section",
]

#: a run "reaches" the best method's final success at this share of it (issue 44: "90% of the best method's final
#: success")
REACH_FRACTION = 0.9
#: success rates are counts over episodes: a rate equal to the threshold up to rounding reaches it
_TOL = 1e-9
#: the comparisons of the verdict: (DER lambda, reference), each within its group (shielded with shielded)
_DER = ("der0.1", "der0.5", "der0.9")
_REFS = ("dqn", "per")


def success_auc(steps: Sequence[float] | np.ndarray, success: Sequence[float] | np.ndarray) -> float:
    """Normalised area under a success curve: trapezoid over ``steps`` / (last step - first step), in [0, 1].

    NaN with fewer than two evaluations (or all at one step): a single point has no area.
    """
    s = np.asarray(steps, dtype=np.float64)
    y = np.asarray(success, dtype=np.float64)
    ok = ~np.isnan(y)
    s, y = s[ok], y[ok]
    if s.size < 2 or s[-1] <= s[0]:
        return math.nan
    return float(np.trapezoid(y, s) / (s[-1] - s[0]))


@dataclass(frozen=True)
class Reach:
    """When a run's success curve first reached a threshold: ``step`` (its budget when it never did, and then
    ``reached`` is False; NaN when undefined)."""

    step: float
    reached: bool


def steps_to_reach(
    steps: Sequence[float] | np.ndarray, success: Sequence[float] | np.ndarray, threshold: float
) -> Reach:
    """The first evaluation step whose success is >= ``threshold`` (up to rounding), or the last step (the
    budget) with ``reached=False`` if none is. Undefined (NaN) for a threshold <= 0 or NaN, or no evaluations."""
    s = np.asarray(steps, dtype=np.float64)
    y = np.asarray(success, dtype=np.float64)
    if s.size == 0 or not threshold > 0:
        return Reach(math.nan, False)
    hit = np.flatnonzero(y >= threshold - _TOL)
    if hit.size:
        return Reach(float(s[hit[0]]), True)
    return Reach(float(s.max()), False)


def _shielded(name: str) -> bool:
    return name.endswith(SHIELD_SUFFIX)


def reach_thresholds(final_success: Mapping[str, Sequence[float]]) -> dict[str, tuple[float, str]]:
    """Per method: (``REACH_FRACTION`` x the best final-success IQM of its group, the best method's name).

    ``final_success``: learned method -> its per-seed final greedy success (NaN for a seed without one).
    The group of a method is whether it runs behind the shield. The threshold is NaN for a group with no
    final success at all.
    """
    best: dict[bool, tuple[float, str]] = {}
    for name, values in final_success.items():
        x = np.asarray(values, dtype=np.float64)
        x = x[~np.isnan(x)]
        if not x.size:
            continue
        value = float(iqm(x))
        group = _shielded(name)
        if group not in best or value > best[group][0]:
            best[group] = (value, name)
    out = {}
    for name in final_success:
        value, which = best.get(_shielded(name), (math.nan, ""))
        out[name] = (REACH_FRACTION * value, which)
    return out


def der_comparisons(names: Sequence[str]) -> list[tuple[str, str]]:
    """(X, Y) pairs of the verdict among ``names``: each DER lambda against DQN and against PER, unshielded
    methods with unshielded ones, then shielded with shielded."""
    present = set(names)
    return [(x + sfx, y + sfx) for sfx in ("", SHIELD_SUFFIX) for x in _DER for y in _REFS
            if x + sfx in present and y + sfx in present]  # fmt: skip


def _json(value: float) -> float | None:
    return None if math.isnan(value) else value


def _interval_json(x: Interval) -> list[float | None]:
    return [_json(v) for v in x.to_list()]


def efficiency_section(
    runs: Mapping[str, Sequence[Any]],
    payload: dict[str, dict[str, Any]],
    labels: Mapping[str, str],
) -> list[str]:
    """The sample-efficiency lines of one network's table, and its JSON keys added to ``payload``.

    ``runs``: learned method -> its RunResults (``spec.run_dir`` holds ``evaluations.csv``; ``spec.seed``);
    ``payload``: the network's JSON entries (method -> fields, ``eval_success`` per seed in the order of
    ``runs``), extended in place with new keys only: per seed ``eval_success_auc``, ``eval_steps_to_90``
    (censored at the budget), ``eval_reached_90``; and ``sample_efficiency`` (the IQMs with their CIs, the
    threshold and whose it is, the count not reached, and for DER methods the probabilities of improvement
    and verdicts against DQN and PER, and the probability of reaching 90% in fewer steps).
    """
    learned = [m for m in runs if m in payload and "seeds" in payload[m] and runs[m]]
    if not learned:
        return []
    thresholds = reach_thresholds({m: payload[m]["eval_success"] for m in learned})
    cis: dict[str, tuple[Interval, Interval]] = {}
    for m in learned:
        curves = [evaluation_curve(Path(r.spec.run_dir)) for r in runs[m]]
        auc = [success_auc(c["step"], c["success"]) for c in curves]
        reach = [steps_to_reach(c["step"], c["success"], thresholds[m][0]) for c in curves]
        auc_ci = iqm_interval(auc)
        steps_ci = iqm_interval([r.step for r in reach])
        cis[m] = (auc_ci, steps_ci)
        defined = [r for r in reach if not math.isnan(r.step)]
        payload[m]["eval_success_auc"] = [_json(a) for a in auc]
        payload[m]["eval_steps_to_90"] = [_json(r.step) for r in reach]
        payload[m]["eval_reached_90"] = [r.reached for r in reach]
        payload[m]["sample_efficiency"] = {
            "success_auc_iqm": _interval_json(auc_ci),
            "steps_to_90_iqm": _interval_json(steps_ci),
            "steps_to_90_threshold": _json(thresholds[m][0]),
            "steps_to_90_best_method": thresholds[m][1] or None,
            "not_reached_90": sum(not r.reached for r in defined),
            "runs_90": len(defined),
        }
    lines = ["", "Sample efficiency, from each run's greedy evaluation curve (`evaluations.csv`; docs/evaluation.md):",
             "*success AUC* = the area under the success curve over training steps divided by the step span (1 = every",
             "episode succeeds from step 0 on); *steps to 90%* = the first evaluation step at which a run's success",
             f"reaches τ = {REACH_FRACTION:g} × the best method's final success IQM (shielded methods against the best",
             "shielded one), a run that never does counted at its budget and listed as not reached. IQM over seeds",
             "[95% stratified-bootstrap CI] (rliable).", "",
             "| Method | Success AUC | Steps to 90% | τ (best method) | Not reached |", "|---|---|---|---|---|"]  # fmt: skip
    for m in learned:
        se = payload[m]["sample_efficiency"]
        tau, best = thresholds[m]
        tau_cell = "n/a" if math.isnan(tau) else f"{tau:.3f} ({labels.get(best, best)})"
        lines.append(f"| {labels.get(m, m)} (n={len(runs[m])}) | {cis[m][0].format(3)} | {cis[m][1].format(0)} "
                     f"| {tau_cell} | {se['not_reached_90']}/{se['runs_90']} |")  # fmt: skip
    pairs = der_comparisons(learned)
    if pairs:
        lines += _verdict_lines(pairs, payload, labels)
    return lines


def _nan(values: Sequence[float | None]) -> list[float]:
    return [math.nan if v is None else float(v) for v in values]


def _ranked_steps(entry: Mapping[str, Any]) -> np.ndarray:
    """Per seed, the steps to 90% for ranking: +inf where not reached (behind a run that reached it at the budget,
    which the censored value would tie), NaN where undefined."""
    steps = np.asarray(_nan(entry["eval_steps_to_90"]), dtype=np.float64)
    return np.where(np.asarray(entry["eval_reached_90"], dtype=bool) | np.isnan(steps), steps, np.inf)


#: measure name in the text -> per-seed key of the payload
_MEASURES = {"final success": "eval_success", "success AUC": "eval_success_auc"}


def _verdict_lines(pairs: list[tuple[str, str]], payload: dict[str, dict[str, Any]],
                   labels: Mapping[str, str]) -> list[str]:  # fmt: skip
    """The probability-of-improvement table (final success, AUC, and fewer steps to 90%), and the verdict on DER
    (final success and AUC)."""
    lines = ["", "Probability of improvement over training seeds [95% CI] (rliable), shielded methods against shielded",
             "ones; on the steps to 90%, P(X reaches it in fewer steps than Y) (a run not reaching it ranks behind",
             "every run that does; ties count one half):", "",
             "| X vs Y | P(X > Y) on final success | P(X > Y) on success AUC | P(X < Y) on steps to 90% |",
             "|---|---|---|---|"]  # fmt: skip
    counts = {what: {"better": 0, "worse": 0, "indistinguishable": 0, None: 0} for what in _MEASURES}
    bullets = []
    for x, y in pairs:
        n = min(len(payload[x]["seeds"]), len(payload[y]["seeds"]))
        parts, cells = [], []
        entry = payload[x]["sample_efficiency"].setdefault("vs", {}).setdefault(y, {})
        for what, key in _MEASURES.items():
            poi = probability_of_improvement(_nan(payload[x][key]), _nan(payload[y][key]))
            word = verdict(poi, n)
            counts[what][word] += 1
            cells.append(poi.format(2))
            entry[f"poi_{key}"] = _interval_json(poi)
            entry[f"verdict_{key}"] = word
            parts.append(f"{word or 'no verdict'} on {what} (P = {poi.format(2)})")
        # fewer steps is better: P(X < Y) = P(-X > -Y); a run that never reached τ ranks behind every run that did
        faster = probability_of_improvement(-_ranked_steps(payload[x]), -_ranked_steps(payload[y]))
        entry["poi_fewer_eval_steps_to_90"] = _interval_json(faster)
        lines.append(f"| {labels.get(x, x)} vs {labels.get(y, y)} | {cells[0]} | {cells[1]} | {faster.format(2)} |")
        bullets.append(f"{labels.get(x, x)} against {labels.get(y, y)}: {'; '.join(parts)}.")
    summary = []
    for what, c in counts.items():
        text = (f"on {what}, better in {c['better']} of {len(pairs)} comparisons, worse in {c['worse']}, "
                f"indistinguishable in {c['indistinguishable']}")  # fmt: skip
        if c[None]:
            text += f", no verdict in {c[None]} (fewer than {MIN_SEEDS_FOR_VERDICT} seeds on a side)"
        summary.append(text)
    lines += ["", "**Verdict on DER** (each λ against DQN and against PER; better if the CI of P(X > Y) lies above 0.5,",
              "worse if below, indistinguishable if it contains 0.5):", ";\n".join(summary) + ".", "",
              *[f"- {b}" for b in bullets]]  # fmt: skip
    return lines

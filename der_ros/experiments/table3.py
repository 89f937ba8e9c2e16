"""``der table3``: Table 3 of the paper (SUMO lane change: ring and urban network), evaluated greedily.

Protocol (paper section 5.1, and the evaluation protocol of docs/evaluation.md):

* DQN, PER and DER (lambda = 0.1 / 0.5 / 0.9) trained for 15,000 environment steps on each
  network; only the replay differs between methods (``config/ring.yaml``, ``config/urban.yaml``).
* **Headline: the greedy policy** (epsilon = 0) at the end of training, on 300 held-out evaluation
  episodes per training seed (seeds never used in training, the same for every method): success,
  caused collision, time limit, mean return. Periodic evaluations (every 1,000 steps) give the
  curves of the figures.
* **Baselines** on the same evaluation episodes: never change, immediate change, random, gap
  acceptance (tuned on tuning seeds) and SUMO's own lane-change model
  (:mod:`der_ros.experiments.baselines`).
* **Aggregates over >= 10 training seeds** (rliable): IQM with stratified-bootstrap 95% CIs, the
  mean with its CI, and the probability of improvement of each DER lambda over DQN and over PER;
  "better" only when the CI of P(X > Y) excludes 0.5.
* **Episode by episode** against the gap rule and SUMO's model: every run's evaluation episodes that
  start from a seeded reset are paired with the baseline's on the same traffic
  (:mod:`der_ros.experiments.paired`): who succeeds where the other fails, in how many distinct
  traffic situations the agent's caused collisions fall, and a paired permutation test over
  situations (each evaluation seed counted once) of the difference in success and in caused
  collisions.
* The paper's own "total reward" stays, labelled as what it is: the mean return over all
  *training* episodes of a run (exploration included).
* **Sample efficiency** from each run's greedy evaluation curve: the IQM of the area under the success
  curve and of the steps to reach 90% of the best method's final success, with the probability of
  improvement of each DER lambda over DQN and PER on final success and on that area, and the verdict on
  DER that follows from the CIs (:mod:`der_ros.experiments.sample_efficiency`).

Writes ``<results>/table3.md``, ``table3.json`` (every per-seed number) and
``table3_<network>_curves.png`` (``--name`` replaces the stem ``table3``, e.g. ``table_exit`` for the exit
suite); run directories go to ``--out/<network>/<method>/seed<k>``
(finished runs are reused, interrupted ones resume), baselines to ``--out/<network>/baselines``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from der_ros.experiments.aggregate import (
    Interval,
    final_evaluation,
    iqm_interval,
    mean_interval,
    probability_of_improvement,
    significance_sentence,
)
from der_ros.experiments.backends.dispatch import add_backend_arguments, backend_from_args, run_specs
from der_ros.experiments.baselines import (
    DEFAULT_PARAMS_FILE,
    SHIELDED_BASELINES,
    BaselineJob,
    baseline_job,
    baseline_names,
    gap_params_tuned,
    rule_params,
    run_baselines,
    shielded_env_config,
)
from der_ros.experiments.paired import PairedCounts, paired_counts
from der_ros.experiments.sample_efficiency import efficiency_section
from der_ros.experiments.stats import average_score, paired_permutation_p
from der_ros.experiments.suite import (
    SHIELD_SUFFIX,
    Method,
    RunResult,
    RunSpec,
    add_suite_arguments,
    environment_info,
    load_result,
    methods_by_name,
    plan_runs,
    report_interrupted,
    shielded_method,
    suite_command,
    suite_overrides,
    suite_seeds,
)
from der_ros.experiments.suite_plots import plot_eval_curves
from der_ros.experiments.table_report import run_details, total_training_time, write_markdown
from der_ros.safety.config import SAFETY_KINDS, SAFETY_MODES
from der_ros.train.config import load_experiment_config
from der_ros.train.eval_result import EvalResult
from der_ros.train.eval_seeds import EVAL_SEED_BASE

__all__ = ["PAPER_TABLE3", "NETWORKS", "BASELINE_LABELS", "add_arguments", "run", "score_run", "write_table3"]

log = logging.getLogger(__name__)

#: Table 3 of the paper: network -> method -> total reward
PAPER_TABLE3: dict[str, dict[str, float]] = {
    "ring": {"dqn": 135.74, "der0.1": 117.46, "der0.5": 122.78, "der0.9": 216.91, "per": 135.71},
    "urban": {"dqn": 60.64, "der0.1": 75.84, "der0.5": 70.25, "der0.9": 81.77, "per": 79.50},
}
NETWORKS: dict[str, str] = {"ring": "Ring network", "urban": "Yeongdong Bridge (synthetic stand-in)"}
BASELINE_LABELS: dict[str, str] = {
    "keep": "never change (keep)",
    "immediate": "immediate change",
    "random": "random",
    "gap_acceptance": "gap acceptance (tuned)",
    "sumo": "SUMO's own model (standing request)",
    "mobil": "IDM+MOBIL (exit bias tuned)",
    "sumo_tuned": "SUMO's own model, lane-change parameters tuned",
    "immediate+shield": "immediate change + shield",
    "random+shield": "random + shield",
    "gap_acceptance+shield": "gap acceptance (tuned) + shield",
}
#: the comparisons of the significance section: (X, Y) -> P(X > Y)
COMPARISONS = [(f"der{lam}", ref) for lam in ("0.1", "0.5", "0.9") for ref in ("dqn", "per")]
SCORE_KEYS = ("eval_success", "eval_collision", "eval_time_limit", "eval_return", "eval_episodes", "eval_interventions",
              "eval_time_to_exit", "eval_imposed_brake", "train_total_reward")
#: success at what cost to others (issue 44): mean seconds to success over the successful episodes, and the mean
#: over episodes of the harshest deceleration a new follower showed after the ego's lane changes (m/s²). null in
#: the JSON (and "–" in the table) for evaluations made before these were measured: never 0.
COST_KEYS = ("eval_time_to_exit", "eval_imposed_brake")
#: the results' file stem without --name
DEFAULT_NAME = "table3"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_suite_arguments(parser, default_config="config/ring.yaml", default_out="runs/table3", default_seeds=10)
    parser.description = (parser.description or "") + " (--config is the ring network's training YAML)"
    parser.add_argument("--urban-config", dest="urban_config", default="config/urban.yaml",
                        help="training YAML of the urban network (default config/urban.yaml)")  # fmt: skip
    parser.add_argument("--networks", nargs="+", default=list(NETWORKS),
                        help="which networks to run (default: ring urban; also exit, or a name given by "
                        "--scenario-config)")  # fmt: skip
    parser.add_argument("--exit-config", dest="exit_config", default="config/exit.yaml",
                        help="training YAML of the exit scenario (default config/exit.yaml)")  # fmt: skip
    parser.add_argument("--scenario-config", dest="scenario_configs", action="append", default=[], metavar="NAME=YAML",
                        help="a training YAML whose env is a scenario file, run as network NAME (repeatable)")  # fmt: skip
    parser.add_argument("--urban-seeds", dest="urban_seeds", type=int, default=None,
                        help="urban runs use only the first N of the seeds (an urban run costs ~3 ring runs; "
                        "default: all of them)")  # fmt: skip
    parser.add_argument("--baseline-params", dest="baseline_params", default=None,
                        help="tuned gap-acceptance thresholds (default config/baselines.yaml)")  # fmt: skip
    parser.add_argument("--no-baselines", dest="baselines", action="store_false", help="skip the baseline rows")
    parser.add_argument("--shield", "--safety", dest="shield", choices=SAFETY_KINDS, default="none",
                        help="also run every method behind this safety shield (rows '<method>+shield', and the "
                        "baselines 'immediate+shield', 'random+shield', 'gap_acceptance+shield'; docs/safety.md)")  # fmt: skip
    parser.add_argument("--shield-mode", "--safety-mode", dest="shield_mode", choices=SAFETY_MODES, default=None,
                        help="replace or mask for the shielded rows (default: the config's env.safety.mode)")  # fmt: skip
    parser.add_argument("--shield-networks", dest="shield_networks", nargs="+", default=None, metavar="NETWORK",
                        help="the networks that get the shielded rows (default: every one of --networks); the "
                        "others keep the paper's rows only")  # fmt: skip
    parser.add_argument("--shield-only", dest="shield_only", action="store_true",
                        help="run only the shielded rows (the unshielded ones are reused when present)")  # fmt: skip
    parser.add_argument("--name", default=DEFAULT_NAME,
                        help=f"file stem of the results: <results>/<name>.md, <name>.json, <name>_<network>_curves.png "
                        f"(default {DEFAULT_NAME}; e.g. table_exit for the exit suite)")  # fmt: skip
    add_backend_arguments(parser)


def check_name(name: str) -> str:
    """``--name`` as given if it is a plain file stem (letters, digits, '_', '-', not starting with '-'); else
    SystemExit with one line naming the value."""
    if not re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_-]*", name):
        raise SystemExit(f"der table3: --name {name!r}, expected a plain file stem (letters, digits, '_' or '-'; "
                         "no folder, no extension), e.g. table_exit")  # fmt: skip
    return name


def score_run(run: RunResult) -> dict[str, float]:
    """Per-run scores: the final greedy evaluation, and the paper's total reward over training episodes."""
    ev = final_evaluation(run.spec.run_dir)
    nan = math.nan
    return {
        "eval_success": ev.success_rate if ev else nan,
        "eval_collision": ev.collision_rate if ev else nan,
        "eval_time_limit": ev.time_limit_rate if ev else nan,
        "eval_return": ev.mean_return if ev else nan,
        "eval_episodes": float(ev.n) if ev else 0.0,
        "eval_interventions": ev.mean_interventions if ev else nan,
        "eval_time_to_exit": ev.mean_time_to_success if ev else nan,
        "eval_imposed_brake": ev.mean_imposed_brake if ev else nan,
        "train_total_reward": average_score(run.returns),
        "train_episodes": float(len(run.returns)),
    }


def _baseline_scores(res: EvalResult) -> dict[str, float]:
    return {"eval_success": res.success_rate, "eval_collision": res.collision_rate,
            "eval_time_limit": res.time_limit_rate, "eval_return": res.mean_return, "episodes": float(res.n),
            "eval_episodes": float(res.n), "eval_interventions": res.mean_interventions,
            "eval_time_to_exit": res.mean_time_to_success, "eval_imposed_brake": res.mean_imposed_brake}  # fmt: skip


def _null_unmeasured(scores: dict[str, Any]) -> dict[str, Any]:
    """``scores`` with the COST_KEYS' NaN (not measured) as None (JSON null); the other fields as they are."""
    def null(v: Any) -> Any:
        if isinstance(v, list):
            return [null(x) for x in v]
        return None if isinstance(v, float) and math.isnan(v) else v

    return {k: null(v) if k in COST_KEYS else v for k, v in scores.items()}


def _cost_cell(values: Sequence[float] | float, digits: int = 1) -> str:
    """A COST_KEYS cell: one value, or mean ± CI over the seeds that have one; "–" when none has."""
    if not isinstance(values, (list, tuple)):
        return "–" if math.isnan(values) else f"{values:.{digits}f}"
    finite = [v for v in values if not math.isnan(v)]
    if not finite:
        return "–"
    ci = mean_interval(finite)
    return f"{ci.value:.{digits}f} ± {max(ci.high - ci.value, ci.value - ci.low):.{digits}f}"


def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("eclipse-sumo", "libsumo", "rliable"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def _cell(x: Interval, digits: int = 3) -> str:
    return x.format(digits)


def write_table3(
    results: dict[str, dict[str, list[RunResult]]],
    labels: dict[str, str],
    baselines: dict[str, dict[str, EvalResult]],
    path: Path,
    command: str,
    seeds: Sequence[int],
    steps: dict[str, int],
    wall_s: float,
    baseline_labels: dict[str, dict[str, str]] | None = None,
) -> tuple[Path, Path]:
    """``table3.md`` (see the module docstring) and ``table3.json`` (every per-seed number).

    ``baseline_labels``: per network, labels that replace ``BASELINE_LABELS`` (e.g. an untuned gap rule)."""
    scores = {net: {m: [score_run(r) for r in runs] for m, runs in by_m.items()} for net, by_m in results.items()}
    n_eval = max((int(s["eval_episodes"]) for by_m in scores.values() for ss in by_m.values() for s in ss), default=0)
    lines = [
        "# Table 3 — SUMO lane change (reproduction, greedy evaluation)",
        "",
        f"**Headline: the greedy policy** (ε = 0) after training, on {n_eval} held-out evaluation episodes per",
        f"training seed (evaluation seeds {EVAL_SEED_BASE}+k: never used in training, the same for every method and",
        "baseline). Learned methods: **IQM over training seeds [95% stratified-bootstrap CI]** (rliable);",
        "baselines: the same episodes, no training. *Caused collision* = a collision within 3 s of the agent's",
        "own lane change. *Return* = the paper's reward over the 50-step episode (log mean speed per step, +100",
        "once for reaching the target lane, −100 for a caused collision). The last columns are the paper's own",
        "metric, *total reward* = mean return over all **training** episodes (ε-greedy exploration included;",
        "mean over seeds ± 95% CI), beside the paper's value.",
        "*Time to success* = simulated seconds from an episode's start to its success (the change held on the target",
        "lane, or the exit taken), mean over the successful episodes; *imposed braking* = the harshest deceleration",
        "of the ego's new follower within 3 s of each of its lane changes (MOBIL's safety criterion; 0 without a",
        "change), mean over episodes, in m/s² (sumo_bridge/lane_change_env.py); learned methods: mean over seeds",
        "± 95% CI. \"–\": an evaluation made before these were measured.",
        "",
    ]
    per_seed = ["| Network | Method | Seed | Eval success | Eval caused collision | Eval time limit | Eval return "
                "| Eval time to success (s) | Eval imposed braking (m/s²) | Train total reward | Train episodes |",
                "|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    payload: dict[str, Any] = {}
    for net, by_method in scores.items():
        payload[net] = {}
        lines += [
            f"## {NETWORKS.get(net, net)}",
            "",
            "| Method | Success | Caused collision | Time limit | Return | Interventions / episode "
            "| Time to success (s) | Imposed braking (m/s²) | Total reward (training, paper's metric) | Total reward (paper) |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for name, per in by_method.items():
            run_seeds = [r.spec.seed for r in results[net][name]]
            col = {k: [s[k] for s in per] for k in SCORE_KEYS}
            payload[net][name] = _null_unmeasured({"seeds": run_seeds, **{k: col[k] for k in SCORE_KEYS}})
            paper = PAPER_TABLE3.get(net, {}).get(name, math.nan)  # exit, scenario files: none
            lines.append(
                f"| {labels[name]} (n={len(per)}) | {_cell(iqm_interval(col['eval_success']))} "
                f"| {_cell(iqm_interval(col['eval_collision']))} | {_cell(iqm_interval(col['eval_time_limit']))} "
                f"| {_cell(iqm_interval(col['eval_return']), 1)} | {_mean_pm(col['eval_interventions'])} "
                f"| {_cost_cell(col['eval_time_to_exit'])} | {_cost_cell(col['eval_imposed_brake'])} "
                f"| {_mean_pm(col['train_total_reward'])} | {'—' if math.isnan(paper) else f'{paper:.2f}'} |"
            )
            for r, s in zip(results[net][name], per):
                per_seed.append(
                    f"| {net} | {labels[name]} | {r.spec.seed} | {s['eval_success']:.3f} | {s['eval_collision']:.3f} "
                    f"| {s['eval_time_limit']:.3f} | {s['eval_return']:.2f} | {_cost_cell(s['eval_time_to_exit'])} "
                    f"| {_cost_cell(s['eval_imposed_brake'])} | {s['train_total_reward']:.2f} "
                    f"| {int(s['train_episodes'])} |"
                )
        b_names = {b: (baseline_labels or {}).get(net, {}).get(b) or BASELINE_LABELS.get(b, b) for b in baselines.get(net, {})}
        for bname, res in baselines.get(net, {}).items():
            b = _baseline_scores(res)
            payload[net][bname] = _null_unmeasured(b)
            lines.append(f"| *baseline:* {b_names[bname]} | {b['eval_success']:.3f} "
                         f"| {b['eval_collision']:.3f} | {b['eval_time_limit']:.3f} | {b['eval_return']:.1f} "
                         f"| {b['eval_interventions']:.2f} | {_cost_cell(b['eval_time_to_exit'])} "
                         f"| {_cost_cell(b['eval_imposed_brake'])} | — | — |")  # fmt: skip
        lines += ["", "Mean over seeds [95% CI] of the same evaluation (the IQM above is the headline):", "",
                  "| Method | Success | Caused collision | Return |", "|---|---|---|---|"]  # fmt: skip
        for name in by_method:
            col = payload[net][name]
            lines.append(f"| {labels[name]} | {_cell(mean_interval(col['eval_success']))} "
                         f"| {_cell(mean_interval(col['eval_collision']))} | {_cell(mean_interval(col['eval_return']), 1)} |")  # fmt: skip
        lines += _significance(net, payload[net], labels)
        lines += efficiency_section(results[net], payload[net], labels)
        lines += _paired(results[net], baselines.get(net, {}), labels, b_names)
        lines += ["", f"![{net}: evaluation and training curves]({path.stem}_{net}_curves.png)", ""]
    info = environment_info() | _versions()
    counts = {net: max((len(runs) for runs in by_m.values()), default=0) for net, by_m in results.items()}
    seeds_per = "method and network"
    if len(set(counts.values())) > 1:  # --urban-seeds: urban ran the first few seeds only
        seeds_per = "method; runs per network: " + ", ".join(f"{net} {n}" for net, n in counts.items())
    lines += run_details(command, seeds, steps, wall_s, info, per_seed, seeds_per=seeds_per)
    md = write_markdown(path, lines)
    js = path.with_suffix(".json")
    tmp = js.with_name(f".{js.name}.tmp")
    tmp.write_text(json.dumps(payload, indent=1, allow_nan=True))
    tmp.replace(js)
    return md, js


def _mean_pm(values: Sequence[float]) -> str:
    ci = mean_interval(values)
    if math.isnan(ci.value):
        return "n/a"
    return f"{ci.value:.2f} ± {max(ci.high - ci.value, ci.value - ci.low):.2f}"


def _significance(net: str, payload: dict[str, Any], labels: dict[str, str]) -> list[str]:
    """The probability-of-improvement table and the sentences that follow from it."""
    pairs = [(x, y) for x, y in COMPARISONS if x in payload and y in payload and "seeds" in payload[x]]
    if not pairs:
        return []
    lines = ["", "Is DER better? Probability of improvement P(X > Y) over training seeds [95% CI] (rliable):", "",
             "| X vs Y | P(X > Y) on success | P(X > Y) on return |", "|---|---|---|"]  # fmt: skip
    sentences = []
    for x, y in pairs:
        p_s = probability_of_improvement(payload[x]["eval_success"], payload[y]["eval_success"])
        p_r = probability_of_improvement(payload[x]["eval_return"], payload[y]["eval_return"])
        lines.append(f"| {labels[x]} vs {labels[y]} | {p_s.format(2)} | {p_r.format(2)} |")
        n = min(len(payload[x]["seeds"]), len(payload[y]["seeds"]))
        sentences.append(significance_sentence(labels[x], labels[y], p_r, "greedy return", n))
    lines += ["", *[f"- {s}" for s in sentences]]
    return lines


#: the baselines a learned agent is paired with episode by episode: the two a user holds it to
PAIRED_BASELINES = ("gap_acceptance", "sumo")


def _range(values: Sequence[int]) -> str:
    lo, hi = min(values), max(values)
    return f"{lo}" if lo == hi else f"{lo}–{hi}"


def _noun(values: Sequence[int], word: str) -> str:
    return word if min(values) == max(values) == 1 else word + "s"


def _paired(runs: dict[str, list[RunResult]], baselines: dict[str, EvalResult], labels: dict[str, str],
            b_labels: dict[str, str]) -> list[str]:  # fmt: skip
    """Learned runs against the gap rule and SUMO's model on identical traffic (:mod:`der_ros.experiments.paired`)."""
    evals = {m: [ev for r in rs if (ev := final_evaluation(r.spec.run_dir)) is not None] for m, rs in runs.items()}
    table: dict[str, dict[str, PairedCounts]] = {}
    for b in PAIRED_BASELINES:
        if b not in baselines:
            continue
        for m, evs in evals.items():
            counts = paired_counts(evs, baselines[b]) if evs else None
            if counts is not None:
                table.setdefault(b, {})[m] = counts
    if not table:
        return []
    per_run = max(c.pairs // c.runs for by_m in table.values() for c in by_m.values())
    lines = ["", "Episode by episode against the gap rule and SUMO's model: each run's evaluation episodes paired with the",
             f"baseline's on identical traffic (the episodes that start from a seeded reset, {per_run} per run); counts over",
             "all runs of a method. One hard situation repeats in every run, so the last two columns count traffic",
             "situations instead (each evaluation seed once, the method's runs pooled: better where its success rate",
             "is above the baseline's, worse where below), with p of a paired permutation test over situations that",
             "the method's rate and the baseline's are the same.", "",
             "| Method | Baseline | Pairs | Only the method succeeds | Only the baseline succeeds | Caused collisions "
             "(distinct episodes) | …of them, the baseline succeeds | Baseline's caused collisions "
             "| Situations: method better / worse on success (p) | …on caused collisions (p) |",
             "|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    sentences = []
    for b, by_m in table.items():
        for m, c in by_m.items():
            lines.append(f"| {labels[m]} | {b_labels.get(b, b)} | {c.pairs} | {c.only_method} | {c.only_baseline} "
                         f"| {c.method_caused} ({c.method_caused_situations}) | {c.method_caused_baseline_succeeds} "
                         f"| {c.baseline_caused} | {c.success_better} / {c.success_worse} ({_p_cell(c.success_p)}) "
                         f"| {c.caused_fewer} / {c.caused_more} ({_p_cell(c.caused_p)}) |")  # fmt: skip
        cs = list(by_m.values())
        caused = [c.method_caused for c in cs]
        text = (f"Against {b_labels.get(b, b)}: each learned method succeeds in {_range([c.only_method for c in cs])} "
                f"pairs where the baseline fails, the baseline in {_range([c.only_baseline for c in cs])} where the "
                "method fails")  # fmt: skip
        if sum(caused):
            situations = [c.method_caused_situations for c in cs]
            text += (f"; a method's caused collisions ({_range(caused)}) fall in "
                     f"{_range(situations)} distinct traffic {_noun(situations, 'situation')}")  # fmt: skip
            if all(c.method_caused_baseline_succeeds == c.method_caused for c in cs):
                text += ", and the baseline gets through every one of them"
        sentences.append(text + ".")
        sentences.append(_situation_sentence(b_labels.get(b, b), by_m, labels))
    return lines + ["", *[f"- {s}" for s in sentences]]


#: the level below which a permutation-test p counts as a difference in the generated sentences (uncorrected)
PAIRED_ALPHA = 0.05


def _p_text(p: float) -> str:
    return "p < 0.001" if p < 0.001 else f"p = {p:.3f}"


def _p_cell(p: float) -> str:
    return "< 0.001" if p < 0.001 else f"{p:.3f}"


def _situation_sentence(b_label: str, by_m: dict[str, PairedCounts], labels: dict[str, str]) -> str:
    """What the permutation tests over traffic situations say, method by method, against one baseline."""
    found = []
    for m, c in by_m.items():
        for what, p, good, bad in (("success", c.success_p, c.success_better, c.success_worse),
                                   ("caused collisions", c.caused_p, c.caused_fewer, c.caused_more)):  # fmt: skip
            if p < PAIRED_ALPHA:
                side = "better" if good > bad else "worse"
                found.append(f"{labels[m]} is {side} on {what} ({good} against {bad} situations, {_p_text(p)})")
    text = f"Paired by traffic situation (permutation test, p < {PAIRED_ALPHA}, uncorrected), against {b_label}: "
    if found:
        text += "; ".join(found) + "; no other difference"
    else:
        text += "no learned method differs on success or on caused collisions"
    # the fewest situations that can reach the level: n all one way, p = 2 · 2^-n
    need = next(n for n in range(1, 17) if paired_permutation_p([1.0] * n) < PAIRED_ALPHA)
    most = {"success": max(c.success_better + c.success_worse for c in by_m.values()),
            "caused collisions": max(c.caused_fewer + c.caused_more for c in by_m.values())}  # fmt: skip
    short = [what for what, n in most.items() if n < need]
    if short:
        n = max(most[what] for what in short)
        text += (f". On {' or '.join(short)} no difference could show: it takes {need} situations all one way, and "
                 f"here at most {n} {'differs' if n == 1 else 'differ'}")  # fmt: skip
    return text + "."


def run(args: argparse.Namespace) -> int:
    stem = check_name(args.name)  # before anything runs
    paper_methods = methods_by_name(args.methods)
    shielded: list[Method] = []
    if args.shield != "none":  # the shielded twins (Table 3 gains rows; the paper's rows stay)
        shielded = [shielded_method(m, args.shield, args.shield_mode) for m in paper_methods]
    elif args.shield_only or args.shield_networks:
        raise SystemExit("der table3: --shield-only / --shield-networks need --shield rss or --shield sumo")
    shield_nets = set(args.networks if args.shield_networks is None else args.shield_networks)
    stray = sorted(shield_nets - set(args.networks))
    if stray:
        raise SystemExit(f"der table3: --shield-networks {stray[0]!r} is not one of --networks ({', '.join(args.networks)})")

    def net_methods(net: str) -> list[Method]:
        twins = shielded if net in shield_nets else []
        return twins if args.shield_only else paper_methods + twins

    methods = paper_methods + shielded  # every label
    seeds = suite_seeds(args)
    overrides = suite_overrides(args)
    configs = {"ring": args.config, "urban": args.urban_config, "exit": args.exit_config}
    for item in args.scenario_configs:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise SystemExit(f"der table3: --scenario-config {item!r}, expected NAME=YAML")
        configs[name] = path
    unknown = [net for net in args.networks if net not in configs]
    if unknown:
        raise SystemExit(f"der table3: --networks {unknown[0]!r}, expected one of {', '.join(configs)}")
    specs: list[RunSpec] = []
    if args.urban_seeds is not None and not 1 <= args.urban_seeds <= len(seeds):
        raise SystemExit(f"der table3: --urban-seeds = {args.urban_seeds}, expected 1..{len(seeds)} (--seeds)")
    net_seeds = {net: seeds[: args.urban_seeds] if net == "urban" and args.urban_seeds else seeds for net in args.networks}
    for net in args.networks:
        specs += plan_runs(configs[net], net_methods(net), net_seeds[net], args.out, overrides, group=net)
    summaries = run_specs(specs, backend=backend_from_args(args), train=args.train)
    if report_interrupted("table3", summaries):
        return 130
    results: dict[str, dict[str, list[RunResult]]] = {net: {m.name: [] for m in net_methods(net)} for net in args.networks}
    for spec in specs:
        results[spec.group][spec.method.name].append(load_result(spec, ()))
    baselines: dict[str, dict[str, EvalResult]] = {}
    if args.baselines:
        jobs: list[tuple[str, BaselineJob]] = []
        for net in args.networks:
            cfg = load_experiment_config(configs[net], overrides or None)
            episodes = cfg.train.final_eval_episodes or cfg.train.eval_episodes
            params_file = args.baseline_params or DEFAULT_PARAMS_FILE
            folder = Path(args.out) / net / "baselines"
            for name in baseline_names(cfg.env):
                jobs.append((net, baseline_job(cfg.env, name, episodes, cfg.train.eval_episodes_per_seed,
                                               cfg.train.eval_seed_base, folder / name, rule_params(name, net, params_file))))  # fmt: skip
            if args.shield != "none" and net in shield_nets:
                env_s = shielded_env_config(cfg.env, args.shield, args.shield_mode)
                for name in SHIELDED_BASELINES:
                    jobs.append((net, baseline_job(env_s, name + SHIELD_SUFFIX, episodes, cfg.train.eval_episodes_per_seed,
                                                   cfg.train.eval_seed_base, folder / (name + SHIELD_SUFFIX),
                                                   rule_params(name, net, params_file))))  # fmt: skip
        evaluated = run_baselines([j for _, j in jobs], args.jobs)
        for net, job in jobs:
            baselines.setdefault(net, {})[job.name] = evaluated[job.out_dir]
    labels = {m.name: m.label for m in methods}
    params_file = args.baseline_params or DEFAULT_PARAMS_FILE
    b_labels = {net: {"gap_acceptance": "gap acceptance (not tuned: hand-set thresholds)"}
                for net in baselines if not gap_params_tuned(net, params_file)}  # fmt: skip
    steps = {net: max(int(r.summary["steps"]) for runs in by_m.values() for r in runs) for net, by_m in results.items()}
    out = Path(args.results)
    extra = ["--urban-config", str(args.urban_config), "--networks", *args.networks]
    if "exit" in args.networks:
        extra += ["--exit-config", str(args.exit_config)]
    for item in args.scenario_configs:
        extra += ["--scenario-config", item]
    if args.urban_seeds is not None:
        extra += ["--urban-seeds", str(args.urban_seeds)]
    if args.shield != "none":
        extra += ["--shield", args.shield] + (["--shield-mode", args.shield_mode] if args.shield_mode else [])
        extra += ["--shield-only"] if args.shield_only else []
        extra += ["--shield-networks", *args.shield_networks] if args.shield_networks is not None else []
    if stem != DEFAULT_NAME:
        extra += ["--name", stem]
    md, js = write_table3(results, labels, baselines, out / f"{stem}.md", suite_command("table3", args, extra), seeds,
                          steps, total_training_time(results), b_labels)  # fmt: skip
    figures = []
    for net, by_method in results.items():
        fig = out / f"{stem}_{net}_curves.png"
        marks = {b_labels.get(net, {}).get(b, BASELINE_LABELS[b]): {"success": r.success_rate, "collision": r.collision_rate}
                 for b, r in baselines.get(net, {}).items() if b in ("gap_acceptance", "sumo")}  # fmt: skip
        plot_eval_curves(by_method, labels, fig, metrics=("success", "collision"), baselines=marks,
                         title=f"{NETWORKS.get(net, net)}: greedy evaluation (IQM over seeds) and training returns")  # fmt: skip
        figures.append(str(fig))
    print(md.read_text())
    print(f"wrote {md}, {js}, {', '.join(figures)}")
    return 0

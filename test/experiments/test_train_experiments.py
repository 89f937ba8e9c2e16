"""Experiment suites: bootstrap statistics, paper scores, `der table1` / `der table2` end to end."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from der_ros import cli
from der_ros.experiments.stats import (
    average_score,
    bootstrap_band,
    bootstrap_ci,
    curve_on_grid,
    max_moving_average,
    mean_of_last,
    moving_average,
)
from der_ros.experiments.suite import PAPER_METHODS, methods_by_name, plan_runs

REPO = Path(__file__).resolve().parents[2]


def test_bootstrap_ci_on_known_data() -> None:
    rng = np.random.default_rng(42)
    x = rng.normal(10.0, 2.0, size=400)
    ci = bootstrap_ci(x, n_resamples=10_000, seed=0)
    assert ci.mean == pytest.approx(float(x.mean()))
    half = 1.96 * x.std(ddof=1) / np.sqrt(x.size)  # normal-theory 95% half-width
    assert ci.low < ci.mean < ci.high
    assert (ci.high - ci.low) / 2 == pytest.approx(half, rel=0.1)
    assert bootstrap_ci(x, seed=0) == ci  # fixed seed: reproducible bit for bit
    const = bootstrap_ci([3.0, 3.0, 3.0])
    assert (const.low, const.mean, const.high) == (3.0, 3.0, 3.0)
    one = bootstrap_ci([5.0])
    assert (one.low, one.high, one.n) == (5.0, 5.0, 1)
    assert np.isnan(bootstrap_ci([]).mean)
    # two values 0 and 1: resampled means take values 0, 0.5, 1 -> 95% interval is [0, 1]
    two = bootstrap_ci([0.0, 1.0])
    assert (two.low, two.mean, two.high) == (0.0, 0.5, 1.0)


def test_bootstrap_band_per_point() -> None:
    curves = np.array([[0.0, 1.0, np.nan], [2.0, 1.0, 4.0]])
    mean, lo, hi = bootstrap_band(curves)
    np.testing.assert_allclose(mean, [1.0, 1.0, 4.0])
    np.testing.assert_allclose(lo, [0.0, 1.0, 4.0])
    np.testing.assert_allclose(hi, [2.0, 1.0, 4.0])


def test_paper_scores() -> None:
    returns = np.array([10, 20, 30, 40, 500, 500, 0], dtype=float)
    assert max_moving_average(returns, window=2) == 500.0
    assert max_moving_average(returns, window=3) == pytest.approx((40 + 500 + 500) / 3)
    assert max_moving_average(returns[:2], window=20) == 15.0  # fewer episodes than the window
    assert average_score(returns) == pytest.approx(returns.mean())
    assert mean_of_last(returns, 3) == pytest.approx(1000 / 3)
    np.testing.assert_allclose(moving_average([1, 2, 3, 4], 2), [1.5, 2.5, 3.5])
    # learning curve on a step grid: moving average of the episodes finished by each grid step
    steps = np.array([10, 20, 30, 40])
    curve = curve_on_grid(steps, [1.0, 3.0, 5.0, 7.0], np.array([5, 10, 25, 40, 100]), window=2)
    np.testing.assert_allclose(curve, [np.nan, 1.0, 2.0, 6.0, 6.0])


def test_methods_and_run_plan() -> None:
    assert [m.name for m in PAPER_METHODS] == ["dqn", "der0.1", "der0.5", "der0.9", "per"]
    specs = plan_runs("cfg.yaml", methods_by_name(["dqn", "der0.9"]), [0, 1], "/out", {"train.total_steps": 5})
    assert [Path(s.run_dir).relative_to("/out").as_posix() for s in specs] == [
        "dqn/seed0",
        "dqn/seed1",
        "der0.9/seed0",
        "der0.9/seed1",
    ]
    ov = specs[2].all_overrides()
    assert ov["replay.kind"] == "der" and ov["replay.lam"] == 0.9 and ov["train.seed"] == 0
    assert ov["train.total_steps"] == 5 and ov["train.progress"] is False
    with pytest.raises(ValueError, match="unknown"):
        methods_by_name(["dqn", "nope"])


@pytest.mark.slow
def test_table1_end_to_end_and_resumable(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out, results = tmp_path / "runs", tmp_path / "results"
    argv = ["table1", "--config", str(REPO / "config" / "cartpole.yaml"), "--seeds", "2", "--steps", "300"]
    argv += ["--methods", "dqn", "der0.9", "--jobs", "2", "--out", str(out), "--results", str(results)]
    argv += ["--set", "agent.learning_starts=100", "--set", "agent.hidden_sizes=[32]"]
    argv += ["--set", "train.tensorboard=false", "--set", "train.save_final_checkpoint=false"]
    argv += ["--set", "train.eval_interval=100", "--set", "train.eval_episodes=4", "--set", "train.final_eval_episodes=6"]
    assert cli.main(argv) == 0
    md = (results / "table1.md").read_text()
    assert "| DQN (n=2) |" in md and "| λ = 0.9 (n=2) |" in md
    assert "373.80" in md and "229.30" in md and "285.49" in md  # the paper's numbers beside ours
    assert "Greedy return (IQM)" in md and "*baseline:* random" in md and "*baseline:* scripted" in md
    assert "P(X > Y) on max score" in md and "too few for a verdict" in md  # 2 seeds: no verdict
    assert "--seeds 2" in md and "torch:" in md and "rliable:" in md and "seeds: 1000, 1001" in md
    for png in ("table1_curves.png", "table1_td.png"):
        assert (results / png).stat().st_size > 10_000
    summaries = sorted(out.glob("*/seed*/summary.json"))
    assert len(summaries) == 4
    for p in summaries:
        s = json.loads(p.read_text())
        assert s["steps"] == 300 and s["episodes"] > 0
    # the per-seed rows and the JSON twin carry each run's own scores
    dqn0 = json.loads((out / "dqn" / "seed1000" / "summary.json").read_text())
    final = json.loads((out / "dqn" / "seed1000" / "evaluation.json").read_text())
    assert len(final["episodes"]) == 6 and min(final["seeds"]) >= 1_000_000_000
    row = f"| DQN | 1000 | {dqn0['episodes']} | {dqn0['max_ma20_return']:.2f} | {dqn0['mean_return']:.2f} "
    assert row + f"| {final['summary']['mean_return']:.2f} |" in md
    table = json.loads((results / "table1.json").read_text())["cartpole"]
    assert table["dqn"]["seeds"] == [1000, 1001]
    assert table["dqn"]["max_ma20"][0] == pytest.approx(dqn0["max_ma20_return"])
    assert table["dqn"]["avg_score"][0] == pytest.approx(dqn0["mean_return"])
    assert table["dqn"]["eval_return"][0] == pytest.approx(final["summary"]["mean_return"])
    assert set(table) == {"dqn", "der0.9", "random", "constant", "scripted"} and "seeds" not in table["scripted"]
    assert table["scripted"]["eval_return"] > table["random"]["eval_return"]
    # rerun: every run is finished, nothing is retrained
    mtimes = [p.stat().st_mtime_ns for p in summaries]
    (results / "table1.md").unlink()
    assert cli.main(argv) == 0
    assert [p.stat().st_mtime_ns for p in summaries] == mtimes
    assert (results / "table1.md").read_text().split("## Runs")[0] == md.split("## Runs")[0]
    capsys.readouterr()


@pytest.mark.slow
def test_table3_tiny_end_to_end_writes_the_evaluation_columns(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out, results = tmp_path / "runs", tmp_path / "results"
    argv = ["table3", "--networks", "ring", "--methods", "dqn", "der0.9", "--seeds", "1", "--steps", "120"]
    argv += ["--jobs", "2", "--out", str(out), "--results", str(results)]
    argv += ["--set", "agent.learning_starts=60", "--set", "agent.hidden_sizes=[32]", "--set", "train.tensorboard=false"]
    argv += ["--set", "train.eval_interval=60", "--set", "train.eval_episodes=2", "--set", "train.final_eval_episodes=3"]
    # --no-train before any run: refused, the unfinished runs named, nothing trained or written
    assert cli.main([*argv, "--no-train"]) == 1
    err = capsys.readouterr().err
    assert "2 of 2 runs are not finished and --no-train was given" in err and str(out / "ring" / "dqn" / "seed1000") in err
    assert not (out / "ring" / "dqn" / "seed1000" / "summary.json").exists() and not (results / "table3.md").exists()
    assert cli.main(argv) == 0
    (results / "table3.md").unlink()
    assert cli.main([*argv, "--no-train"]) == 0  # finished runs: re-tabled
    md = (results / "table3.md").read_text()
    for col in ("| Success | Caused collision | Time limit | Return |", "Total reward (training, paper's metric)",
                "*baseline:* never change (keep)", "*baseline:* gap acceptance (tuned)",
                "*baseline:* SUMO's own model", "P(X > Y) on success", "216.91",
                "Episode by episode against the gap rule and SUMO's model", "| DQN | gap acceptance (tuned) | 3 |"):
        assert col in md
    table = json.loads((results / "table3.json").read_text())["ring"]
    assert set(table) == {"dqn", "der0.9", "keep", "immediate", "random", "gap_acceptance", "sumo"}
    for key in ("seeds", "eval_success", "eval_collision", "eval_return", "train_total_reward"):
        assert len(table["dqn"][key]) == 1
    final = json.loads((out / "ring" / "dqn" / "seed1000" / "evaluation.json").read_text())
    assert table["dqn"]["eval_return"][0] == pytest.approx(final["summary"]["mean_return"])
    # success at what cost to others, measured in this evaluation: per seed, from the run's own episodes
    assert table["dqn"]["eval_imposed_brake"][0] == pytest.approx(final["summary"]["imposed_brake"])
    assert all(e["imposed_brake"] >= 0.0 for e in final["episodes"])
    assert table["keep"]["eval_imposed_brake"] == 0.0 and table["keep"]["eval_time_to_exit"] is None
    assert table["keep"]["eval_success"] == 0.0 and table["keep"]["eval_time_limit"] == 1.0  # never changes lane
    assert "seeds" not in table["keep"]
    # every baseline rate is the count of its own episodes, recounted here (a rate in [0, 1] could be any rate)
    for name in ("gap_acceptance", "sumo", "keep"):
        eps = json.loads((out / "ring" / "baselines" / name / "evaluation.json").read_text())["episodes"]
        assert len(eps) == 3
        caused = sum(e["outcome"] == "collision" and e["caused"] for e in eps) / 3
        success = sum(e["outcome"] == "success" for e in eps) / 3
        assert (table[name]["eval_collision"], table[name]["eval_success"]) == (pytest.approx(caused),
                                                                              pytest.approx(success)), name
        assert table[name]["eval_return"] == pytest.approx(sum(e["ret"] for e in eps) / 3), name
    assert (results / "table3_ring_curves.png").stat().st_size > 10_000
    capsys.readouterr()


@pytest.mark.slow
def test_table2_short_atari_run(tmp_path: Path) -> None:
    out, results = tmp_path / "runs", tmp_path / "results"
    argv = ["table2", "--config", str(REPO / "config" / "atari.yaml"), "--games", "Breakout", "--methods", "der0.1"]
    argv += ["--seeds", "1", "--steps", "300", "--jobs", "1", "--out", str(out), "--results", str(results)]
    argv += ["--set", "replay.capacity=500", "--set", "replay.h2_capacity=64", "--set", "agent.batch_size=16"]
    argv += ["--set", "agent.learning_starts=100", "--set", "train.tensorboard=false"]
    argv += ["--set", "train.final_eval_episodes=1", "--set", "env.max_episode_steps=400"]
    assert cli.main(argv) == 0
    md = (results / "table2.md").read_text()
    assert "| Breakout |" in md and "58.28" in md  # paper's lambda = 0.1 Breakout score beside ours
    summary = json.loads((out / "breakout" / "der0.1" / "seed1000" / "summary.json").read_text())
    assert summary["steps"] == 300
    assert (results / "table2_curves.png").is_file()
    cfg = (out / "breakout" / "der0.1" / "seed1000" / "config.yaml").read_text()
    assert "ALE/Breakout-v5" in cfg


@pytest.mark.slow
def test_a_failing_run_does_not_stop_the_suite(tmp_path: Path) -> None:
    from der_ros.experiments.backends.dispatch import run_specs
    from der_ros.experiments.suite import PAPER_METHODS, SuiteRunError, plan_runs

    dqn = [m for m in PAPER_METHODS if m.name == "dqn"]
    small = {"train.total_steps": 200, "agent.learning_starts": 50, "agent.hidden_sizes": [16],
             "train.tensorboard": False, "train.save_final_checkpoint": False}
    good = plan_runs(REPO / "config" / "cartpole.yaml", dqn, [0], tmp_path, small, group="good")
    bad = plan_runs(REPO / "config" / "cartpole.yaml", dqn, [0], tmp_path, small | {"env.id": "NoSuchEnv-v0"},
                    group="bad")
    with pytest.raises(SuiteRunError) as err:
        run_specs(bad + good, jobs=1)
    assert [spec.group for spec, _ in err.value.failures] == ["bad"]
    assert "NoSuchEnv" in str(err.value) and "rerun the same command" in str(err.value)
    assert json.loads((tmp_path / "good" / "dqn" / "seed0" / "summary.json").read_text())["steps"] == 200
    assert not (tmp_path / "bad" / "dqn" / "seed0" / "summary.json").exists()


@pytest.mark.slow
def test_a_run_directory_made_with_other_settings_is_refused(tmp_path: Path) -> None:
    from der_ros.configuration import ConfigError
    from der_ros.experiments.backends.dispatch import run_specs
    from der_ros.experiments.suite import run_one

    dqn = [m for m in PAPER_METHODS if m.name == "dqn"]
    small = {"train.total_steps": 200, "agent.learning_starts": 50, "agent.hidden_sizes": [16],
             "train.tensorboard": False, "train.save_final_checkpoint": False, "train.final_eval_episodes": 2}
    cartpole = REPO / "config" / "cartpole.yaml"
    (spec,) = plan_runs(cartpole, dqn, [0], tmp_path, small)
    assert run_specs([spec], jobs=1)[0]["steps"] == 200
    summary = Path(spec.run_dir) / "summary.json"
    mtime = summary.stat().st_mtime_ns
    # the same settings (a different log interval does not change the result): reused, not retrained
    same = plan_runs(cartpole, dqn, [0], tmp_path, small | {"train.log_interval": 7})
    assert run_specs(same, jobs=1) == [] and summary.stat().st_mtime_ns == mtime
    # another gamma in the same directory: refused before any run starts, naming the field; the old run is kept
    other = plan_runs(cartpole, dqn, [0], tmp_path, small | {"agent.gamma": 0.9})
    with pytest.raises(ConfigError, match=r"agent\.gamma = 0\.98 there, 0\.9 now.*another --out"):
        run_specs(other, jobs=1)
    # an interrupted run (no summary) is not resumed under other settings either
    summary.unlink()
    with pytest.raises(ConfigError, match=r"agent\.gamma"):
        run_one(other[0])
    assert not summary.exists()


def test_a_scenario_field_added_after_a_run_counts_as_its_default(tmp_path: Path) -> None:
    """Env kwargs are stored as written: a run made before a scenario field existed has no such key.
    The same-settings check completes the scenario with its defaults, so such a run is reused when
    the field is at its default now, and refused, naming the field, when it is not."""
    import yaml

    from der_ros.configuration import ConfigError
    from der_ros.experiments.run_compare import check_same_settings
    from der_ros.train.config import load_experiment_config

    ring = REPO / "config" / "ring.yaml"
    data = load_experiment_config(ring).to_dict()
    scenario = data["env"]["kwargs"]["scenario"]
    assert "required_decel_scale" not in scenario["observation"]  # the shipped config leaves it out
    # an older run: these fields did not exist yet (false / 0.0 = the behaviour before them)
    scenario.pop("commit_on_success")
    scenario["observation"].pop("near_gap_horizon")
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(data))
    old_rule = "env.kwargs.scenario.commit_on_success=false"
    old_look = "env.kwargs.scenario.observation.near_gap_horizon=0.0"  # the shipped ring uses 1.0
    for extra in ([], ["env.kwargs.scenario.observation.required_decel_scale=0"]):
        check_same_settings(tmp_path, load_experiment_config(ring, [old_rule, old_look, *extra]))
    with pytest.raises(ConfigError, match=r"scenario\.commit_on_success = False there, True now"):
        check_same_settings(tmp_path, load_experiment_config(ring))
    look_ahead = "env.kwargs.scenario.observation.near_gap_horizon=0.5"
    with pytest.raises(ConfigError, match=r"near_gap_horizon = 0\.0 there, 0\.5 now"):
        check_same_settings(tmp_path, load_experiment_config(ring, [old_rule, look_ahead]))
    # a field the current code does not know is compared as written, so it shows up as a change
    scenario["no_such_field"] = 1
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"no_such_field = 1 there, None now"):
        check_same_settings(tmp_path, load_experiment_config(ring, [old_rule]))


@pytest.mark.slow
def test_sweep_evaluates_on_the_tuning_seeds(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A sweep is tuning: its greedy evaluations use the tuning evaluation seeds, never the report's,
    unless --set train.eval_seed_base says otherwise; sweep.md and sweep.json name the set."""
    from der_ros.train.eval_seeds import EVAL_SEED_BASE, TUNING_EVAL_SEED_BASE

    base = ["sweep", str(REPO / "config" / "cartpole.yaml"), "--grid", "agent.gamma=0.9,0.98", "--seeds", "1",
            "--jobs", "2", "--set", "train.total_steps=150", "--set", "agent.learning_starts=50",
            "--set", "agent.hidden_sizes=[16]", "--set", "train.tensorboard=false",
            "--set", "train.eval_interval=0", "--set", "train.final_eval_episodes=3"]  # fmt: skip
    assert cli.main(base + ["--out", str(tmp_path / "tune")]) == 0
    for point in ("gamma=0.9", "gamma=0.98"):
        final = json.loads((tmp_path / "tune" / point / "seed100" / "evaluation.json").read_text())
        assert final["seeds"] == [TUNING_EVAL_SEED_BASE + k for k in range(3)]
    assert f"- evaluation seeds: {TUNING_EVAL_SEED_BASE} + k" in (tmp_path / "tune" / "sweep.md").read_text()
    assert json.loads((tmp_path / "tune" / "sweep.json").read_text())["eval_seed_base"] == TUNING_EVAL_SEED_BASE
    explicit = base + ["--out", str(tmp_path / "report"), "--set", f"train.eval_seed_base={EVAL_SEED_BASE}"]
    assert cli.main(explicit) == 0
    final = json.loads((tmp_path / "report" / "gamma=0.9" / "seed100" / "evaluation.json").read_text())
    assert min(final["seeds"]) == EVAL_SEED_BASE
    capsys.readouterr()

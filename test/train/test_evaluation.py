"""Greedy evaluation on held-out seeds (der_ros.train.evaluation) and its place in the training loop."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from der_ros.configuration import ConfigError
from der_ros.train.config import load_experiment_config
from der_ros.train.envs import make_env
from der_ros.train.eval_episodes import run_episodes
from der_ros.train.eval_result import read_evaluations
from der_ros.train.eval_seeds import (
    EVAL_SEED_BASE,
    TRAINING_SEED_LIMIT,
    TUNING_EVAL_SEED_BASE,
    check_disjoint,
    check_training_seed,
    evaluation_seeds,
    training_env_seed,
)
from der_ros.train.runner import train

ROOT = Path(__file__).resolve().parents[2]
CARTPOLE = ROOT / "config" / "cartpole.yaml"


def _small(steps: int, **extra: object) -> dict[str, object]:
    return {
        "agent.hidden_sizes": [32], "agent.batch_size": 32, "agent.learning_starts": 100,
        "agent.epsilon_decay_steps": 300, "agent.target_update_interval": 50, "replay.capacity": 2000,
        "replay.h2_capacity": 320, "replay.kind": "der", "replay.lam": 0.5, "train.total_steps": steps,
        "train.log_interval": 50, "train.tensorboard": False, "train.progress": False, "train.eval_interval": 0,
        **extra,
    }  # fmt: skip


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_evaluation_seeds_are_disjoint_from_training_seeds() -> None:
    report, tuning = evaluation_seeds(300), evaluation_seeds(300, TUNING_EVAL_SEED_BASE)
    assert report[0] == EVAL_SEED_BASE and len(set(report)) == 300 and not set(report) & set(tuning)
    check_disjoint(range(0, 2000), report + tuning)
    with pytest.raises(ValueError, match="also training seeds"):
        check_disjoint([EVAL_SEED_BASE + 3], report)
    with pytest.raises(ValueError, match="training range"):
        check_disjoint([1], [5])
    with pytest.raises(ConfigError, match="reserved for evaluation"):
        check_training_seed(TRAINING_SEED_LIMIT)
    with pytest.raises(ConfigError, match="eval_seed_base"):
        evaluation_seeds(10, base=12345)
    # a resumed run's environment seed stays in the training range
    assert all(0 <= training_env_seed(s, step) < TRAINING_SEED_LIMIT for s in (0, 7, 999_999_999) for step in (1, 10**6))
    with pytest.raises(ConfigError, match=r"\[train\]: seed = 1000000000"):
        load_experiment_config(CARTPOLE, {"train.seed": EVAL_SEED_BASE})


def test_episodes_do_not_depend_on_how_many_envs_run_them() -> None:
    def policy(obs: np.ndarray, infos: object) -> list[int]:
        return [int(o[2] > 0) for o in obs]  # a weak CartPole rule: returns vary with the seed

    results = []
    for n_envs in (1, 3):
        envs = [make_env("CartPole-v1", seed=0) for _ in range(n_envs)]
        results.append(run_episodes(policy, envs, evaluation_seeds(4), episodes=7, episodes_per_seed=2))
        for env in envs:
            env.close()
    one, three = results
    assert [(e.stream, e.seed, e.ret, e.length) for e in one] == [(e.stream, e.seed, e.ret, e.length) for e in three]
    assert [e.seed is not None for e in one] == [True, False] * 3 + [True]  # streams of 2: seeded + follow-up
    assert len({e.ret for e in one}) > 1


@pytest.mark.slow
def test_evaluation_leaves_training_unchanged_and_is_written(tmp_path: Path) -> None:
    """Evaluations never touch the training env or the agent's RNGs: same training with or without them."""
    with_eval = train(load_experiment_config(CARTPOLE, _small(400, **{"train.eval_interval": 200,
                                                                      "train.eval_episodes": 5,
                                                                      "train.final_eval_episodes": 8})),
                      run_dir=tmp_path / "eval")  # fmt: skip
    without = train(load_experiment_config(CARTPOLE, _small(400, **{"train.final_eval_episodes": 0})),
                    run_dir=tmp_path / "plain")  # fmt: skip
    ep_a = [(r["episode"], r["step"], r["return"]) for r in _rows(tmp_path / "eval" / "episodes.csv")]
    ep_b = [(r["episode"], r["step"], r["return"]) for r in _rows(tmp_path / "plain" / "episodes.csv")]
    assert ep_a == ep_b
    loss = lambda d: [r["value"] for r in _rows(tmp_path / d / "metrics.csv") if r["name"] == "losses/td_loss"]  # noqa: E731
    assert loss("eval") == loss("plain")
    ev = read_evaluations(tmp_path / "eval" / "evaluations.csv")
    assert ev["step"].tolist() == [0, 200, 400] and ev["episodes"].tolist() == [5, 5, 8]
    final = json.loads((tmp_path / "eval" / "evaluation.json").read_text())
    assert final["step"] == 400 and len(final["episodes"]) == 8
    assert all(s >= EVAL_SEED_BASE for s in final["seeds"])
    check_disjoint([3], final["seeds"])
    assert with_eval.eval_return == pytest.approx(final["summary"]["mean_return"])
    assert not (tmp_path / "plain" / "evaluation.json").exists() and np.isnan(without.eval_return)


@pytest.mark.slow
def test_resumed_run_redoes_no_evaluation_and_matches_the_full_run(tmp_path: Path) -> None:
    extra = {"train.eval_interval": 100, "train.eval_episodes": 3, "train.final_eval_episodes": 4}
    train(load_experiment_config(CARTPOLE, _small(300, **extra)), run_dir=tmp_path / "full")
    train(load_experiment_config(CARTPOLE, _small(200, **extra)), run_dir=tmp_path / "split")
    # the first part ended at 200 with a final evaluation there; the resumed run drops it and continues
    train(load_experiment_config(CARTPOLE, _small(300, **extra)), run_dir=tmp_path / "split",
          resume=tmp_path / "split" / "checkpoint.pt")  # fmt: skip
    full = read_evaluations(tmp_path / "full" / "evaluations.csv")
    split = read_evaluations(tmp_path / "split" / "evaluations.csv")
    for key in ("step", "episodes", "mean_return"):
        assert full[key].tolist() == split[key].tolist()


@pytest.mark.slow
def test_the_evaluation_process_exits_when_its_trainer_is_killed(tmp_path: Path) -> None:
    """A SIGKILLed training process leaves no evaluation process behind (it polls its parent)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "trainer.py"
    script.write_text(
        "import sys, time\n"
        "from der_ros.train.config import EnvConfig\n"
        "from der_ros.train.evaluation import make_evaluator\n"
        "if __name__ == '__main__':  # spawn runs this file again in the worker\n"
        "    ev = make_evaluator(EnvConfig(id='CartPole-v1'), (4,), 'float32', 2, 'mlp', [8], 1, 1_000_000_000,\n"
        "                        mode='process')\n"
        "    print(ev._proc.pid, flush=True)\n"
        "    time.sleep(600)\n"
    )
    err = tmp_path / "stderr.txt"  # inherited by the resource tracker and the worker too
    with err.open("w") as err_file:
        proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=err_file, text=True)
    child = int(proc.stdout.readline())
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            break
        time.sleep(0.2)
    else:
        os.kill(child, signal.SIGKILL)
        raise AssertionError("the evaluation process outlived its killed trainer by 30 s")
    # issue 45: no "resource_tracker: There appear to be 6 leaked semaphore objects" on the terminal. The
    # tracker writes it when it sees its pipe close (the trainer's death), before the worker notices it.
    assert "leaked semaphore" not in err.read_text() and "Traceback" not in err.read_text(), err.read_text()


@pytest.mark.slow  # starts an evaluator process (~5 s idle): full run only
def test_the_process_evaluator_gives_the_inline_results_over_pipes() -> None:
    """Jobs larger than a pipe's buffer (a 1 MB network) queue up; results come back in order."""
    from der_ros.agent.config import DQNConfig
    from der_ros.agent.dqn import DQNAgent
    from der_ros.replay.config import ReplayConfig
    from der_ros.train.config import EnvConfig
    from der_ros.train.eval_policies import net_state
    from der_ros.train.evaluation import make_evaluator

    agent = DQNAgent((4,), np.float32, 2, DQNConfig(hidden_sizes=(512, 512), batch_size=8), ReplayConfig(capacity=64),
                     seed=5)
    state = net_state(agent.q_net)
    assert sum(v.nbytes for v in state.values()) > 1_000_000
    results = {}
    for mode in ("process", "inline"):
        ev = make_evaluator(EnvConfig(id="CartPole-v1"), (4,), np.float32, 2, "mlp", [512, 512], 1,
                            TUNING_EVAL_SEED_BASE, mode=mode)  # fmt: skip
        try:
            for step in (0, 10, 20):
                ev.submit(step, state, 2)
            results[mode] = [r.to_json() for r in ev.finish()]
        finally:
            ev.close()
    assert [r["step"] for r in results["process"]] == [0, 10, 20]
    same = lambda r: {k: v for k, v in r.items() if k != "wall_s"} | {"summary": {  # noqa: E731
        k: v for k, v in r["summary"].items() if k != "wall_s"}}
    assert [same(r) for r in results["process"]] == [same(r) for r in results["inline"]]


class _ScriptedEnv:
    """An env whose episodes end as scripted: (outcome, info time_to_success, info imposed_brake) per episode."""

    def __init__(self, script: list[tuple[str, float | None, float]]) -> None:
        self.script, self.k = script, -1
        self.unwrapped = self

    def reset(self, seed: int | None = None) -> tuple[np.ndarray, dict[str, object]]:
        self.k += 1
        return np.zeros(2, dtype=np.float32), {}

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, object]]:
        event, tts, brake = self.script[self.k]
        info = {"event": event, "caused": event == "collision", "time_to_success": tts, "imposed_brake": brake}
        return np.zeros(2, dtype=np.float32), 1.0, event == "collision", event != "collision", info

    def close(self) -> None:
        pass


def test_episodes_carry_time_to_success_and_imposed_braking(tmp_path: Path) -> None:
    """Success at what cost to others (issue 44): the env's last info per episode; a time to success only for
    an episode that ended in success (a collision after the goal was reached has none); means in the summary
    and in evaluation.json; results written before the metrics load as unmeasured (None / NaN), never 0."""
    from der_ros.train.eval_result import EvalResult

    script = [("success", 6.5, 4.0), ("collision", 3.0, 9.0), ("time_limit", None, 0.0), ("success", 2.5, 1.0)]
    env = _ScriptedEnv(script)
    eps = run_episodes(lambda obs, infos: [0] * len(obs), [env], evaluation_seeds(4), episodes=4)
    assert [(e.outcome, e.time_to_success, e.imposed_brake) for e in eps] == [
        ("success", 6.5, 4.0), ("collision", None, 9.0), ("time_limit", None, 0.0), ("success", 2.5, 1.0)]
    res = EvalResult(step=7, episodes=eps, seeds=evaluation_seeds(4))
    assert res.summary()["time_to_success"] == pytest.approx(4.5)  # (6.5 + 2.5) / 2 successes
    assert res.summary()["imposed_brake"] == pytest.approx(3.5)  # (4 + 9 + 0 + 1) / 4 episodes
    saved = json.loads(res.save(tmp_path / "evaluation.json").read_text())
    assert [e["time_to_success"] for e in saved["episodes"]] == [6.5, None, None, 2.5]
    assert saved["summary"]["imposed_brake"] == pytest.approx(3.5)
    back = EvalResult.load(tmp_path / "evaluation.json")
    assert back.mean_time_to_success == pytest.approx(4.5) and back.episodes[1].imposed_brake == 9.0
    for e in saved["episodes"]:  # an evaluation.json from before the metrics
        del e["time_to_success"], e["imposed_brake"]
    old = EvalResult.from_json(saved)
    assert old.episodes[0].time_to_success is None and old.episodes[0].imposed_brake is None
    assert np.isnan(old.mean_time_to_success) and np.isnan(old.mean_imposed_brake)
    # envs without the metrics (gymnasium's): unmeasured as well
    cart = [make_env("CartPole-v1", seed=0)]
    plain = EvalResult(step=0, episodes=run_episodes(lambda obs, infos: [0] * len(obs), cart, evaluation_seeds(1), 1))
    cart[0].close()
    assert plain.episodes[0].imposed_brake is None and np.isnan(plain.summary()["imposed_brake"])

"""Benchmark: the ROS 2 lockstep graph against the same training loop in one process.

Runs, on the ring scenario with the agent/replay settings of ``config/graph.params.yaml``:

1. ``inprocess``: ``LaneChangeEnv`` + ``DQNAgent`` in one Python process (act, step, observe,
   learn), no ROS: the peer.
2. ``graph``: ``bridge_node`` and ``agent_node`` as two processes in lockstep over Fast DDS
   (localhost only, a private ``ROS_DOMAIN_ID``); the bridge runs ``max_steps`` steps, logs its
   summary (steps/s, round-trip percentiles measured in the bridge: state published -> the
   command answering it received) and exits.
3. ``graph_eval``: the same graph with the agent in evaluation mode (acting only, no learning),
   which isolates the transport + executor round trip from the gradient step.
4. ``graph_no_markers``: the training graph with the bridge's scene markers off (``markers:=false``;
   on by default: every vehicle on ``scene/vehicles`` each step), run next to the training
   graph, so the two differ only in the markers: what the scene costs the graph. First of all, in
   one process, the marker work itself: env steps with and without the scene's subscriptions, and
   ``env.scene()`` + encoding per step (``scene_*``).

``--safety`` also runs the training graph (markers on) with the safety node between agent and
bridge (``der graph --safety rss``, the default of ``der graph``), alternating with the graph
without it in each pair: ``safety_*`` figures (steps/s, ratio to in-process, round trip, which then
includes the safety node's hop) and ``safety_cost_pairs`` (1 - with/without, within each pair). The RSS
shield changes the episodes (a vetoed change is a keep, so episodes are longer and steps cheaper), so
its steps/s are not the hop's cost; for that each pair also runs the safety node with
``safety.kind: none`` (it passes every command, the agent's commands are the unshielded graph's):
``safety_passthrough_*`` and ``safety_hop_cost_pairs`` (1 - pass-through/without).

``--record`` adds the recorder node (all default topics, so the markers too when they are on) to
both training graphs: the cost of recording them as well (a third process on two cores).

The in-process loop calls the learner in the node's order (observe, act, then learn), with the
params file's scenario and seeds, so both runs make the same decisions: ``graph_episodes`` and
``inprocess_episodes`` agree when no command timed out.

Ends with one JSON line: graph_steps_per_s, inprocess_steps_per_s, graph_ratio,
roundtrip_p50_ms, roundtrip_p99_ms (training graph, markers on), the same for the graph without
markers (no_markers_*), eval_roundtrip_p50_ms/p99_ms, the eval graph's steps/s, episode counts.
Targets: graph >= 0.85x in-process (issue 11; >= 0.6x before it), round-trip p50 <= 1 ms.

``--pairs N`` runs the in-process loop and the graphs without and with markers N times each, the
graphs in ABBA order (off-on, on-off, ...), and reports the median run of each (``graph_ratio``:
median graph over median in-process; ``graph_ratio_pairs`` within each pair) and the markers' cost
within each pair (``markers_cost_pairs``: 1 - on/off; one pair on a loaded machine can be off by 30%
either way).

    .venv/bin/python bench/graph.py [--steps 3000] [--quick] [--record] [--pairs N]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PARAMS_FILE = REPO / "config" / "graph.params.yaml"


def _agent_config(overrides: dict) -> tuple:
    """DQNConfig, ReplayConfig and seed of the agent node section of the params file (+ overrides)."""
    import yaml

    from der_ros.agent.config import DQNConfig
    from der_ros.configuration import from_dict, unflatten_names
    from der_ros.replay.config import ReplayConfig

    values = dict(yaml.safe_load(PARAMS_FILE.read_text())["agent_node"]["ros__parameters"])
    values.update(overrides)
    agent = from_dict(DQNConfig, unflatten_names(values, "agent"))
    replay = from_dict(ReplayConfig, unflatten_names(values, "replay"))
    return agent, replay, int(values.get("seed", 0))


def _scenario_config() -> object:
    """The bridge's ScenarioConfig from the params file (the graph runs exactly this scenario)."""
    import yaml

    from der_ros.configuration import from_dict, unflatten_names
    from sumo_bridge.scenario import ScenarioConfig

    values = yaml.safe_load(PARAMS_FILE.read_text())["bridge_node"]["ros__parameters"]
    scenario = {k: v for k, v in values.items() if k.startswith("scenario.")}
    return from_dict(ScenarioConfig, unflatten_names(scenario, "scenario"))


def run_inprocess(steps: int, overrides: dict) -> tuple[float, int]:
    """Steps/s and episodes of the plain training loop (act -> env.step -> observe -> learn)."""
    import numpy as np
    import torch

    torch.set_num_threads(1)
    from der_ros.agent.dqn import DQNAgent
    from sumo_bridge.lane_change_env import LaneChangeEnv

    dqn_cfg, replay_cfg, seed = _agent_config(overrides)
    env = LaneChangeEnv(_scenario_config())
    obs, _ = env.reset()
    agent = DQNAgent(obs.shape, np.float32, int(env.action_space.n), dqn_cfg, replay_cfg, seed=seed)
    # Same order of calls as the agent node (der_ros.agent.online + agent_node): observe the
    # transition, act on the new state, then learn (the node publishes before it learns); at a
    # terminal state learn, then reset and act on the first state of the next episode.
    episodes = 1
    a = agent.act(obs)
    t0 = time.perf_counter()
    for _ in range(steps):
        next_obs, r, term, trunc, _ = env.step(a)
        agent.observe(obs, a, r, next_obs, term, trunc)
        if term or trunc:
            agent.learn()
            obs, _ = env.reset()
            episodes += 1
            a = agent.act(obs)
        else:
            obs = next_obs
            a = agent.act(obs)
            agent.learn()
    rate = steps / (time.perf_counter() - t0)
    env.close()
    return rate, episodes


def scene_cost(steps: int, network: str = "ring") -> dict:
    """The bridge's marker work per decision step, in one process: env steps with the scene's position
    subscriptions vs without (SUMO side), and ``env.scene()`` + the CDR encoding (what the bridge adds
    per published state). The two envs alternate in blocks of 50 steps (one libsumo env at a time);
    medians over blocks, so a burst of load on the shared machine does not decide the figure."""
    import statistics

    from der_ros.contract import vehicle_markers_cdr
    from sumo_bridge.lane_change_env import LaneChangeEnv
    from sumo_bridge.scenario import ScenarioConfig

    cfg = (ScenarioConfig.ring if network == "ring" else ScenarioConfig.urban)(max_episode_steps=50)
    blocks: dict[str, list[float]] = {"off": [], "on": [], "markers": []}
    vehicles = 0
    for block in range(max(2, steps // 50)):
        mode = "on" if block % 2 else "off"
        env = LaneChangeEnv(cfg)
        if mode == "on":
            env.enable_scene()
        env.reset(seed=1_000_000_000 + block // 2)
        stepping = marking = 0.0
        for k in range(50):
            t0 = time.perf_counter()
            env.step(0)  # 50 decisions = one episode: no reset inside the block
            t1 = time.perf_counter()
            stepping += t1 - t0
            if mode == "on":
                scene = env.scene()
                vehicle_markers_cdr(scene.vehicles, scene.removed, k, "map")
                marking += time.perf_counter() - t1
                vehicles = len(scene.vehicles)
        env.close()
        blocks[mode].append(stepping / 50)
        if mode == "on":
            blocks["markers"].append(marking / 50)
    us = {k: round(1e6 * statistics.median(v), 1) for k, v in blocks.items()}
    return {"env_step_us_scene_off": us["off"], "env_step_us_scene_on": us["on"], "markers_us_per_step": us["markers"],
            "vehicles": vehicles}


def _param_args(params: dict) -> list[str]:
    out = []
    for k, v in params.items():
        text = json.dumps(v) if isinstance(v, (list, bool)) else str(v)
        if isinstance(v, bool):
            text = "true" if v else "false"
        out += ["-p", f"{k}:={text}"]
    return out


def run_graph(steps: int, agent_overrides: dict, evaluate: bool, workdir: Path, markers: bool = True,
              record: bool = False, safety: str | None = None) -> dict:  # fmt: skip
    """Start (recorder +) agent (+ safety node) + bridge, wait for the bridge to finish, return its summary."""
    from der_ros.graph.graph_cli import AGENT_REMAP
    from der_ros.graph.supervisor import reserve_domain_id

    lease = reserve_domain_id()  # same lock files as the test harness: never a shared domain
    env = dict(os.environ, ROS_DOMAIN_ID=str(lease.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    agent_params = {**agent_overrides, "evaluate": evaluate, "checkpoint_out": str(workdir / "agent.pt")}
    procs = []
    tag = ("_eval" if evaluate else "") + ("" if markers else "_no_markers") + ("_record" if record else "")
    tag += f"_safety_{safety}" if safety else ""
    try:
        agent_log = open(workdir / f"agent{tag}.log", "wb")  # noqa: SIM115
        bridge_log_path = workdir / f"bridge{tag}.log"
        bridge_log = open(bridge_log_path, "wb")  # noqa: SIM115
        base = [sys.executable, "-m"]
        ros = ["--ros-args", "--params-file", str(PARAMS_FILE)]
        bridge_params = {"max_steps": steps, "command_timeout": 5.0, "markers": markers}
        if record:
            rec_log = open(workdir / f"recorder{tag}.log", "wb")  # noqa: SIM115
            procs.append(subprocess.Popen(
                base + ["der_ros.nodes.recorder_node"] + ros + _param_args({"output": str(workdir / f"bag{tag}")}),
                env=env, stdout=rec_log, stderr=subprocess.STDOUT, start_new_session=True))  # fmt: skip
            bridge_params["min_subscribers"] = 2  # agent and recorder, as der graph does
        remap = ["-r", AGENT_REMAP] if safety else []
        procs.append(subprocess.Popen(base + ["der_ros.nodes.agent_node"] + ros + remap + _param_args(agent_params),
                                      env=env, stdout=agent_log, stderr=subprocess.STDOUT, start_new_session=True))
        if safety:
            safety_log = open(workdir / f"safety{tag}.log", "wb")  # noqa: SIM115
            procs.append(subprocess.Popen(base + ["der_ros.nodes.safety_node"] + ros + _param_args({"safety.kind": safety}),
                                          env=env, stdout=safety_log,
                                          stderr=subprocess.STDOUT, start_new_session=True))  # fmt: skip
        bridge = subprocess.Popen(
            base + ["der_ros.nodes.bridge_node"] + ros + _param_args(bridge_params),
            env=env, stdout=bridge_log, stderr=subprocess.STDOUT, start_new_session=True)
        procs.append(bridge)
        code = bridge.wait(timeout=60 + steps / 20)
        text = bridge_log_path.read_text()
        if code != 0:
            raise RuntimeError(f"bridge exited {code}:\n{text[-3000:]}")
        match = re.search(r"bridge summary: (\{.*\})", text)
        if match is None:
            raise RuntimeError(f"no bridge summary:\n{text[-3000:]}")
        return json.loads(match.group(1))
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
                try:
                    p.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait()
        lease.release()


def _median_run(runs: list[dict]) -> dict:
    """The run with the median steps/s (its own round trip and busy fraction come with it)."""
    return sorted(runs, key=lambda r: r["steps_per_s"])[len(runs) // 2]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000, help="environment steps per run")
    parser.add_argument("--quick", action="store_true", help="600 steps, small learning_starts (smoke run)")
    parser.add_argument("--record", action="store_true", help="run the recorder node in both training graphs too")
    parser.add_argument("--safety", action="store_true",
                        help="also the training graph with the safety node in the loop, in each pair (safety_*)")
    parser.add_argument("--pairs", type=int, default=1,
                        help="training graphs without / with markers, alternately, this many times each (medians "
                        "reported; on a shared machine one pair can differ by 30%% either way)")
    args = parser.parse_args()
    steps = 600 if args.quick else args.steps
    overrides = {"agent.learning_starts": 100} if args.quick else {}
    workdir = Path(tempfile.mkdtemp(prefix="der_bench_graph_"))
    scene = scene_cost(400 if args.quick else 1000)
    print(f"scene markers in one process (ring): {json.dumps(scene)}", file=sys.stderr)
    plains, graphs, inprocs, shielded, unshielded, passthrough = [], [], [], [], [], []
    inproc_episodes = 0
    for pair in range(max(1, args.pairs)):
        pair_dir = workdir / f"pair{pair}"
        pair_dir.mkdir()
        # the peer once per pair too: one in-process run moved 465-620 steps/s between sessions
        rate, inproc_episodes = run_inprocess(steps, overrides)
        inprocs.append(rate)
        print(f"in-process: {rate:.1f} steps/s, {inproc_episodes} episodes", file=sys.stderr)
        # off-on, on-off, off-on, ...: neither variant always runs first (ABBA order)
        for markers in (False, True) if pair % 2 == 0 else (True, False):
            run = run_graph(steps, overrides, evaluate=False, workdir=pair_dir, markers=markers, record=args.record)
            (graphs if markers else plains).append(run)
            print(f"graph (training, markers {'on' if markers else 'off'}): {json.dumps(run)}", file=sys.stderr)
        if args.safety:  # without, with a pass-through and with the RSS safety node; order rotates per pair
            kinds: list[str | None] = [None, "none", "rss"]
            for kind in kinds[pair % 3:] + kinds[:pair % 3]:
                run = run_graph(steps, overrides, evaluate=False, workdir=pair_dir, record=args.record, safety=kind)
                {None: unshielded, "none": passthrough, "rss": shielded}[kind].append(run)
                print(f"graph (training, safety node {kind or 'off'}): {json.dumps(run)}", file=sys.stderr)
    plain, graph = _median_run(plains), _median_run(graphs)
    inproc = sorted(inprocs)[len(inprocs) // 2]
    graph_eval = run_graph(steps, overrides, evaluate=True, workdir=workdir)
    print(f"graph (evaluation mode): {json.dumps(graph_eval)}", file=sys.stderr)
    result = {
        "bench": "graph",
        "steps": steps,
        "graph_steps_per_s": round(graph["steps_per_s"], 1),
        "inprocess_steps_per_s": round(inproc, 1),
        "inprocess_steps_per_s_runs": [round(r, 1) for r in inprocs],
        "graph_ratio_pairs": [round(g["steps_per_s"] / r, 3) for g, r in zip(graphs, inprocs)],
        "graph_ratio": round(graph["steps_per_s"] / inproc, 3),
        "roundtrip_p50_ms": round(graph["roundtrip_p50_ms"], 3),
        "roundtrip_p99_ms": round(graph["roundtrip_p99_ms"], 3),
        "timeouts": graph["commands/timeouts"],
        "recorder": args.record,
        "pairs": len(graphs),
        "graph_steps_per_s_runs": [round(r["steps_per_s"], 1) for r in graphs],
        "no_markers_graph_steps_per_s_runs": [round(r["steps_per_s"], 1) for r in plains],
        "no_markers_graph_steps_per_s": round(plain["steps_per_s"], 1),
        "no_markers_graph_ratio": round(plain["steps_per_s"] / inproc, 3),
        "no_markers_roundtrip_p50_ms": round(plain["roundtrip_p50_ms"], 3),
        "markers_cost": round(1.0 - graph["steps_per_s"] / plain["steps_per_s"], 3),
        "markers_cost_pairs": [round(1.0 - on["steps_per_s"] / off["steps_per_s"], 3) for off, on in zip(plains, graphs)],
        "bridge_busy_fraction_no_markers": round(plain["busy_fraction"], 3),
        **{f"scene_{k}": v for k, v in scene.items()},
        "graph_episodes": int(graph["episodes_started"]),
        "inprocess_episodes": inproc_episodes,
        "graph_bridge_busy_fraction": round(graph["busy_fraction"], 3),
        # of which the env step and publishing the step (older bridges do not report them: NaN)
        "graph_bridge_env_step_fraction": round(graph.get("env_step_fraction", float("nan")), 3),
        "graph_bridge_publish_fraction": round(graph.get("publish_fraction", float("nan")), 3),
        "eval_graph_steps_per_s": round(graph_eval["steps_per_s"], 1),
        "eval_roundtrip_p50_ms": round(graph_eval["roundtrip_p50_ms"], 3),
        "eval_roundtrip_p99_ms": round(graph_eval["roundtrip_p99_ms"], 3),
        "logs": str(workdir),
    }
    if shielded:
        safe = _median_run(shielded)
        result.update({
            "safety_graph_steps_per_s": round(safe["steps_per_s"], 1),
            "safety_graph_ratio": round(safe["steps_per_s"] / inproc, 3),
            "safety_roundtrip_p50_ms": round(safe["roundtrip_p50_ms"], 3),
            "safety_roundtrip_p99_ms": round(safe["roundtrip_p99_ms"], 3),
            "safety_timeouts": safe["commands/timeouts"],
            "safety_off_roundtrip_p50_ms": round(_median_run(unshielded)["roundtrip_p50_ms"], 3),
            "safety_cost_pairs": [round(1.0 - on["steps_per_s"] / off["steps_per_s"], 3)
                                  for on, off in zip(shielded, unshielded)],
            "safety_episodes": int(safe["episodes_started"]),
            "safety_off_episodes": int(_median_run(unshielded)["episodes_started"]),
            "safety_off_graph_steps_per_s": round(_median_run(unshielded)["steps_per_s"], 1),
            "safety_passthrough_graph_steps_per_s": round(_median_run(passthrough)["steps_per_s"], 1),
            "safety_passthrough_episodes": int(_median_run(passthrough)["episodes_started"]),
            "safety_passthrough_roundtrip_p50_ms": round(_median_run(passthrough)["roundtrip_p50_ms"], 3),
            "safety_passthrough_roundtrip_p99_ms": round(_median_run(passthrough)["roundtrip_p99_ms"], 3),
            "safety_hop_cost_pairs": [round(1.0 - on["steps_per_s"] / off["steps_per_s"], 3)
                                      for on, off in zip(passthrough, unshielded)],
        })  # fmt: skip
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())

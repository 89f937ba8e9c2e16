"""Why did a shielded agent cause a collision on the exit? Replays episodes and names the cause (diagnosis only).

docs/safety.md, "The exit table's caused collisions". For each run directory (config.yaml + checkpoint.pt +
evaluation.json) the episodes its evaluation marked ``caused`` are replayed in process with the run's greedy
policy behind the run's own shield (a seeded reset is a pure function of the seed), or, with ``--seeds``, the
episodes named there (e.g. tuning seeds). At every decision the script keeps the ego's lane, speed and distance
to the split and every vehicle on the approach (lane, position, speed); at the end SUMO's collision record names
the other vehicle. The cause, from where that vehicle was at the decision of the ego's last lane change:

* ``C``: two lanes beyond the ego's lane, on the side of the change (it changed into the same lane in the step);
* ``leader``: ahead of the ego on the lane the ego changed into (then its own lane), the ego ran into it;
* ``unobserved follower``: behind on the target lane, farther than the neighbour range (30 m of gap);
* ``observed follower``: behind on the target lane, within the range;
* ``other``: anything else (printed in full).

Diagnosis only: report episodes are read, never used to choose anything.

    python research/exit/diagnose_caused.py RUN_DIR [RUN_DIR ...] [--seeds S ...] [--beyond-lane] [--json F]
    python research/exit/diagnose_caused.py RUN_DIR --seeds S --trace DECISION [--release]   # SUMO step by step
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from der_ros.agent.dqn import DQNAgent
from der_ros.train.config import load_experiment_config
from der_ros.train.envs import make_env_from_config
from der_ros.train.eval_policies import GreedyQPolicy
from sumo_bridge.observation import field_index

SPEED, GAP, LANE = field_index("speed"), field_index("gap"), field_index("lane")
RANGE = 30.0  # the observation's neighbour range (m of gap)


def _vehicles(api: Any, edge: str) -> dict[str, tuple[int, float, float, float]]:
    """id -> (lane index, position, speed, length) of every vehicle on ``edge``."""
    out = {}
    for vid in api.edge.getLastStepVehicleIDs(edge):
        out[vid] = (int(api.vehicle.getLaneIndex(vid)), float(api.vehicle.getLanePosition(vid)),
                    float(api.vehicle.getSpeed(vid)), float(api.vehicle.getLength(vid)))
    return out


def replay(env: Any, policy: GreedyQPolicy, seed: int) -> dict[str, Any]:
    """One episode: per-decision records and SUMO's collisions of the ego."""
    obs, info = env.reset(seed=seed)
    inner = env.unwrapped
    api, edge = inner.api, "approach"
    log: list[dict[str, Any]] = []
    done = False
    while not done:
        ego = inner.ego_id
        pts = info["points"]
        cars = _vehicles(api, edge)
        a = int(policy(obs[None], [info])[0])
        mask = info.get("action_mask")
        obs, _r, term, trunc, info = env.step(a)
        done = term or trunc
        log.append({"ego": ego, "lane": int(pts[0, LANE]), "speed": float(pts[0, SPEED]),
                    "to_split": float(pts[0, GAP]), "proposed": a, "applied": int(info.get("applied_action", a)),
                    "mask": None if mask is None else [bool(m) for m in mask], "cars": cars, "points": pts.copy()})
    collisions = [(c.collider, c.victim, c.type, c.lane, float(c.pos)) for c in api.simulation.getCollisions()]
    return {"seed": seed, "event": info.get("event"), "caused": bool(info.get("caused")), "log": log,
            "collisions": collisions, "end_cars": _vehicles(api, edge), "end_ego": log[-1]["ego"] if log else None}


def classify(rec: dict[str, Any]) -> dict[str, Any]:
    """The cause of the ego's collision in ``rec`` (see the module docstring)."""
    log = rec["log"]
    ego = rec["end_ego"]
    mine = [c for c in rec["collisions"] if ego in (c[0], c[1])]
    if not mine:
        return {"cause": "no collision in the replay", "detail": rec["event"]}
    collider, victim, kind, lane_id, pos = mine[0]
    other = victim if collider == ego else collider
    changes = [i for i, d in enumerate(log) if d["applied"] in (1, 2)]
    if not changes:
        return {"cause": "other", "detail": f"no lane change; {kind} with {other}"}
    k = changes[-1]
    d = log[k]
    offset = 1 if d["applied"] == 1 else -1
    target = d["lane"] + offset
    me = d["cars"].get(ego)
    you = d["cars"].get(other)
    row = {"decision": k, "of": len(log), "from_lane": d["lane"], "to_lane": target, "ego_speed": round(d["speed"], 1),
           "to_split": round(d["to_split"], 1), "kind": kind, "ego_role": "collider" if collider == ego else "victim",
           "other": other, "changes": [(i, log[i]["lane"], "L" if log[i]["applied"] == 1 else "R") for i in changes]}
    # the ego's speed over the decisions after the change (m/s) and its mean deceleration there
    speeds = [round(x["speed"], 1) for x in log[k:]]
    row["ego_speeds_after"] = speeds
    if you is None or me is None:
        row["cause"] = "other"
        row["detail"] = "the other vehicle was not on the approach at the change"
        return row
    lane_o, pos_o, v_o, len_o = you
    _lane_e, pos_e, _v_e, len_e = me
    gap = (pos_o - len_o - pos_e) if pos_o > pos_e else (pos_e - len_e - pos_o)
    row.update(other_lane=lane_o, other_speed=round(v_o, 1), other_gap=round(gap, 1),
               other_ahead=bool(pos_o > pos_e))
    if lane_o == target + offset:
        row["cause"] = "C"
    elif lane_o == target and pos_o > pos_e:
        row["cause"] = "leader"
    elif lane_o == target:
        row["cause"] = "unobserved follower" if gap > RANGE else "observed follower"
    else:
        row["cause"] = "other"
    return row


def trace(env: Any, policy: GreedyQPolicy, seed: int, decision: int, release: bool, steps: int = 30) -> None:
    """Replay to ``decision`` (the last lane change, from the table), apply it by hand and print the ego's speed,
    acceleration and leader gap at every SUMO step after it. ``release``: first drop the ego's TraCI speed
    command (``setSpeed(-1)``), so that SUMO's car-following alone sets the speed."""
    obs, info = env.reset(seed=seed)
    for _ in range(decision):
        obs, _r, _te, _tr, info = env.step(int(policy(obs[None], [info])[0]))
    inner = env.unwrapped
    api, ego = inner.api, inner.ego_id
    a = int(policy(obs[None], [info])[0])
    print(f"decision {decision}: action {a}, speed mode {api.vehicle.getSpeedMode(ego)}, decel "
          f"{api.vehicle.getDecel(ego)}, emergencyDecel {api.vehicle.getEmergencyDecel(ego)}, release {release}")
    if release:
        api.vehicle.setSpeed(ego, -1.0)
    if a in (1, 2):
        api.vehicle.changeLane(ego, api.vehicle.getLaneIndex(ego) + (1 if a == 1 else -1), 0.1)
    for t in range(steps):
        api.simulationStep()
        lead = api.vehicle.getLeader(ego, 100.0)
        hit = any(ego in (c.collider, c.victim) for c in api.simulation.getCollisions())
        gap = f"{lead[1]:.2f} m to {lead[0]} at {api.vehicle.getSpeed(lead[0]):.2f} m/s" if lead and lead[0] else "-"
        print(f"  step {t + 1}: lane {api.vehicle.getLaneID(ego)}, speed {api.vehicle.getSpeed(ego):.2f} m/s, "
              f"accel {api.vehicle.getAcceleration(ego):.2f} m/s^2, leader {gap}{', COLLISION' if hit else ''}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--seeds", nargs="*", type=int, default=None, help="replay these seeds instead of the caused ones")
    ap.add_argument("--beyond-lane", action="store_true", help="the run's shield with beyond_lane on")
    ap.add_argument("--trace", type=int, default=None, metavar="DECISION",
                    help="with one run and one --seeds: print SUMO step by step after this decision's lane change")
    ap.add_argument("--release", action="store_true", help="with --trace: drop the ego's TraCI speed command first")
    ap.add_argument("--json", type=Path, default=None, help="write the rows (with the applied actions) here")
    args = ap.parse_args()
    rows = []
    for run in args.runs:
        cfg = load_experiment_config(run / "config.yaml")
        seeds = args.seeds
        if seeds is None:
            ev = json.loads((run / "evaluation.json").read_text())
            seeds = [e["seed"] for e in ev["episodes"] if e["caused"]]
        agent = DQNAgent.load(run / "checkpoint.pt")
        agent.q_net.eval()
        policy = GreedyQPolicy(agent.q_net, np.float32, use_mask=cfg.env.safety.mode == "mask")
        env_cfg = cfg.env
        if args.beyond_lane:
            env_cfg = dataclasses.replace(env_cfg, safety=dataclasses.replace(env_cfg.safety, beyond_lane=True))
        env = make_env_from_config(env_cfg, int(seeds[0]) if seeds else 0)
        try:
            if args.trace is not None:
                trace(env, policy, int(seeds[0]), args.trace, args.release)
                return
            for s in seeds:
                rec = replay(env, policy, s)
                row = {"run": f"{run.parent.name}/{run.name}", "seed": s, "event": rec["event"],
                       "caused": rec["caused"], **classify(rec), "actions": [d["applied"] for d in rec["log"]]}
                rows.append(row)
                print(json.dumps(row), flush=True)
        finally:
            env.close()
    print()
    print("| run | seed | event | last change | speed (m/s) | to split (m) | other: lane, speed, gap at the change | "
          "SUMO | cause |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "to_lane" not in r:
            print(f"| {r['run']} | {r['seed']} | {r['event']} | – | – | – | – | – | {r['cause']} |")
            continue
        where = "ahead" if r.get("other_ahead") else "behind"
        other = (f"lane {r['other_lane']}, {r['other_speed']}, {r['other_gap']} m {where}"
                 if "other_lane" in r else "–")
        print(f"| {r['run']} | {r['seed']} | {r['event']}{'' if r['caused'] else ' (not caused)'} | "
              f"{r['from_lane']} -> {r['to_lane']} (decision {r['decision']} of {r['of']}) | {r['ego_speed']} | "
              f"{r['to_split']} | {other} | {r['kind']}, ego {r['ego_role']} | {r['cause']} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()

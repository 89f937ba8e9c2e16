"""Transitions (s, a, r, s', terminated, truncated) rebuilt from a recorded bag, as the agent saw them.

Alignment (:mod:`der_ros.contract`): transition k is

    s_k     = encode_observation(points of the ``state`` stamped t_k, cfg)
    a_k     = the action the bridge applied: ``applied_action=<a>`` in the frame_id of the
              ``reward`` stamped t_{k+1} (else, in bags whose bridge did not report it,
              buttons[0] of the ``lane_change_cmd`` stamped t_k)
    r_{k+1}, terminated_{k+1}, truncated_{k+1} = x, y, z of the ``reward`` stamped t_{k+1}
    s_{k+1} = encode_observation(points of the ``state`` stamped t_{k+1}, cfg)

The applied action is what the online learner stores (:mod:`der_ros.agent.online`): after a
command timeout (or a late or duplicate command) the bridge applies its default instead of the
command, and a transition that claimed the command would teach the offline learner an action
the simulation never took. ``Transitions.overridden`` counts the transitions where the two differ.

for consecutive steps of one episode (no transition leaves a terminal or truncated state: the
next stamp is the first state of a new episode). The points are decoded from the FLOAT64
PointCloud2 bytes and passed through the same :func:`sumo_bridge.observation.encode_observation`
as the environment and the agent node, so the observations are bit-identical. Rewards stay
float64 (the message's type). Steps with a missing part (a state or reward the recorder did not
get, e.g. at a cut, or no action known at all) produce no transition and are counted in ``skipped``.

The observation scales (``ObservationConfig``) are not in the PointCloud2; they come from the
caller, else the bag's ``custom_data['der_ros/observation']`` (JSON), else the run's
``params.yaml`` beside the bag (``der graph`` layout), else the defaults.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from der_ros.bag.reader import BagError, BagReader
from der_ros.configuration import flatten_names, from_dict, unflatten_names
from der_ros.contract import REWARD, STATE
from der_ros.offline.episodes import iter_steps, mistyped_topics, resolve_topics
from der_ros.yaml_loader import load_yaml
from sumo_bridge.observation import POINT_FIELDS, ObservationConfig, encode_observation

__all__ = ["Transitions", "build_transitions", "save_transitions", "load_transitions", "observation_config_of"]

log = logging.getLogger(__name__)

OBS_CONFIG_KEY = "der_ros/observation"


@dataclass
class Transitions:
    """Arrays of N transitions (row i of every array is one transition)."""

    obs: np.ndarray  # (N, obs_dim) float32
    actions: np.ndarray  # (N,) int64
    rewards: np.ndarray  # (N,) float64, as published
    next_obs: np.ndarray  # (N, obs_dim) float32
    terminated: np.ndarray  # (N,) bool
    truncated: np.ndarray  # (N,) bool
    stamps_ns: np.ndarray  # (N,) int64: t_k of s_k
    episode: np.ndarray  # (N,) int64: index of the episode in the bag (0-based)
    skipped: dict[str, int] = field(default_factory=dict)
    #: transitions whose applied action differs from the recorded command (timeouts, late commands)
    overridden: int = 0

    def __len__(self) -> int:
        return int(self.actions.shape[0])

    def arrays(self) -> dict[str, np.ndarray]:
        return {
            "obs": self.obs,
            "actions": self.actions,
            "rewards": self.rewards,
            "next_obs": self.next_obs,
            "terminated": self.terminated,
            "truncated": self.truncated,
            "stamps_ns": self.stamps_ns,
            "episode": self.episode,
        }


def observation_config_of(reader: BagReader) -> Any | None:
    """The ``ObservationConfig`` the agent used, if the bag or its run says so, else None.

    Looked up in order: the bag's ``custom_data['der_ros/observation']`` (JSON), then the
    ``params.yaml`` that ``der graph`` writes beside the bag (``<run>/params.yaml`` for
    ``<run>/bag``): the agent node's ``observation.*`` parameters (what the agent encoded
    with), else the bridge's ``scenario.observation.*``.
    """
    custom = ((reader.metadata or {}).get("custom_data") or {}).get(OBS_CONFIG_KEY)
    if custom:
        try:
            return from_dict(ObservationConfig, json.loads(custom), source=f"{reader.path} custom_data")
        except Exception as exc:  # noqa: BLE001 - a bad record means "not usable"
            log.warning("%s: custom_data %s is unusable (%s); ignoring it", reader.path, OBS_CONFIG_KEY, exc)
    bag_dir = reader.path if reader.path.is_dir() else reader.path.parent
    params_path = bag_dir.parent / "params.yaml"
    if not params_path.is_file():
        return None
    try:
        params = load_yaml(params_path) or {}
        for node, prefix in (("agent_node", "observation"), ("bridge_node", "scenario.observation")):
            values = flatten_names((params.get(node) or {}).get("ros__parameters") or {})
            found = unflatten_names(values, prefix)
            if found:
                log.info("%s: observation config from %s (%s)", reader.path, params_path, node)
                return from_dict(ObservationConfig, found, source=str(params_path))
    except Exception as exc:  # noqa: BLE001 - an unrelated params.yaml
        log.warning("%s: cannot use %s for the observation config (%s)", reader.path, params_path, exc)
    return None


def build_transitions(reader: BagReader, obs_cfg: Any | None = None, namespace: str | None = None) -> Transitions:
    """Rebuild the transitions of a bag (see the module docstring for the alignment)."""
    if obs_cfg is None:
        obs_cfg = observation_config_of(reader)
        if obs_cfg is None:
            log.info("%s: no observation config recorded; using ObservationConfig() defaults", reader.path)
            obs_cfg = ObservationConfig()
    roles = resolve_topics(reader, namespace)
    missing = [r for r in (STATE, REWARD) if r not in roles]
    if missing:
        wrong = mistyped_topics(reader, missing)  # our topic names with other types: say so, not just "missing"
        raise BagError(reader.path, None, f"cannot export transitions: no {', '.join(missing)} topic in the bag "
                       + (f"of the expected type: {'; '.join(wrong.values())}" if wrong else
                          f"(found {', '.join(sorted(reader.topics())) or 'no topics'})"))
    obs_l: list[np.ndarray] = []
    next_l: list[np.ndarray] = []
    act_l: list[int] = []
    rew_l: list[float] = []
    term_l: list[bool] = []
    trunc_l: list[bool] = []
    stamp_l: list[int] = []
    ep_l: list[int] = []
    skipped = {"no_command": 0, "no_state": 0, "no_reward": 0}
    overridden = 0
    prev = None
    prev_obs: np.ndarray | None = None
    episode = 0
    for s in iter_steps(reader, roles):
        obs = None
        if s.points is not None:
            if s.fields != POINT_FIELDS:
                raise BagError(reader.path, None, f"state fields at stamp {s.stamp_ns} are {s.fields}, expected {POINT_FIELDS}")
            try:
                obs = encode_observation(s.points, obs_cfg)
            except ValueError as exc:
                raise BagError(reader.path, None, f"state stamped {s.stamp_ns} ns: {exc}") from None
        if prev is not None and not (prev.terminated or prev.truncated):
            # the action the bridge applied to go from prev to s, as the online learner stores it
            action = s.applied_action if s.applied_action is not None else prev.action
            if action is None:
                skipped["no_command"] += 1
            elif prev_obs is None or obs is None:
                skipped["no_state"] += 1
            elif s.reward is None:
                skipped["no_reward"] += 1
            else:
                overridden += int(prev.action is not None and prev.action != action)
                obs_l.append(prev_obs)
                next_l.append(obs)
                act_l.append(action)
                rew_l.append(s.reward)
                term_l.append(s.terminated)
                trunc_l.append(s.truncated)
                stamp_l.append(prev.stamp_ns)
                ep_l.append(episode)
        if prev is not None and (prev.terminated or prev.truncated):
            episode += 1
        prev, prev_obs = s, obs
    dim = len(obs_l[0]) if obs_l else 0
    return Transitions(
        obs=np.asarray(obs_l, dtype=np.float32).reshape(len(obs_l), dim),
        actions=np.asarray(act_l, dtype=np.int64),
        rewards=np.asarray(rew_l, dtype=np.float64),
        next_obs=np.asarray(next_l, dtype=np.float32).reshape(len(next_l), dim),
        terminated=np.asarray(term_l, dtype=bool),
        truncated=np.asarray(trunc_l, dtype=bool),
        stamps_ns=np.asarray(stamp_l, dtype=np.int64),
        episode=np.asarray(ep_l, dtype=np.int64),
        skipped={k: v for k, v in skipped.items() if v},
        overridden=overridden,
    )


def save_transitions(tr: Transitions, path: str | Path) -> Path:
    """Write ``.npz`` (numpy) or ``.parquet`` (needs pyarrow; one row per transition)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".npz":
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez(tmp, **tr.arrays())
        tmp.replace(path)
        return path
    if path.suffix == ".parquet":
        try:
            import pyarrow as pa
            import pyarrow.parquet as pq
        except ImportError:
            raise BagError(path, None, "writing .parquet needs pyarrow (pip install pyarrow); "
                           "or export to .npz instead") from None
        n, dim = tr.obs.shape
        cols = {
            "obs": pa.FixedSizeListArray.from_arrays(pa.array(tr.obs.reshape(-1), type=pa.float32()), dim),
            "action": pa.array(tr.actions, type=pa.int64()),
            "reward": pa.array(tr.rewards, type=pa.float64()),
            "next_obs": pa.FixedSizeListArray.from_arrays(pa.array(tr.next_obs.reshape(-1), type=pa.float32()), dim),
            "terminated": pa.array(tr.terminated, type=pa.bool_()),
            "truncated": pa.array(tr.truncated, type=pa.bool_()),
            "stamp_ns": pa.array(tr.stamps_ns, type=pa.int64()),
            "episode": pa.array(tr.episode, type=pa.int64()),
        }
        tmp = path.with_name(path.name + ".tmp")
        pq.write_table(pa.table(cols), tmp)
        tmp.replace(path)
        return path
    raise BagError(path, None, f"unknown export format {path.suffix!r}; use .npz or .parquet")


def load_transitions(path: str | Path) -> Transitions:
    """Read back what :func:`save_transitions` wrote (.npz or .parquet)."""
    path = Path(path)
    if path.suffix == ".npz":
        with np.load(path) as z:
            return Transitions(**{k: z[k] for k in z.files})
    import pyarrow.parquet as pq

    t = pq.read_table(path)
    n = t.num_rows

    def mat(name: str) -> np.ndarray:
        col = t.column(name).combine_chunks()
        return col.flatten().to_numpy().astype(np.float32).reshape(n, -1)

    return Transitions(
        obs=mat("obs"), actions=t.column("action").to_numpy().astype(np.int64),
        rewards=t.column("reward").to_numpy().astype(np.float64), next_obs=mat("next_obs"),
        terminated=t.column("terminated").to_numpy().astype(bool), truncated=t.column("truncated").to_numpy().astype(bool),
        stamps_ns=t.column("stamp_ns").to_numpy().astype(np.int64), episode=t.column("episode").to_numpy().astype(np.int64),
    )

"""The shield decides lane changes only: the speed actions of a five-action scenario (exit) pass like keep
lane, in process (ShieldWrapper, the mask-mode target) and in the graph's command filter. Before, they were
outside the three-entry mask and replaced by keep lane, so behind the shield exit agents had no speed actions."""

from __future__ import annotations

import numpy as np

from der_ros.safety.apply import replace_unsafe, with_speed_actions
from der_ros.safety.command_filter import CommandFilter
from der_ros.safety.config import SafetyConfig
from der_ros.safety.observation_mask import ObservationMask
from sumo_bridge.observation import ObservationConfig, observation_size


def test_with_speed_actions_widens_one_mask_and_a_batch() -> None:
    lane = np.array([True, False, True])
    assert with_speed_actions(lane, 5).tolist() == [True, False, True, True, True]
    assert with_speed_actions(lane, 3) is not None and with_speed_actions(lane, 3).tolist() == lane.tolist()
    batch = np.array([[True, False, False], [True, True, False]])
    wide = with_speed_actions(batch, 5)
    assert wide.shape == (2, 5) and wide[:, 3:].all() and (wide[:, :3] == batch).all()
    # replace mode: a speed action is applied, a refused change still becomes keep
    assert replace_unsafe(3, with_speed_actions(lane, 5)) == (3, False)
    assert replace_unsafe(1, with_speed_actions(lane, 5)) == (0, True)
    assert replace_unsafe(4, lane) == (0, True)  # the old, three-entry mask: what exit agents suffered


def test_observation_mask_has_one_column_per_action() -> None:
    obs_cfg = ObservationConfig(max_lanes=4, goal_distance_scale=300.0)
    obs = np.zeros((4, observation_size(obs_cfg)), dtype=np.float32)
    three = ObservationMask(SafetyConfig(kind="rss"), obs_cfg)(obs)
    five = ObservationMask(SafetyConfig(kind="rss"), obs_cfg, 5)(obs)
    assert three.shape == (4, 3) and five.shape == (4, 5)
    assert (five[:, :3] == three).all() and five[:, 3:].all()


def test_command_filter_passes_speed_actions_without_a_state_and_refuses_what_the_scenario_lacks() -> None:
    never = lambda points: np.array([True, False, False])  # noqa: E731 - every change unsafe
    five = CommandFilter(never, n_actions=5)
    assert five.command(7, 3, now=0.0).verdict == "pass"  # no state needed, as for keep lane
    assert five.command(8, 4, now=0.0).applied == 4
    assert five.command(9, 5, now=0.0).verdict == "malformed"
    three = CommandFilter(never)
    assert three.command(7, 3, now=0.0).verdict == "malformed"  # the ring has no speed actions

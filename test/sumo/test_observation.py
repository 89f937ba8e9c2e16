"""The observation encoder: the env's list route equals the array route bit for bit, and both
equal a plain numpy statement of the documented formula (sumo_bridge/observation.py)."""

from __future__ import annotations

import numpy as np
import pytest

from der_ros.configuration import ConfigError, validate
from sumo_bridge.observation import (
    POINT_FIELDS,
    SLOT_NAMES,
    ObservationConfig,
    empty_points,
    encode_observation,
    encode_point_rows,
    field_index,
    observation_size,
)

C = {name: field_index(name) for name in POINT_FIELDS}


def _reference(points: np.ndarray, cfg: ObservationConfig) -> np.ndarray:
    """The module docstring's formula, written with numpy (independent of the fast code)."""
    ego = points[0]
    lane = ego[C["lane"]]
    out = [
        np.clip(ego[C["speed"]] / cfg.speed_scale, 0.0, 1.0),
        np.clip(lane / (cfg.max_lanes - 1), 0.0, 1.0),
        np.clip(ego[C["target_lane"]] - lane, -1.0, 1.0),
        float(lane < ego[C["lane_count"]] - 1),
        float(lane > 0),
    ]
    for name, row in zip(SLOT_NAMES, points[1:]):
        if row[C["present"]] > 0.5:
            gap, rel, h = row[C["gap"]], row[C["rel_speed"]], cfg.near_gap_horizon
            near = gap
            if h > 0:
                later = gap + rel * h if name.endswith("leader") else gap - rel * h
                near = np.where(later < gap, later, gap)
            out += [1.0, np.clip(gap / cfg.neighbour_range, -1.0, 1.0),
                    np.clip(rel / cfg.speed_scale, -1.0, 1.0),
                    np.clip(near / cfg.near_gap_range, -1.0, 1.0)]  # fmt: skip
        else:
            out += [0.0, 1.0, 0.0, 1.0]
    if cfg.required_decel_scale > 0:
        for name, row in zip(SLOT_NAMES, points[1:]):
            gap, rel = row[C["gap"]], row[C["rel_speed"]]
            closing = -rel if name.endswith("leader") else rel
            if row[C["present"]] <= 0.5:
                out.append(0.0)  # empty slot
            elif gap <= 0:
                out.append(1.0)  # overlap
            elif not closing > 0:
                out.append(0.0)  # the gap opens or holds
            else:
                out.append(np.minimum(closing**2 / (2 * gap) / cfg.required_decel_scale, 1.0))
    return np.array(out, dtype=np.float32)


def _builtin_reference(rows: list[list[float]], cfg: ObservationConfig) -> np.ndarray:
    """The encoder written with ``min(max(x, lo), hi)``: the fast version must match it byte for byte
    (signed zeros and NaN included), or the env and the agent node could encode differently."""
    ego, lane = rows[0], rows[0][C["lane"]]
    out = [min(max(ego[C["speed"]] / cfg.speed_scale, 0.0), 1.0), min(max(lane / (cfg.max_lanes - 1), 0.0), 1.0),
           min(max(ego[C["target_lane"]] - lane, -1.0), 1.0), 1.0 if lane < ego[C["lane_count"]] - 1 else 0.0,
           1.0 if lane > 0 else 0.0]  # fmt: skip
    for name, row in zip(SLOT_NAMES, rows[1:]):
        if row[C["present"]] > 0.5:
            gap, rel, h = row[C["gap"]], row[C["rel_speed"]], cfg.near_gap_horizon
            near = gap if h == 0 else min(gap, gap + rel * h if name.endswith("leader") else gap - rel * h)
            out += (1.0, min(max(gap / cfg.neighbour_range, -1.0), 1.0),
                    min(max(rel / cfg.speed_scale, -1.0), 1.0),
                    min(max(near / cfg.near_gap_range, -1.0), 1.0))  # fmt: skip
        else:
            out += (0.0, 1.0, 0.0, 1.0)
    for name, row in zip(SLOT_NAMES, rows[1:]) if cfg.required_decel_scale > 0 else ():
        gap, closing = row[C["gap"]], (-row[C["rel_speed"]] if name.endswith("leader") else row[C["rel_speed"]])
        present = row[C["present"]] > 0.5
        out.append(1.0 if present and gap <= 0 else
                   min(closing * closing / (2 * gap) / cfg.required_decel_scale, 1.0) if present and closing > 0 else 0.0)  # fmt: skip
    return np.array(out, dtype=np.float32)


def _random_points(rng: np.random.Generator) -> np.ndarray:
    pts = empty_points()
    pts[0, C["speed"]] = rng.choice([rng.uniform(-5, 40), 0.0, -0.0, 20.0])
    pts[0, C["lane"]] = rng.integers(0, 4)
    pts[0, C["target_lane"]] = rng.integers(0, 4)
    pts[0, C["lane_count"]] = rng.integers(1, 5)
    for i in range(1, 1 + len(SLOT_NAMES)):
        if rng.random() < 0.7:
            pts[i, C["present"]] = 1.0
            pts[i, C["gap"]] = rng.choice([rng.uniform(-10, 60), 30.0, -30.0, 0.0, -0.0, np.nan])
            pts[i, C["rel_speed"]] = rng.choice([rng.uniform(-40, 40), 20.0, -20.0, -0.0, np.inf])
    return pts


@pytest.mark.parametrize(
    "cfg",
    [
        ObservationConfig(),
        ObservationConfig(near_gap_horizon=0.5),
        ObservationConfig(neighbour_range=12.5, speed_scale=7.0, max_lanes=5, near_gap_range=2.5, near_gap_horizon=1.5),
        ObservationConfig(required_decel_scale=9.0),
        ObservationConfig(near_gap_horizon=0.5, required_decel_scale=0.5),
    ],
)
def test_list_route_equals_array_route_and_the_formula(cfg: ObservationConfig) -> None:
    rng = np.random.default_rng(7)
    for _ in range(500):
        pts = _random_points(rng)
        via_array = encode_observation(pts, cfg)
        via_rows = encode_point_rows(pts.tolist(), cfg)
        assert via_array.dtype == np.float32 and via_array.shape == (observation_size(cfg),)
        assert via_rows.tobytes() == via_array.tobytes()  # same arithmetic: bit for bit
        assert via_rows.tobytes() == _builtin_reference(pts.tolist(), cfg).tobytes()
        assert np.array_equal(via_array, _reference(pts, cfg), equal_nan=True), pts


def test_wrong_shape_is_rejected_with_the_expected_shape() -> None:
    with pytest.raises(ValueError, match=r"shape \(6, 12\), expected \(7, 12\)"):
        encode_observation(np.zeros((6, 12)), ObservationConfig())


def test_the_near_gap_channel_resolves_what_decides_a_lane_change() -> None:
    """Half a metre of overlap and one metre free are far apart in the near channel (the 30 m one barely
    tells them apart): the reason the channel exists (observation module docstring)."""
    cfg = ObservationConfig()
    obs = []
    for gap in (-0.5, 1.0):
        pts = empty_points()
        row = 1 + SLOT_NAMES.index("left_follower")
        pts[row, C["present"]], pts[row, C["gap"]] = 1.0, gap
        obs.append(encode_observation(pts, cfg))
    base = 5 + 4 * SLOT_NAMES.index("left_follower")
    assert obs[1][base + 1] - obs[0][base + 1] == pytest.approx(1.5 / 30.0)
    assert obs[1][base + 3] - obs[0][base + 3] == pytest.approx(1.5 / 5.0)
    assert observation_size() == 5 + 4 * len(SLOT_NAMES) == 29


def _one_neighbour(slot: str, gap: float, rel_speed: float) -> np.ndarray:
    pts = empty_points()
    row = 1 + SLOT_NAMES.index(slot)
    pts[row, C["present"]], pts[row, C["gap"]], pts[row, C["rel_speed"]] = 1.0, gap, rel_speed
    return pts


@pytest.mark.parametrize("slot", SLOT_NAMES)
def test_the_near_gap_channel_reads_the_gap_half_a_second_later_when_it_closes(slot: str) -> None:
    """A leader 0.84 m ahead and 3.7 m/s slower (the case Table 3's ring run collided in) reads as an
    overlap; the same vehicle pulling away reads its gap now; a follower mirrors the sign."""
    cfg = ObservationConfig(near_gap_horizon=0.5)
    near = 5 + 4 * SLOT_NAMES.index(slot) + 3
    closing = -3.7 if slot.endswith("leader") else 3.7
    assert encode_observation(_one_neighbour(slot, 0.84, closing), cfg)[near] == pytest.approx((0.84 - 1.85) / 5.0)
    assert encode_observation(_one_neighbour(slot, 0.84, -closing), cfg)[near] == pytest.approx(0.84 / 5.0)
    flat = ObservationConfig()  # the default: the gap now
    assert encode_observation(_one_neighbour(slot, 0.84, closing), flat)[near] == pytest.approx(0.84 / 5.0)
    other = [i for i in range(observation_size()) if i != near]
    both = (
        encode_observation(_one_neighbour(slot, 0.84, closing), cfg),
        encode_observation(_one_neighbour(slot, 0.84, closing), flat),
    )
    assert np.array_equal(both[0][other], both[1][other])  # only the near channel looks ahead


@pytest.mark.parametrize("bad", [-0.5, 10.5, float("nan")])
def test_a_bad_look_ahead_is_refused_naming_the_field(bad: float) -> None:
    with pytest.raises(ConfigError, match=r"near_gap_horizon = "):
        validate(ObservationConfig(near_gap_horizon=bad))


@pytest.mark.parametrize("name", ["neighbour_range", "near_gap_range", "near_gap_horizon", "required_decel_scale"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_the_observation_check_itself_refuses_a_non_finite_scale(name: str, bad: float) -> None:
    """``check()`` on its own (an ObservationConfig built in code is never passed through validate())."""
    cfg = ObservationConfig()
    setattr(cfg, name, bad)
    with pytest.raises(ConfigError, match=rf"^{name} = {bad!r}, expected a finite number$"):
        cfg.check()
    setattr(cfg, name, getattr(ObservationConfig(), name))
    cfg.check()  # the defaults pass


@pytest.mark.parametrize("bad", [-1.0, 100.5, float("nan"), float("inf")])
def test_a_bad_deceleration_scale_is_refused_naming_the_field(bad: float) -> None:
    with pytest.raises(ConfigError, match=r"required_decel_scale = "):
        validate(ObservationConfig(required_decel_scale=bad))


@pytest.mark.parametrize("slot", SLOT_NAMES)
def test_the_required_deceleration_block(slot: str) -> None:
    """closing speed^2 / (2 gap) per slot, scaled and clipped; a leader closes when it is slower, a follower
    when it is faster. The two ring states that most learned runs collided in (a leader 0.84 m ahead and
    3.7 m/s slower; 3.4 m ahead and 8 m/s slower) read above 8 m/s^2, a safe one (3 m, 3.7 m/s) 2.3."""
    cfg = ObservationConfig(required_decel_scale=9.0)
    base = observation_size()  # the block follows the 29 entries of the defaults, one entry per slot
    assert observation_size(cfg) == base + len(SLOT_NAMES) == 35
    col = base + SLOT_NAMES.index(slot)
    sign = -1.0 if slot.endswith("leader") else 1.0  # rel_speed of a closing neighbour has this sign

    def decel(gap: float, closing: float) -> float:
        return float(encode_observation(_one_neighbour(slot, gap, sign * closing), cfg)[col]) * 9.0

    assert decel(0.84, 3.7) == pytest.approx(3.7**2 / 1.68, rel=1e-6) and decel(0.84, 3.7) > 8.0
    assert decel(3.4, 8.0) == pytest.approx(9.0)  # 9.4 m/s^2, clipped at the scale
    assert decel(3.0, 3.7) == pytest.approx(3.7**2 / 6.0, rel=1e-6) and decel(3.0, 3.7) < 3.0
    assert decel(0.84, -3.7) == 0.0 and decel(0.84, 0.0) == 0.0  # pulling away or holding: no braking needed
    assert decel(-0.5, -3.7) == 9.0 and decel(0.0, 1.0) == 9.0  # an overlap reads as the maximum
    obs = encode_observation(_one_neighbour(slot, 0.84, sign * 3.7), cfg)
    others = [c for c in range(base, base + len(SLOT_NAMES)) if c != col]
    assert np.all(obs[others] == 0.0)  # empty slots need no braking
    # the rest of the vector is the one without the block
    assert np.array_equal(obs[:base], encode_observation(_one_neighbour(slot, 0.84, sign * 3.7), ObservationConfig()))


def test_the_env_and_the_graph_size_their_networks_from_the_same_observation_config() -> None:
    from der_ros.graph.snapshot_evaluation import observation_shape
    from der_ros.train.config import EnvConfig
    from sumo_bridge.observation import observation_space

    on = {"scenario": {"observation": {"required_decel_scale": 9.0}}}
    assert observation_shape(EnvConfig(id="der_ros/LaneChangeRing-v0", kwargs=on)) == (35,)
    assert observation_shape(EnvConfig(id="der_ros/LaneChangeRing-v0", kwargs={})) == (29,)
    assert observation_space(ObservationConfig(required_decel_scale=9.0)).shape == (35,)
    with pytest.raises(ConfigError, match="required_decel_scale"):
        observation_shape(EnvConfig(id="der_ros/LaneChangeRing-v0",
                                    kwargs={"scenario": {"observation": {"required_decel_scale": -1.0}}}))  # fmt: skip

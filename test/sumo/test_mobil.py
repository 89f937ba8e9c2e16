"""IDM and MOBIL (sumo_bridge/idm.py, sumo_bridge/mobil.py) on hand-built situations: a beneficial safe
change is taken, an unsafe one is refused by b_safe, politeness and the exit bias act as MOBIL says."""

from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from sumo_bridge.idm import IdmParams, idm_acceleration
from sumo_bridge.mobil import (
    MobilParams,
    Neighbour,
    Situation,
    change_incentive,
    exit_bias,
    mobil_decision,
    mobil_policy,
    situation_from_points,
)
from sumo_bridge.observation import empty_points, field_index

IDM = IdmParams()
EXIT_ROUTES = Path(__file__).resolve().parents[2] / "sumo_bridge" / "scenarios" / "exit" / "exit.rou.xml"


def test_idm_free_road_and_following() -> None:
    assert idm_acceleration(0.0, None, None, IDM) == pytest.approx(IDM.max_accel)  # standing, free road: a
    assert idm_acceleration(IDM.desired_speed, None, None, IDM) == pytest.approx(0.0)  # at v0: no more
    # at the equilibrium gap s0 + vT behind a leader of the same speed the interaction term is 1: a (free - 1)
    v = 20.0
    free = 1.0 - (v / IDM.desired_speed) ** 4
    assert idm_acceleration(v, IDM.min_gap + v * IDM.time_headway, v, IDM) == pytest.approx(IDM.max_accel * (free - 1.0))
    # closing in on a slower leader brakes harder than following one of the same speed at the same gap
    assert idm_acceleration(v, 20.0, 10.0, IDM) < idm_acceleration(v, 20.0, v, IDM) < 0.0
    assert idm_acceleration(v, -1.0, v, IDM) < -1e4  # an overlap: finite, very hard braking


def _slow_leader(**kw: object) -> Situation:
    """The ego at 25 m/s on the middle of three lanes, 12 m behind a truck at 15 m/s; the right lane as slow."""
    base = dict(speed=25.0, length=5.0, lane=1, lane_count=3, leader=Neighbour(12.0, 15.0),
                right_leader=Neighbour(5.0, 15.0))
    base.update(kw)
    return Situation(**base)  # type: ignore[arg-type]


def test_a_clearly_beneficial_safe_change_is_taken() -> None:
    s = _slow_leader()
    p = MobilParams()
    assert change_incentive(s, +1, p) is not None and change_incentive(s, +1, p) > p.threshold  # type: ignore[operator]
    assert mobil_decision(s, p) == 1  # left: the free lane
    assert change_incentive(dataclasses.replace(s, lane=2), +1, p) is None  # no lane left of the leftmost


def test_an_unsafe_change_is_refused_by_b_safe() -> None:
    # a car 4 m behind on the left lane at 30 m/s would have to brake far beyond 4 m/s^2
    s = _slow_leader(left_follower=Neighbour(4.0, 30.0))
    behind = idm_acceleration(30.0, 4.0, 25.0, IDM)
    assert behind < -4.0
    assert change_incentive(s, +1, MobilParams()) is None
    assert mobil_decision(s, MobilParams()) == 0
    # the same change with a b_safe that tolerates that braking: the incentive decides, and it is taken
    assert mobil_decision(s, MobilParams(safe_decel=-behind + 0.1, politeness=0.0)) == 1
    # an overlap is never safe, whatever b_safe
    assert change_incentive(_slow_leader(left_follower=Neighbour(-0.5, 25.0)), +1, MobilParams(safe_decel=1e12)) is None


def test_politeness_weighs_the_braking_imposed_on_the_new_follower() -> None:
    # the ego gains ~2.1 m/s^2 from leaving a car 40 m ahead at 22 m/s; the new follower, 18 m behind at
    # 25 m/s, would brake at ~1.6 m/s^2 (safe: > -b_safe) behind the ego instead of driving free (+0.7)
    s = _slow_leader(leader=Neighbour(40.0, 22.0), left_follower=Neighbour(18.0, 25.0))
    selfish, polite = MobilParams(politeness=0.0), MobilParams(politeness=1.0)
    gain_selfish, gain_polite = change_incentive(s, +1, selfish), change_incentive(s, +1, polite)
    assert gain_selfish is not None and gain_polite is not None
    assert gain_polite < gain_selfish
    assert mobil_decision(s, selfish) == 1
    assert mobil_decision(s, polite) == 0


def test_the_exit_bias_pulls_toward_the_exit_lane_and_grows_as_the_exit_nears() -> None:
    # free road everywhere: no speed incentive either way; the exit is reached from lane 0
    s = Situation(speed=25.0, length=5.0, lane=2, lane_count=4, target_lane=0, exit_distance=250.0)
    assert mobil_decision(s, MobilParams(exit_bias=0.0)) == 0
    p = MobilParams(exit_bias=1.0, exit_lookahead=100.0)
    assert mobil_decision(s, p) == -1  # right, toward the exit
    near, far = (exit_bias(dataclasses.replace(s, exit_distance=d), -1, p) for d in (150.0, 1000.0))
    assert near == pytest.approx(1.0)  # 2 changes still needed within 2 x 100 m: in full
    assert far == pytest.approx(0.2) and far < near
    # at 250 m: toward the exit 2 changes are still needed (2 x 100 / 250), away 3 (capped at 1): a larger penalty
    assert (exit_bias(s, -1, p), exit_bias(s, +1, p)) == (pytest.approx(0.8), pytest.approx(-1.0))
    # on the exit lane behind a slow leader with a free lane to the left: far away it overtakes,
    # near the exit the bias keeps it there
    # (a gain of ~2.1 m/s^2 against a bias of 3 m/s^2 in full, 0.06 at 5 km)
    on_exit = Situation(speed=25.0, length=5.0, lane=0, lane_count=4, leader=Neighbour(40.0, 22.0), target_lane=0,
                        exit_distance=5000.0)  # fmt: skip
    p3 = MobilParams(exit_bias=3.0)
    assert mobil_decision(on_exit, p3) == 1
    assert mobil_decision(dataclasses.replace(on_exit, exit_distance=80.0), p3) == 0


def test_the_policy_reads_the_env_points() -> None:
    pts = empty_points()
    col = {n: field_index(n) for n in ("speed", "gap", "lane", "target_lane", "present", "lane_count", "length")}
    pts[0, [col["speed"], col["gap"], col["lane"], col["target_lane"], col["lane_count"], col["length"]]] = (
        25.0, 120.0, 3.0, 0.0, 4.0, 5.0)  # fmt: skip
    s = situation_from_points(pts)
    assert (s.speed, s.exit_distance, s.lane, s.target_lane, s.lane_count, s.length) == (25.0, 120.0, 3, 0, 4, 5.0)
    assert s.right_follower is None and s.leader is None
    assert mobil_policy(pts, MobilParams()) == 2  # free road, exit to the right: change right
    rf = 1 + 5  # row of right_follower (SLOT_NAMES order)
    pts[rf, [col["present"], col["gap"], col["speed"]]] = (1.0, 2.0, 30.0)
    assert situation_from_points(pts).right_follower == Neighbour(2.0, 30.0)
    assert mobil_policy(pts, MobilParams()) == 0  # a fast car 2 m behind on the right: unsafe, keep


def test_the_exit_scenarios_idm_ego_drives_with_the_rules_idm() -> None:
    vtype = next(v for v in ET.parse(EXIT_ROUTES).getroot().iter("vType") if v.get("id") == "ego_idm")
    assert vtype.get("carFollowModel") == "IDM"
    assert float(vtype.get("tau", "nan")) == IDM.time_headway
    assert float(vtype.get("minGap", "nan")) == IDM.min_gap
    assert float(vtype.get("accel", "nan")) == IDM.max_accel
    assert float(vtype.get("decel", "nan")) == IDM.comfort_decel
    assert float(vtype.get("delta", "nan")) == IDM.delta

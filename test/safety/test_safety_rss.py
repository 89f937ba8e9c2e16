"""Our plain-Python RSS distance against Intel's ad-rss (LGPL; an optional dev dependency).

Skipped where ``ad-rss`` has no wheel (it ships Linux x86_64 CPython 3.10-3.13 only); CI installs
it from requirements-dev.txt.
"""

from __future__ import annotations

import itertools

import pytest

from der_ros.safety.rss import safe_longitudinal_distance

ad_rss = pytest.importorskip("ad_rss")
from ad_rss import physics, rss  # noqa: E402

rss.core.setLogLevel("off") if hasattr(rss.core, "setLogLevel") else None


def _state(v: float, rho: float, acc: float, bmin: float, bmax: float):  # noqa: ANN202 - ad-rss's type
    """A RelativeObjectState with every field valid (defaults are NaN or out of range: rss.md's pitfalls)."""
    o = rss.core.RelativeObjectState()
    o.object_type = rss.world.ObjectType.OtherVehicle
    d = o.dynamics
    d.alpha_lon.accel_max = physics.Acceleration(acc)
    d.alpha_lon.brake_max = physics.Acceleration(-bmax)
    d.alpha_lon.brake_min = physics.Acceleration(-bmin)
    d.alpha_lon.brake_min_correct = physics.Acceleration(-bmin)
    d.alpha_lat.accel_max = physics.Acceleration(0.2)
    d.alpha_lat.brake_min = physics.Acceleration(-0.8)
    d.lateral_fluctuation_margin = physics.Distance(0.0)
    d.response_time = physics.Duration(rho)
    d.max_speed_on_acceleration = physics.Speed(100.0)
    d.min_longitudinal_safety_distance = physics.Distance(0.0)
    u = d.unstructured_settings
    u.pedestrian_turning_radius = physics.Distance(2.0)
    u.drive_away_max_angle = physics.Angle(2.4)
    u.vehicle_yaw_rate_change = physics.AngularAcceleration(0.3)
    u.vehicle_min_radius = physics.Distance(3.5)
    u.vehicle_trajectory_calculation_step = physics.Duration(0.2)
    for name in dir(u):
        if name.endswith("_steps"):
            setattr(u, name, 1)
    uo = o.unstructured_object_state
    uo.yaw, uo.yaw_rate, uo.steering_angle = physics.Angle(0.0), physics.AngularVelocity(0.0), physics.Angle(0.0)
    uo.dimension.length, uo.dimension.width = physics.Distance(5.0), physics.Distance(2.0)
    uo.center_point.x, uo.center_point.y = physics.Distance(0.0), physics.Distance(0.0)
    uo.speed_range.minimum, uo.speed_range.maximum = physics.Speed(v), physics.Speed(v)
    s = o.structured_object_state
    s.velocity.speed_lon_min = s.velocity.speed_lon_max = physics.Speed(v)
    s.velocity.speed_lat_min = s.velocity.speed_lat_max = physics.Speed(0.0)
    s.is_in_correct_lane, s.has_priority = True, False
    s.distance_to_enter_intersection = s.distance_to_leave_intersection = physics.Distance(0.0)
    return o


def ad_rss_distance(v_rear: float, v_front: float, rho: float, acc: float, bmin: float, bmax: float) -> float:
    out = physics.Distance(0.0)
    ok = rss.structured.calculateSafeLongitudinalDistanceSameDirection(
        _state(v_front, rho, acc, bmin, bmax), _state(v_rear, rho, acc, bmin, bmax), out
    )
    assert ok, "ad-rss refused its input (it returns False and logs to stderr)"
    return out.mDistance


def test_matches_ad_rss_on_a_grid() -> None:
    speeds = (0.0, 2.5, 8.0, 13.9, 20.0, 33.0)
    params = ((0.5, 2.6, 4.5, 9.0), (1.0, 3.5, 4.0, 8.0), (0.2, 1.0, 6.0, 7.0), (0.05, 0.0, 4.5, 9.0))  # ad-rss requires rho > 0
    n = 0
    for (v_r, v_f), (rho, acc, bmin, bmax) in itertools.product(itertools.product(speeds, speeds), params):
        ours = safe_longitudinal_distance(v_r, v_f, rho, acc, bmin, bmax)
        theirs = ad_rss_distance(v_r, v_f, rho, acc, bmin, bmax)
        assert ours == pytest.approx(theirs, abs=1e-3), (v_r, v_f, rho, acc, bmin, bmax)
        n += 1
    assert n == 144


def test_textbook_figure() -> None:
    assert ad_rss_distance(20, 20, 1.0, 3.5, 4.0, 8.0) == pytest.approx(65.78125, abs=1e-3)

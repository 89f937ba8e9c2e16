"""``scenario.background_sigma`` / ``background_tau``: the less-careful-drivers shift (config/shift/ring_careless.yaml)."""

from __future__ import annotations

from pathlib import Path

import pytest

from der_ros.configuration import ConfigError
from sumo_bridge.lane_change_env import LaneChangeEnv
from sumo_bridge.scenario import ScenarioConfig

TINY = Path(__file__).resolve().parents[1] / "scenarios" / "tiny" / "tiny.yaml"


def driver_params(**shift: float) -> dict[str, tuple[float, float]]:
    env = LaneChangeEnv(ScenarioConfig.ring(**shift))
    try:
        env.reset(seed=5)
        api = env.api
        # every background vehicle, not only its type: the shift reaches the cars on the road
        types = {t: (api.vehicletype.getImperfection(t), api.vehicletype.getTau(t))
                 for t in api.vehicletype.getIDList() if not t.startswith("DEFAULT_")}  # fmt: skip
        for vid in api.vehicle.getIDList():
            assert (api.vehicle.getImperfection(vid), api.vehicle.getTau(vid)) == types[api.vehicle.getTypeID(vid)]
        env.reset(seed=6)  # the next build (a reload) keeps the shift
        assert api.vehicletype.getImperfection("car") == types["car"][0]
        return types
    finally:
        env.close()


def test_the_shift_reaches_every_background_driver_but_not_the_ego() -> None:
    assert driver_params() == {"car": (0.5, 1.0), "slow": (0.5, 1.0), "ego": (0.5, 1.0)}
    shifted = driver_params(background_sigma=0.9, background_tau=0.6, ring_rebuild_every=1)
    assert shifted == {"car": (0.9, 0.6), "slow": (0.9, 0.6), "ego": (0.5, 1.0)}


def test_out_of_range_and_file_scenarios_are_refused() -> None:
    with pytest.raises(ConfigError, match="background_sigma"):
        ScenarioConfig.ring(background_sigma=1.5)
    with pytest.raises(ValueError, match="background_sigma / background_tau with the scenario file"):
        LaneChangeEnv(ScenarioConfig(network="tiny", file=str(TINY), background_tau=0.6))

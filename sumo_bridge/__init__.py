"""sumo_bridge: the SUMO lane-change scenario as a gymnasium package (networks, libsumo environment).

ROS-free, like sumo-rl: the ROS 2 node that drives it is :mod:`der_ros.nodes.bridge_node`;
:mod:`sumo_bridge.lockstep` is that node's ROS-free command gate.
"""

import gymnasium as _gym

#: gymnasium ids registered on import (paper section 5.1: ring network and Yeongdong Bridge), and the
#: id of scenario files (``gym.make(SCENARIO_ENV_ID, scenario="path/to/scenario.yaml")``, docs/scenarios.md).
SCENARIO_ENV_ID = "der_ros/LaneChangeScenario-v0"
ENV_IDS: tuple[str, ...] = ("der_ros/LaneChangeRing-v0", "der_ros/LaneChangeUrban-v0", SCENARIO_ENV_ID)
#: the scenario network (``ScenarioConfig.network``) of each registered id ('scenario': named by the
#: file in its kwargs), and the id of each network
ENV_NETWORKS: dict[str, str] = dict(zip(ENV_IDS, ("ring", "urban", "scenario")))
NETWORK_ENV_IDS: dict[str, str] = {network: env_id for env_id, network in ENV_NETWORKS.items()}

for _env_id, _entry in zip(ENV_IDS, ("make_ring_env", "make_urban_env", "make_scenario_env")):
    if _env_id not in _gym.registry:
        _gym.register(id=_env_id, entry_point=f"sumo_bridge.lane_change_env:{_entry}", disable_env_checker=False)

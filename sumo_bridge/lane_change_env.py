"""LaneChangeEnv: the paper's SUMO lane-change task (section 5.1) as a gymnasium environment.

Task
----
SUMO drives speed, braking and steering of every vehicle; the agent decides only *when* to
change lanes. The ego vehicle starts on ``ego_lane`` among background traffic and must reach
``target_lane`` without a collision:

* ``ring`` (``der_ros/LaneChangeRing-v0``): two concentric lanes on a ~377 m ring; the ego starts
  on the outer lane (0) and must reach the inner lane (1). At every reset the background vehicles
  (6-10 on the outer, 15-21 on the inner lane, 30% of a slower and longer type) are placed at
  random, seeded positions; background vehicles keep SUMO's own lane-change model.
* ``urban`` (``der_ros/LaneChangeUrban-v0``): a synthetic stand-in for the Yeongdong Bridge OSM
  extract (see :mod:`sumo_bridge.network_build`); the ego is inserted on the northbound bridge's
  right lane (0) and must reach the left lane (2), i.e. two lane changes.

The ego's own lane-change model is off (``laneChangeMode 0``): a commanded change is executed
in the next simulation step whether safe or not, so an unsafe change really collides.

Actions (``Discrete(3)``, or ``Discrete(5)`` with speed actions)
-----------------------------------------------------------------
0 keep lane, 1 change left (lane index + 1), 2 change right (lane index - 1). A direction with
no lane is a no-op, and so is every change once the target lane is reached (see below).
Scenarios whose ``actions`` add them (:mod:`sumo_bridge.flow_scenario`): 3 faster, 4 slower.

Scenario files (``ScenarioConfig.file``, ``der_ros/LaneChangeScenario-v0``; docs/scenarios.md) set
up their own road and traffic (:mod:`sumo_bridge.flow_scenario`); a goal edge (an exit) adds the
event ``missed``.

Observation
-----------
``observation.encode_observation(info["points"], config.observation)``; see
:mod:`sumo_bridge.observation` for the point layout (ego + leader/follower on the current, left
and right lanes within 30 m, with present flags) and the normalisation. ``info["beyond_points"]`` holds the
nearest vehicles two lanes to either side (``observation.BEYOND_NAMES``), for the RSS shield only.

Reward (section 5.1)
--------------------
Every step: ``log(max(v_mean, min_speed))`` where ``v_mean`` is the mean speed (m/s) of all
vehicles in the simulation at the end of the step (the floor keeps a standstill finite; with
the default 0.1 m/s the per-step reward is >= -2.3). Plus ``reward_success`` (+100) once per
episode, in the step the ego has reached ``target_lane``, and ``reward_collision`` (-100) when
the agent causes a collision.

Episode structure (fixed horizon)
---------------------------------
An episode lasts ``max_episode_steps`` decisions (default 50 x 0.5 s) unless a collision ends it:

* reaching the target lane (on it for ``settle_time`` seconds without a collision) pays
  ``reward_success`` once; the episode **goes on**: the ego keeps driving on the target lane and the
  speed reward keeps flowing. The task is done, so lane-change commands are no-ops from then on
  (``lane_changes_after_success=False``). When they still acted, greedy agents drifted back and forth
  between the lanes after their success in nearly every episode -- a change back earns nothing, but
  nothing in the observation says the bonus was paid, so a return to the start lane looks like a
  fresh start -- and more than half of their caused collisions happened there (tuning seeds, ring).
  So changing lanes safely *now* beats waiting by
  ``reward_success * (1 - gamma^k)`` for any gamma < 1, whereas when success ended the episode it
  also forfeited the speed reward of the remaining steps and never changing lane was optimal for
  gamma above ~0.977 (``success_ends_episode=True`` restores that older structure).
  The paper's ring total of 216.91 is about 100 + 50 x 2.33: what this horizon pays.
* ``commit_on_success=True`` (the authors' "commit" structure on the same horizon): the step that
  reaches the target lane simulates the rest of the horizon itself (no-op decisions, so nothing the
  agent could do there is lost) and pays +100 plus the undiscounted sum of the remaining speed
  rewards; the episode then terminates (event ``success``, or ``collision`` if one follows;
  ``info["committed_steps"]`` counts the decisions folded in). Returns equal the fixed horizon's
  for the same decisions, but an episode costs only the decisions up to the change, so a budget of
  environment steps holds several times more lane-change outcomes to learn the gap boundary from.
* ``collision`` (terminated): SUMO reports a collision with the ego as collider or victim. The
  agent *caused* it (and gets ``reward_collision``) when it happens within ``collision_window``
  seconds after the ego's own commanded lane change; otherwise (rare: SUMO's car following is
  collision-free) the episode still terminates, without the penalty (``info["caused"]`` False).
* horizon reached (truncated, a time limit the learner bootstraps through): event ``success`` if
  the target lane was reached during the episode, else ``time_limit``. The ego leaving the network
  (urban: end of its route; the default horizon makes this impossible) ends the episode the same way.

``info["event"]`` is the episode's outcome, set in its last step only (None before):
``success``, ``collision`` or ``time_limit`` (scenario files with a goal edge also ``missed``). ``info["target_reached"]`` says whether the bonus
was paid so far.

Success at what cost to others
------------------------------
Two quantities per episode, in every ``info`` (running values; the last step's are the episode's), and
``info["lane_changes_done"]``, the ego's lane changes carried out so far (``lane_changes`` counts the
commands, which SUMO's own model may hold back):

* ``info["time_to_success"]``: simulated seconds from the episode's start (its first observation) to
  the end of the decision that reached the goal -- the target lane held for ``settle_time`` (ring,
  urban), the goal edge (an exit) -- i.e. decisions x ``decision_interval`` x ``step_length``; None
  until then (and in episodes that do not succeed). With ``commit_on_success`` it is the committing
  decision's time, not the end of the horizon the transition runs to.
* ``info["imposed_brake"]``: the harshest deceleration (m/s², >= 0) the ego imposed on others, MOBIL's
  safety criterion. After every lane change of the ego -- commanded or (``ego_lane_change_mode`` != 0)
  made by SUMO's own model -- the *new follower* (``vehicle.getFollower`` on the ego's new lane, just
  after the change) is watched for :data:`BRAKE_WINDOW_SECONDS` of simulated time or until the episode
  ends, and its strongest deceleration (``-vehicle.getAcceleration``, the speed difference of each SUMO
  step) is kept; the episode's value is the maximum over its changes. 0.0 when the ego changed lane
  into a lane without a follower, when the follower did not brake, and when the ego did not change
  lane at all (it imposed nothing). Overlapping windows (a second change within the window) are
  all watched. The follower's own driving is in the number too: with SUMO's driver imperfection
  (sigma 0.5 on the ring) a follower that merely dawdles decelerates by up to sigma x its accel
  (~1.3 m/s² for a car of the ring), so values below that say "nobody had to brake". A lane change
  is the ego's lane index changing on the same edge, read once per SUMO step (``vehicle.getLaneID``:
  with ``ego_lane_change_mode`` 0 only in the decision of a commanded change); a change made in the
  very step the ego crosses onto the next edge is not seen. The lane change is carried out after
  the movements of its step (SUMO's order), so the watch starts with the next step. Cost: one getter
  per SUMO step and watched vehicle, and only then; the commit fast-forward runs the same steps, so
  it observes the follower the same way.

Resets and determinism
----------------------
``reset(seed=s)`` seeds the placement/traffic RNG and SUMO's ``--seed`` (drawn from it) and always
rebuilds the traffic after a ``load`` (which also restarts SUMO's own RNG, the one behind the
drivers' imperfection sigma = 0.5), so it is a pure function of ``s``: the same seed gives the
same trajectory whatever the env did before. Resets without a seed go on with the env's RNG, so a
whole training stream is fixed by its first seed (and the actions).

Ring. A full build -- ``load`` in place (no new process), 22-32 vehicles placed at standstill at
seeded positions, ``warmup_seconds`` (5 s = 50 SUMO steps) of traffic -- costs 8-14 ms, which was
~40% of a training run (issue 11). So an unseeded reset builds only every ``ring_rebuild_every``
(4) episodes; in between it *re-places* the last build's traffic (:mod:`sumo_bridge.warm_state`):
every vehicle goes back to its lane, position, speed and keep-right urge at the end of that
build's warm-up, the ego's lane exactly, the other lane rotated around the ring by a fresh
uniform offset (a build draws each lane's offset independently and uniformly, so a rotation is
as likely as the recorded one), then one SUMO step runs, as after the build's warm-up. A
re-placement's median was 0.77-0.90 ms on the 2-core machine at load 4-8, where builds took
20-45 ms (``bench/train_loop.py`` reports the stream's ``reset_ms_p50``). Leaving the traffic running and replacing only the ego (as on the urban
network) would be cheaper still but changes the task: within one episode the lanes equalise
(7-11 / 15-21 vehicles become ~14 / 14), and the ego then starts beside a sparse inner lane whose
vehicles drive 11-12 m/s instead of 7 (KS statistics 0.3-0.7 against a build's first observations).

What re-placements change, measured by ``bench/reset_variety.py`` (ring.yaml; two-sample KS
statistics of the first observation of 500 stream episodes against 500 seeded builds, in
brackets the same for a stream of builds only, i.e. the chance level):

* target-lane slots, new in every episode: left leader gap 0.043 [0.031], speed 0.063 [0.039];
  left follower gap 0.041 [0.042], speed 0.062 [0.055]; gap quantiles 10/50/90 % -3.7/4.3/18.3
  and -2.9/4.9/18.4 m against -4.0/4.4/18.5 and -3.2/5.0/17.9 m for builds.
* own lane, repeated for ``ring_rebuild_every`` episodes per build: ego speed 0.050 [0.054],
  leader gap 0.078 [0.071], speed 0.099 [0.055], follower (present in ~20% of the starts) gap
  0.178 [0.160], speed 0.096 [0.113]. With ``ring_rebuild_every`` = 8 the own-lane statistics
  grow (see bench/README.md) while the target lane stays at chance level; hence 4.
* dynamics: lane-change state SUMO keeps but does not expose carries over, so after a
  re-placement the background vehicles change lanes ~8% less often (6.6-6.8 vs 7.2-7.3 per
  episode) and the keep-lane return is 0.4% lower (92.9 vs 93.3); gap acceptance succeeds in
  0.81 vs 0.80 of the episodes, without collisions either way (300 episodes each).

``ring_rebuild_every = 1`` gives the earlier behaviour exactly (a build at every reset).

Urban. Resets keep the background traffic running and only replace the ego after
``urban_ego_gap_seconds`` (a full ``load`` + ``urban_warmup_seconds`` happens on ``reset(seed=...)``
and every ``urban_reload_every`` episodes), because filling a 1 km bridge takes ~100 simulated
seconds. The urban ego gets a fresh id (``env.ego_id``) each episode.

Neighbours come from one context subscription on the ego (lanes -1/0/+1, up- and downstream)
per step; the mean speed from per-vehicle speed subscriptions (one read per step); departures
and collisions from a simulation subscription, so on traci a step is one round trip.

Viewers: after :meth:`LaneChangeEnv.enable_scene`, :meth:`LaneChangeEnv.scene` /
:meth:`LaneChangeEnv.lanes` give every vehicle and the road (:mod:`sumo_bridge.scene`, the core of
the bridge's marker topics): on traci through position and angle subscriptions, on libsumo through
getters once per decision. Off by default: training does not pay for it.

Code layout: the set-up of the built-in scenarios is in :mod:`sumo_bridge.builtin_setup`, that of
scenario files in :mod:`sumo_bridge.flow_scenario` (both mixed into :class:`LaneChangeEnv`); this
module keeps the stepping, the reward and the observation reading.

Only one libsumo simulation can live in a process (:mod:`sumo_bridge.sim_backend`): a second
live env raises :class:`~sumo_bridge.sim_backend.SimulationInUseError`. Run parallel envs in
subprocesses.
"""

from __future__ import annotations

import logging
import math
import operator
from typing import Any

import gymnasium as gym
import numpy as np

from der_ros.contract import LaneLine
from sumo_bridge.builtin_setup import RING_EDGES, URBAN_CORRIDOR, RingSetupMixin, UrbanSetupMixin
from sumo_bridge.flow_scenario import FlowScenarioMixin
from sumo_bridge.network_build import BuiltNetwork, build_network, build_scenario_network
from sumo_bridge.observation import (
    BEYOND_NAMES,
    POINT_FIELDS,
    SLOT_NAMES,
    empty_beyond_points,
    empty_points,
    encode_observation,
    encode_point_rows,
    observation_space,
)
from sumo_bridge.scenario import ScenarioConfig
from sumo_bridge.scenario_file import ScenarioSpec, load_scenario, scenario_from_kwargs
from sumo_bridge.scene import SCENE_VARS, Scene, SceneTracker, read_lanes
from sumo_bridge.sim_backend import SumoSimulation, constants
from sumo_bridge.warm_state import WarmState

log = logging.getLogger(__name__)

__all__ = ["LaneChangeEnv", "make_ring_env", "make_urban_env", "make_scenario_env", "EVENTS", "ACTION_MEANINGS",
           "BRAKE_WINDOW_SECONDS"]

#: Possible values of ``info["event"]`` (the outcome, in an episode's last step; None before).
#: ``missed``: a file scenario's goal edge was missed (sumo_bridge.flow_scenario).
EVENTS: tuple[str | None, ...] = (None, "success", "collision", "time_limit", "missed")
#: Seconds of simulated time the ego's new follower is watched after each lane change (``info["imposed_brake"]``).
BRAKE_WINDOW_SECONDS = 3.0
#: Every action by index (der_ros.contract.ACTION_NAMES): the paper's three (the default set) and the speed
#: actions a scenario may add (ScenarioConfig.actions); ``env.action_meanings`` is the scenario's prefix.
ACTION_MEANINGS: tuple[str, ...] = ("keep", "left", "right", "faster", "slower")

_tc = constants()
_V_SPEED, _V_LANE, _V_LANEPOS, _V_ROAD = _tc.VAR_SPEED, _tc.VAR_LANE_INDEX, _tc.VAR_LANEPOSITION, _tc.VAR_ROAD_ID
_V_POS, _V_ANGLE, _V_LENGTH = _tc.VAR_POSITION, _tc.VAR_ANGLE, _tc.VAR_LENGTH
_V_DEPARTED, _V_COLLIDING = _tc.VAR_DEPARTED_VEHICLES_IDS, _tc.VAR_COLLIDING_VEHICLES_NUMBER
_SPEED_ONLY = [_V_SPEED]
_GET_SPEED = operator.itemgetter(_V_SPEED)
#: lanes of the ego's context subscription, relative to its own: the neighbour slots'; with the beyond points
#: (a shield with ``beyond_lane`` asks for them, :meth:`LaneChangeEnv.watch_beyond_lanes`) two lanes out
_CTX_LANES = [-1, 0, 1]
_CTX_LANES_BEYOND = [-2, -1, 0, 1, 2]
_CTX_VARS = [_V_SPEED, _V_LANE, _V_LANEPOS, _V_ROAD, _V_POS, _V_ANGLE, _V_LENGTH]
# _points_from_context writes rows in this order
assert POINT_FIELDS == ("x", "y", "z", "speed", "rel_speed", "gap", "lane", "target_lane", "present", "slot",
                        "lane_count", "length")  # fmt: skip

_INVALID_DISTANCE = 1e10


class LaneChangeEnv(RingSetupMixin, UrbanSetupMixin, FlowScenarioMixin, gym.Env):
    """Gymnasium env of the section 5.1 lane-change task (see the module docstring)."""

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, config: ScenarioConfig | None = None, render_mode: str | None = None) -> None:
        if render_mode is not None:
            raise ValueError(f"render_mode = {render_mode!r}: use ScenarioConfig(gui=True) to watch in sumo-gui")
        self.config = config if config is not None else ScenarioConfig.ring()
        cfg = self.config
        self.action_space = gym.spaces.Discrete(len(cfg.actions))
        self.action_meanings: tuple[str, ...] = tuple(cfg.actions)
        self.observation_space = observation_space(cfg.observation)
        self.step_seconds: float = cfg.step_seconds
        self.ego_id = "ego"  # ring: always "ego"; urban: "ego.<n>", one per episode
        self._ego_serial = 0
        self._spec: ScenarioSpec | None = load_scenario(cfg.file) if cfg.file else None
        if self._spec is not None and (cfg.background_sigma is not None or cfg.background_tau is not None):
            raise ValueError(f"scenario.background_sigma / background_tau with the scenario file {cfg.file}: "
                             "only for the built-in ring and urban (a file scenario sets its drivers in its vTypes)")  # fmt: skip
        if self._spec is not None:
            net = self._spec.network
            self.network: BuiltNetwork = build_scenario_network(cfg.network, net.net, net.nodes, net.edges,
                                                                net.connections, self._spec.demand)  # fmt: skip
        else:
            self.network = build_network(cfg.network)
        self._v_departed, self._v_colliding = _V_DEPARTED, _V_COLLIDING
        self._edge_lengths: dict[str, float] = {}
        self._halted_s = 0.0  # file scenarios: seconds the ego has been halted in the miss zone
        self._target_speed: float | None = None  # speed actions: the ego's target speed (None: SUMO's own)
        self._ego_top_speed = 0.0  # speed actions: the ego's own maximum speed, read at its first one
        self._ego_road_pos_speed: tuple[str, float, float] = ("", 0.0, 0.0)
        self._goal_edge = self._spec.goal.edge if self._spec is not None else None
        self._tc = constants()
        self._sim: SumoSimulation | None = SumoSimulation(
            self._sumo_args(cfg.seed), backend=cfg.backend, gui=cfg.gui, owner=f"LaneChangeEnv({cfg.network})"
        )
        self.api = self._sim.api
        self._rng: np.random.Generator | None = None
        self._ctx_range = cfg.observation.neighbour_range + 15.0
        self._lane_counts: dict[str, int] = {}
        self._edge_lengths: dict[str, float] = {}  # commit fast-forward: lane length and fastest lane per edge
        self._edge_speeds: dict[str, float] = {}
        self._offsets: dict[str, float] = {}
        self._loop_length = 0.0
        self._closed_corridor = cfg.network == "ring"
        self._episodes_since_load = 0
        self._need_load = True
        self._ring_edges: list[tuple[str, float, float]] = []  # (edge, arc offset, length) of the ring's normal edges
        self._warm: WarmState | None = None  # ring: the last build's traffic, one step before its first observation
        self._ego_present = False
        self._colliding = False
        self._hold_target = not cfg.lane_changes_after_success  # commands are no-ops once the target is reached
        self._commit = cfg.commit_on_success  # success runs the rest of the horizon in its transition
        self._points = empty_points()
        self._beyond_points = empty_beyond_points()  # lanes +-2 (observation.BEYOND_NAMES): for the shield only
        self._ctx_lanes = _CTX_LANES  # _CTX_LANES_BEYOND once watch_beyond_lanes() was called
        self._obs = encode_observation(self._points, cfg.observation)
        self._ego_lane = 0  # lane index and lane count of the ego in the last points
        self._ego_lane_count = 0
        self._slots: list[tuple[float, str, dict[int, Any]] | None] = [None] * len(SLOT_NAMES)
        self._ego_xy_angle = (0.0, 0.0, 0.0)
        self._vehicle_vars = _SPEED_ONLY  # what each departing vehicle is subscribed to
        self._vehicle_results: dict[str, dict[int, Any]] | None = None  # the step's subscription results
        self._scene: SceneTracker | None = None
        self._scene_getters = False  # scene poses read with getters (libsumo) instead of subscribed
        # imposed braking (see the module docstring): SUMO's error for a vehicle that left, the window in steps,
        # whether the ego's own model may change lanes (then its lane is read at every step)
        self._sumo_error: tuple[type[Exception], ...] = _sumo_errors(self.api)
        self._brake_window_steps = self._steps(BRAKE_WINDOW_SECONDS)
        self._ego_changes_itself = cfg.ego_lane_change_mode != 0
        self._reached = False
        self._reset_episode_state()

    # ------------------------------------------------------------------ helpers
    def _sumo_args(self, seed: int, gui: bool | None = None) -> list[str]:
        """SUMO's command line for traffic seed ``seed`` (``gui``: the GUI's own options; default the config's)."""
        cfg = self.config
        gui = cfg.gui if gui is None else gui
        return [
            "-n", str(self.network.net_file),
            "-r", ",".join(str(p) for p in self._spec.demand) if self._spec is not None else str(self.network.route_file),
            "--step-length", repr(cfg.step_length),
            "--seed", str(int(seed)),
            "--collision.action", "warn",
            "--collision.check-junctions", "true",
            "--collision.mingap-factor", "0",
            "--time-to-teleport", str(self._spec.traffic.teleport_seconds) if self._spec is not None else "-1",
            "--no-step-log", "true",
            "--no-warnings", "true",
            "--duration-log.disable", "true",
            *(["--start", "true", "--quit-on-end", "true"] if gui else []),
            *(["--save-state.rng", "true"] if self._spec is not None else []),
            *cfg.sumo_args,
        ]  # fmt: skip

    def _reset_episode_state(self) -> None:
        self._episode_step = 0
        self._substep = 0
        self._last_change_substep: int | None = None
        self._on_target_since: int | None = None
        self._reached = False  # before _target_reached: its setter notes the time of success
        self._success_substep: int | None = None
        self._target_reached = False
        self._tracking = False  # imposed braking: on from the end of reset() (the warm-up steps are not watched)
        self._ego_lane_id = ""  # the ego's lane (SUMO lane id) as last read
        self._seen_change_of: int | None = None  # _last_change_substep whose lane change was seen
        self._watched: dict[str, int] = {}  # new follower -> last SUMO step (substep index) of its window
        self._imposed_brake = 0.0
        self._changes_done = 0  # lane changes of the ego seen carried out (_watch_followers)
        self._lane_changes = 0
        self._done = False
        self._committed_steps = 0  # decisions simulated inside the commit transition (commit_on_success)

    @property
    def _target_reached(self) -> bool:
        """Whether the goal was reached (the bonus paid) in this episode; setting it True notes the time."""
        return self._reached

    @_target_reached.setter
    def _target_reached(self, value: bool) -> None:
        if value and not self._reached:
            self._success_substep = self._substep
        self._reached = value

    @property
    def sim(self) -> SumoSimulation:
        if self._sim is None or self._sim.closed:
            raise RuntimeError("the environment is closed")
        return self._sim

    def _steps(self, seconds: float) -> int:
        return int(round(seconds / self.config.step_length))

    def _build_corridor(self) -> None:
        """Longitudinal offsets of the roads the ego drives along (ring: the closed loop).

        Positions on these roads (internal junction lanes included) map to one arc-length
        coordinate, so gaps to vehicles on the next or previous edge need no extra query.
        """
        api = self.api
        if self._spec is not None:
            edges = self._spec.ego.route
        else:
            edges = RING_EDGES if self.config.network == "ring" else URBAN_CORRIDOR
        seq = list(edges) + ([edges[0]] if self._closed_corridor else [])
        offsets: dict[str, float] = {}
        s = 0.0
        for a, b in zip(seq[:-1], seq[1:]):
            offsets[a] = s
            s += api.lane.getLength(f"{a}_0")
            via = ""
            for k in range(self._lane_count(a)):  # the internal lane(s) of the junction from a to b
                link = next((lk for lk in api.lane.getLinks(f"{a}_{k}") if lk[0].rsplit("_", 1)[0] == b), None)
                if link is not None:
                    via = link[4]
                    break
            while via and via.startswith(":"):
                offsets.setdefault(api.lane.getEdgeID(via), s)
                s += api.lane.getLength(via)
                successors = api.lane.getLinks(via)
                via = successors[0][0] if successors else ""
        if not self._closed_corridor:
            offsets[seq[-1]] = s
            s += api.lane.getLength(f"{seq[-1]}_0")
        self._offsets = offsets
        self._loop_length = s

    def _lane_count(self, road: str) -> int:
        n = self._lane_counts.get(road)
        if n is None:
            n = int(self.api.edge.getLaneNumber(road))
            self._lane_counts[road] = n
        return n

    # ------------------------------------------------------------------ reset
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        if seed is not None or self._rng is None:
            self._rng = np.random.default_rng(self.config.seed if seed is None else seed)
            self._need_load = True
        self._reset_episode_state()
        if self._spec is not None:
            self._reset_file()
        elif self.config.network == "ring":
            self._reset_ring()
        else:
            self._reset_urban()
        self._read_points()
        self._ego_lane_id = self.api.vehicle.getLaneID(self.ego_id)
        self._tracking = True
        info = self._info(event=None, mean_speed=self._mean_speed())
        return self._obs, info

    def _load(self) -> None:
        assert self._rng is not None
        sumo_seed = int(self._rng.integers(0, 2**31 - 1))
        self.sim.load(self._sumo_args(sumo_seed))
        self._apply_background_drivers()
        if self._scene is not None:
            self._scene.forget_sizes()
        # departures and collisions arrive with every step's answer (no extra round trip on traci)
        self.api.simulation.subscribe([_V_DEPARTED, _V_COLLIDING])
        self._ego_present = False
        if not self._offsets:
            self._build_corridor()
        self._episodes_since_load = 0
        self._need_load = False

    def _apply_background_drivers(self) -> None:
        """The scenario's driver shift (``background_sigma`` / ``background_tau``) on every vehicle type but
        the ego's and SUMO's built-in defaults; nothing when both are None (the scenarios' own drivers)."""
        cfg = self.config
        if cfg.background_sigma is None and cfg.background_tau is None:
            return
        for vtype in self.api.vehicletype.getIDList():
            if vtype == "ego" or vtype.startswith("DEFAULT_"):
                continue
            if cfg.background_sigma is not None:
                self.api.vehicletype.setImperfection(vtype, cfg.background_sigma)
            if cfg.background_tau is not None:
                self.api.vehicletype.setTau(vtype, cfg.background_tau)

    def _warmup(self, seconds: float, min_steps: int = 0) -> None:
        for _ in range(max(self._steps(seconds), min_steps)):
            self._sim_step()

    def _subscribe_ego(self) -> None:
        tc, api = self._tc, self.api
        api.vehicle.subscribeContext(
            self.ego_id,
            tc.CMD_GET_VEHICLE_VARIABLE,
            self._ctx_range,
            _CTX_VARS,
        )
        api.vehicle.addSubscriptionFilterLanes(
            self._ctx_lanes, noOpposite=True, downstreamDist=self._ctx_range, upstreamDist=self._ctx_range
        )
        self._sim_step()  # fill the subscription (and let the ego settle one step)
        self._ego_present = True

    # ------------------------------------------------------------------ step
    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._done:
            raise RuntimeError("step() called after the episode ended; call reset()")
        n = len(self.action_meanings)
        if type(action) is not int or not 0 <= action < n:  # fast path for plain ints
            if action not in range(n) or isinstance(action, bool):
                meanings = ", ".join(f"{i} ({m})" for i, m in enumerate(self.action_meanings))
                raise ValueError(f"action = {action!r}, expected one of {meanings}")
        reward, terminated, truncated, event, caused, mean_speed, ego_gone = self._advance(int(action))
        if self._commit and self._target_reached and not (terminated or truncated):
            # the authors' commit structure: the rest of the horizon runs inside this transition (no-op
            # decisions, the ego held on the target lane) and its speed rewards are summed into it
            reward, terminated, truncated, event, caused, mean_speed, ego_gone = self._commit_rest(reward)
            terminated, truncated = True, False  # the remainder is in the reward: nothing to bootstrap
        self._done = terminated or truncated
        if ego_gone:
            self._ego_present = False
        info = self._info(event=event, mean_speed=mean_speed)
        info["caused"] = caused
        info["committed_steps"] = self._committed_steps
        # a fresh array per step (the ego gone: a copy of the last one), so callers may keep or modify it
        obs = self._obs.copy() if ego_gone else self._obs
        return obs, float(reward), terminated, truncated, info

    def _advance(self, a: int) -> tuple[float, bool, bool, str | None, bool, float, bool]:
        """One decision: apply action ``a``, run ``decision_interval`` SUMO steps, read the neighbours
        (points and observation), score the decision.

        Returns (reward, terminated, truncated, event, caused, mean speed, ego gone).
        """
        collided = self._simulate_decision(a)
        ctx = self.api.vehicle.getContextSubscriptionResults(self.ego_id)
        ego_gone = not ctx or self.ego_id not in ctx
        if not ego_gone:
            self._points_from_context(ctx)
        mean_speed = self._mean_speed()
        return self._score(collided, ego_gone, mean_speed)

    def _simulate_decision(self, a: int) -> bool:
        """Apply action ``a`` and run ``decision_interval`` SUMO steps (fewer if the ego collides).

        True if the ego was in a collision (as collider or victim) in the last step run."""
        cfg, api = self.config, self.api
        if a >= 3:
            self._speed_action(a)
        elif a != 0 and not (self._target_reached and self._hold_target):
            new_lane = self._ego_lane + 1 if a == 1 else self._ego_lane - 1
            if 0 <= new_lane < self._ego_lane_count:
                api.vehicle.changeLane(self.ego_id, new_lane, self.step_seconds)
                self._last_change_substep = self._substep
                self._lane_changes += 1
        collided = False
        for _ in range(cfg.decision_interval):
            self._sim_step()
            self._substep += 1
            if self._colliding:
                for c in api.simulation.getCollisions():
                    if self.ego_id in (c.collider, c.victim):
                        collided = True
                        break
                if collided:
                    break
        self._episode_step += 1
        return collided

    def _score(self, collided: bool, ego_gone: bool, mean_speed: float) -> tuple[float, bool, bool, str | None, bool, float, bool]:
        """Reward and outcome of the decision just simulated (section 5.1; see the module docstring).

        Returns (reward, terminated, truncated, event, caused, mean speed, ego gone)."""
        cfg = self.config
        reward = math.log(max(mean_speed, cfg.min_speed))
        terminated = truncated = False
        event: str | None = None
        caused = False
        if collided:
            terminated, event = True, "collision"
            caused = self._last_change_substep is not None and (
                (self._substep - self._last_change_substep) * cfg.step_length <= cfg.collision_window + 1e-9
            )
            if caused:
                reward += cfg.reward_collision
        elif self._goal_edge is not None:
            if not ego_gone and not self._target_reached:
                r, terminated, event = self._edge_goal()
                reward += r
        elif self._target_reached:
            pass
        elif not ego_gone and self._ego_lane == cfg.target:
            if self._on_target_since is None:
                changed_now = self._last_change_substep is not None and self._last_change_substep >= self._substep - cfg.decision_interval
                self._on_target_since = self._last_change_substep + 1 if changed_now else self._substep
            if (self._substep - self._on_target_since) * cfg.step_length >= cfg.settle_time - 1e-9:
                self._target_reached = True  # the bonus is paid once per episode
                reward += cfg.reward_success
                if cfg.success_ends_episode:
                    terminated, event = True, "success"
        else:
            self._on_target_since = None
        if not terminated and (ego_gone or self._episode_step >= cfg.max_episode_steps):
            truncated, event = True, ("success" if self._target_reached else "time_limit")
        return reward, terminated, truncated, event, caused, mean_speed, ego_gone

    # ------------------------------------------------------------------ commit fast-forward
    def _commit_rest(self, reward: float) -> tuple[float, bool, bool, str | None, bool, float, bool]:
        """The rest of the horizon after a committed change, with the least work per SUMO step.

        The same decisions as repeated ``_advance(0)`` (no-op actions), bit for bit, but the ego's
        context subscription -- SUMO evaluates it at every simulation step, ~15-20% of a ring step
        with its lane filter -- is dropped while nothing reads it, and no observation is built in
        between: a decision here is ``decision_interval`` SUMO steps, the per-step collision count
        of the simulation subscription and one read of every vehicle's speed for the reward (on
        libsumo by getters once per decision, the per-vehicle speed subscriptions dropped meanwhile:
        SUMO would evaluate them at every step; on traci, where a getter is a round trip, the
        subscriptions stay).
        When the episode ends, the subscriptions are made again and evaluated on the current
        state without a simulation step (``simulationStep(now)`` re-evaluates every subscription),
        so the last observation is the one the full decisions would have built.

        The ego must not leave the network inside a fast decision (the full path would then keep
        the observation of the decision before, which no longer exists): ``_commit_fast_decisions``
        bounds how far the ego can drive (computed again from the ego's position when the bound runs
        out), and the decisions beyond it run in full.

        ``reward`` is the committing decision's reward; the remaining decisions' rewards are added
        to it one by one in order, as the full path did. Returns what ``_advance`` returns.
        """
        api = self.api
        ego = self.ego_id
        fast = self._commit_fast_decisions()
        detached = fast > 0
        getters = detached and self._sim is not None and self._sim.backend == "libsumo" and self._scene is None
        vehicle = api.vehicle
        if detached:
            vehicle.unsubscribeContext(ego, self._tc.CMD_GET_VEHICLE_VARIABLE, self._ctx_range)
        if getters:  # libsumo: a getter is a C++ call, cheaper once per decision than a subscription every step
            for vid in vehicle.getIDList():
                vehicle.unsubscribe(vid)
        get_ids, get_speed, fsum = vehicle.getIDList, vehicle.getSpeed, math.fsum
        committed = 0
        while True:
            if detached and committed == fast > 0:  # the bound ran out: again from where the ego really is
                fast += self._commit_fast_decisions()
            if committed < fast:
                collided = self._simulate_decision(0)
                if getters:  # the same speeds, summed exactly: the same mean as _mean_speed's
                    ids = get_ids()
                    mean_speed = fsum(map(get_speed, ids)) / len(ids) if ids else 0.0
                    ego_gone = ego not in ids
                else:
                    mean_speed = self._mean_speed()
                    ego_gone = ego not in self._vehicle_results  # type: ignore[operator]
                if ego_gone:  # excluded by the bound; the observation stays the one before the commit
                    log.warning("commit: ego %r left the network inside a fast decision", ego)
                r, terminated, truncated, event, caused, mean_speed, ego_gone = self._score(collided, ego_gone, mean_speed)
            else:
                if detached:  # the rest runs in full
                    self._attach(getters, context=True)
                    detached = getters = False
                r, terminated, truncated, event, caused, mean_speed, ego_gone = self._advance(0)
            reward += r
            committed += 1
            if terminated or truncated:
                break
        if detached:
            self._attach(getters, context=not ego_gone)
            if not ego_gone:
                self._points_from_context(vehicle.getContextSubscriptionResults(ego))
        self._committed_steps = committed
        return reward, terminated, truncated, event, caused, mean_speed, ego_gone

    def _attach(self, speeds: bool, context: bool) -> None:
        """Subscribe again what the fast decisions dropped -- every vehicle's speed (``speeds``), the ego's
        context (``context``, as ``_subscribe_ego``) -- and evaluate the subscriptions now, without a step.

        ``simulationStep(t)`` with ``t`` the current time runs no simulation step but evaluates every
        subscription, so the lane filter applies (a fresh subscription alone answers unfiltered)."""
        api = self.api
        vehicle = api.vehicle
        if speeds:
            for vid in vehicle.getIDList():
                vehicle.subscribe(vid, self._vehicle_vars)
        if context:
            vehicle.subscribeContext(self.ego_id, self._tc.CMD_GET_VEHICLE_VARIABLE, self._ctx_range, _CTX_VARS)
            vehicle.addSubscriptionFilterLanes(
                self._ctx_lanes, noOpposite=True, downstreamDist=self._ctx_range, upstreamDist=self._ctx_range
            )
        if not (speeds or context):
            return
        now = api.simulation.getTime()
        if now <= 0.0:  # time 0 would mean "one step"; a reset always leaves time > 0
            raise RuntimeError(f"commit fast-forward at simulation time {now}: expected a time after the reset's warm-up")
        api.simulationStep(now)
        if speeds:  # what scene() reads (the old results hold no vehicle that departed meanwhile)
            self._vehicle_results = vehicle.getAllSubscriptionResults()

    def _commit_fast_decisions(self) -> int:
        """How many of the remaining decisions can run fast: all, unless the ego could reach the end
        of its route (and leave the network) before the horizon.

        A lower bound on the distance left (the edges after the current one, without the last, whose
        arrival position is not read) against an upper bound on the distance driven (the ego's speed
        cap: its type's maximum speed and, with its speed factor, the fastest lane of its route)."""
        cfg, api = self.config, self.api
        remaining = cfg.max_episode_steps - self._episode_step
        if remaining <= 0:
            return 0
        v = api.vehicle
        route = v.getRoute(self.ego_id)
        idx = v.getRouteIndex(self.ego_id)
        if idx < 0:
            return 0
        left = 0.0
        for edge in route[idx + 1 : -1]:
            left += self._edge_length(edge)
        vmax = min(v.getMaxSpeed(self.ego_id), v.getSpeedFactor(self.ego_id) * self._max_lane_speed(route[idx:]))
        vmax = 1.1 * max(vmax, v.getSpeed(self.ego_id)) + 1.0  # margin
        per_decision = vmax * cfg.decision_interval * cfg.step_length
        safe = int(left // per_decision) - 1
        return max(0, min(remaining, safe))

    def _edge_length(self, edge: str) -> float:
        n = self._edge_lengths.get(edge)
        if n is None:
            n = self._edge_lengths[edge] = float(self.api.lane.getLength(f"{edge}_0"))
        return n

    def _max_lane_speed(self, edges: Any) -> float:
        best = 0.0
        for edge in edges:
            m = self._edge_speeds.get(edge)
            if m is None:
                m = max(float(self.api.lane.getMaxSpeed(f"{edge}_{k}")) for k in range(self._lane_count(edge)))
                self._edge_speeds[edge] = m
            best = max(best, m)
        return best

    # ------------------------------------------------------------------ state reading
    def _sim_step(self) -> None:
        """One SUMO step; every vehicle that departs gets a speed subscription (for the reward).

        Departures and the collision count come from a simulation subscription made at load.

        Reading all speeds through ``getAllSubscriptionResults`` is one call per env step, where
        a getter per vehicle would be one call (one round trip on traci) per vehicle.
        """
        api = self.api
        api.simulationStep()
        sim = api.simulation.getSubscriptionResults()
        for vid in sim[_V_DEPARTED]:
            api.vehicle.subscribe(vid, self._vehicle_vars)
        self._colliding = sim[_V_COLLIDING] > 0
        if self._tracking:
            self._watch_followers()

    def _watch_followers(self) -> None:
        """Imposed braking, after the SUMO step ``self._substep`` (see the module docstring): read each
        watched follower's acceleration, then whether the ego changed lane in this step (a new watch)."""
        vehicle = self.api.vehicle
        k = self._substep
        watched = self._watched
        if watched:
            for vid, last in list(watched.items()):
                try:
                    decel = -vehicle.getAcceleration(vid)
                except self._sumo_error:  # it left the network
                    del watched[vid]
                    continue
                if decel > self._imposed_brake:
                    self._imposed_brake = decel
                if k >= last:
                    del watched[vid]
        if not self._ego_changes_itself:  # only a commanded change, in its own decision, until it is seen
            commanded = self._last_change_substep
            if commanded is None or commanded == self._seen_change_of or k - commanded >= self.config.decision_interval:
                return
            if k == commanded:  # the lane the command was given on: the last observation's
                self._ego_lane_id = f"{self._ego_road_pos_speed[0]}_{self._ego_lane}"
        ego = self.ego_id
        try:
            lane_id = vehicle.getLaneID(ego)
        except self._sumo_error:  # the ego left the network
            return
        before, self._ego_lane_id = self._ego_lane_id, lane_id
        if lane_id == before or lane_id.rpartition("_")[0] != before.rpartition("_")[0]:
            return  # the same lane, or another edge (driving on, not a lane change)
        self._seen_change_of = self._last_change_substep
        self._changes_done += 1
        follower = vehicle.getFollower(ego)[0]
        if follower:
            watched[follower] = k + self._brake_window_steps

    def _mean_speed(self) -> float:
        """Mean speed (m/s) of all vehicles in the simulation (section 5.1 reward)."""
        results = self.api.vehicle.getAllSubscriptionResults()
        self._vehicle_results = results  # scene() reads the same answer (with the scene's variables)
        if not results:
            return 0.0
        # fsum: exact, so the result does not depend on the order the backend returns vehicles in
        return math.fsum(map(_GET_SPEED, results.values())) / len(results)

    def _read_points(self) -> None:
        ctx = self.api.vehicle.getContextSubscriptionResults(self.ego_id)
        if not ctx or self.ego_id not in ctx:
            raise RuntimeError(f"ego vehicle {self.ego_id!r} is not in the simulation after reset")
        self._points_from_context(ctx)

    def _distance_off_corridor(self, ego_road: str, ego_pos: float, road: str, pos: float) -> float | None:
        """Signed front-to-front distance along the road (positive: ``road/pos`` is ahead) when one
        of the two roads is off the corridor (SUMO's road distance; on the corridor the caller
        uses the precomputed offsets); None if neither is reachable from the other."""
        dist = self.api.simulation.getDistanceRoad
        ahead = dist(ego_road, ego_pos, road, pos, True)
        if 0.0 <= ahead < _INVALID_DISTANCE:
            return ahead
        behind = dist(road, pos, ego_road, ego_pos, True)
        if 0.0 <= behind < _INVALID_DISTANCE:
            return -behind
        return None

    def _points_from_context(self, ctx: dict[str, dict[int, Any]]) -> None:
        """Points (see :mod:`sumo_bridge.observation`) and observation from one context result.

        Sets ``self._points``, ``self._obs``, the ego's lane/lane count and the slot choice.
        This runs once per env step, so it is written for speed: rows are built as Python lists,
        encoded with :func:`~sumo_bridge.observation.encode_point_rows` and converted to an
        array once (per-element numpy writes would cost more than a SUMO step), and the
        along-road distance is inlined for roads of the corridor.
        """
        cfg = self.config
        ego_id = self.ego_id
        ego = ctx[ego_id]
        ego_road, ego_pos = ego[_V_ROAD], ego[_V_LANEPOS]
        ego_lane, ego_speed, ego_len = ego[_V_LANE], ego[_V_SPEED], ego[_V_LENGTH]
        n_lanes = self._lane_count(ego_road)
        rng_max = cfg.observation.neighbour_range
        offsets = self._offsets
        ego_off = offsets.get(ego_road)
        ego_s = None if ego_off is None else ego_off + ego_pos
        closed, lap = self._closed_corridor, self._loop_length
        half = 0.5 * lap
        has_left, has_right = ego_lane + 1 < n_lanes, ego_lane > 0
        # the slots, then (watch_beyond_lanes) the beyond points, two lanes away: indices 6.. of ``best``
        watching = self._ctx_lanes is _CTX_LANES_BEYOND
        best: list[tuple[float, str, dict[int, Any]] | None] = [None] * (
            len(SLOT_NAMES) + (len(BEYOND_NAMES) if watching else 0))
        for vid, var in ctx.items():
            offset = var[_V_LANE] - ego_lane
            if offset == 0:
                if vid == ego_id:
                    continue
                lead = 0
            elif offset == 1:
                if not has_left:
                    continue
                lead = 2
            elif offset == -1:
                if not has_right:
                    continue
                lead = 4
            elif offset == 2:
                if ego_lane + 2 >= n_lanes:
                    continue
                lead = 6
            elif offset == -2:
                if ego_lane < 2:
                    continue
                lead = 8
            else:
                continue
            # signed front-to-front distance along the road (positive: ahead of the ego)
            road_off = offsets.get(var[_V_ROAD]) if ego_s is not None else None
            if road_off is not None:
                d = (road_off + var[_V_LANEPOS]) - ego_s
                if closed:
                    d = (d + half) % lap - half
            else:
                d = self._distance_off_corridor(ego_road, ego_pos, var[_V_ROAD], var[_V_LANEPOS])
                if d is None:
                    continue
            if d > 0.0:
                slot, gap = lead, d - var[_V_LENGTH]
            else:
                slot, gap = lead + 1, -d - ego_len
            if gap <= rng_max:
                hit = best[slot]
                if hit is None or gap < hit[0]:
                    best[slot] = (gap, vid, var)
        ex, ey = ego[_V_POS]
        heading = math.radians(ego[_V_ANGLE])
        fx, fy = math.sin(heading), math.cos(heading)  # SUMO angle: degrees clockwise from north
        # rows in POINT_FIELDS order: x y z speed rel_speed gap lane target_lane present slot lane_count length
        to_goal = self._goal_distance(ego_road, ego_pos) if self._goal_edge is not None else 0.0
        rows = [[0.0, 0.0, 0.0, ego_speed, 0.0, to_goal, ego_lane, cfg.target, 1.0, 0.0, n_lanes, ego_len]]
        for slot, hit in enumerate(best):
            if hit is None:
                rows.append([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, -1.0, 0.0, slot + 1.0, 0.0, 0.0])
                continue
            gap, _vid, var = hit
            vx, vy = var[_V_POS]
            dx, dy = vx - ex, vy - ey
            speed = var[_V_SPEED]
            rows.append([dx * fx + dy * fy, -dx * fy + dy * fx, 0.0, speed, speed - ego_speed, gap, var[_V_LANE],
                         -1.0, 1.0, slot + 1.0, self._lane_count(var[_V_ROAD]), var[_V_LENGTH]])  # fmt: skip
        if watching:  # else they stay the empty rows: nothing two lanes out is read
            n_slots = 1 + len(SLOT_NAMES)
            self._beyond_points = np.array(rows[n_slots:], dtype=np.float64)
            del rows[n_slots:]
            best = best[: len(SLOT_NAMES)]
        self._slots = best
        self._ego_lane, self._ego_lane_count = int(ego_lane), n_lanes
        self._ego_xy_angle = (float(ex), float(ey), float(ego[_V_ANGLE]))
        self._ego_road_pos_speed = (ego_road, float(ego_pos), float(ego_speed))
        self._obs = encode_point_rows(rows, cfg.observation)
        self._points = np.array(rows, dtype=np.float64)

    # ------------------------------------------------------------------ scene (viewers)
    def enable_scene(self) -> None:
        """Make :meth:`scene` available (sizes: one call per vehicle, once).

        On traci every vehicle is subscribed to position and angle from now on (running vehicles
        re-subscribed), so the scene costs no extra round trip per vehicle and step. On libsumo
        :meth:`scene` reads them with getters instead: SUMO evaluates a subscription at every
        simulation step, five per decision (~200 us per decision for the ring's ~28 vehicles),
        while the scene is read once per decision (~1 us per vehicle)."""
        if self._scene is not None:
            return
        vehicle = self.api.vehicle
        self._scene = SceneTracker(lambda vid: (float(vehicle.getLength(vid)), float(vehicle.getWidth(vid))))
        self._scene_getters = self._sim.backend == "libsumo" if self._sim is not None else False
        if not self._scene_getters:
            self._vehicle_vars = SCENE_VARS
            for vid in vehicle.getIDList():
                vehicle.subscribe(vid, SCENE_VARS)
            self._vehicle_results = None  # read afresh: the last results lack the new variables

    def scene(self) -> Scene:
        """Every vehicle now (world position, angle, size, role: ego / neighbour slot / traffic) and the
        vehicles gone since the previous call; RuntimeError unless :meth:`enable_scene` was called."""
        if self._scene is None:
            raise RuntimeError("scene() needs enable_scene() first (the per-vehicle position subscriptions)")
        results = self._vehicle_results
        if results is None:
            results = self._vehicle_results = self.api.vehicle.getAllSubscriptionResults()
        if self._scene_getters:  # every vehicle of the step's results, its pose read now (see enable_scene)
            position, angle = self.api.vehicle.getPosition, self.api.vehicle.getAngle
            results = {vid: {_V_POS: position(vid), _V_ANGLE: angle(vid)} for vid in results}
        return self._scene.update(results, self.ego_id, self.neighbour_ids())

    def lanes(self) -> tuple[LaneLine, ...]:
        """Every lane of the network: centre line and width (for drawing the road)."""
        return read_lanes(self.api)

    def neighbour_ids(self) -> dict[str, str | None]:
        """Vehicle id in each slot of the last points (for tests and debugging; not observed)."""
        return {name: (None if hit is None else hit[1]) for name, hit in zip(SLOT_NAMES, self._slots)}

    def _info(self, event: str | None, mean_speed: float) -> dict[str, Any]:
        x, y, angle = self._ego_xy_angle
        return {
            "points": self._points.copy(),
            "beyond_points": self._beyond_points.copy(),
            "event": event,
            "mean_speed": mean_speed,
            "episode_step": self._episode_step,
            "sim_time": self._substep * self.config.step_length,
            "lane": self._ego_lane,
            "position": (x, y),
            "angle": angle,
            "lane_changes": self._lane_changes,
            "target_reached": self._target_reached,
            "time_to_success": None if self._success_substep is None else self._success_substep * self.config.step_length,
            "imposed_brake": self._imposed_brake,
            "lane_changes_done": self._changes_done,
        }

    # ------------------------------------------------------------------ lifecycle
    def watch_beyond_lanes(self) -> None:
        """Also read the lanes two to either side (``info["beyond_points"]``, for a shield with ``beyond_lane``)
        from the next reset on. Off by default: a wider context subscription is more vehicles per step, and
        nothing else reads them (the points and the observation are the same either way)."""
        self._ctx_lanes = _CTX_LANES_BEYOND

    def close(self) -> None:
        if self._sim is not None:
            self._sim.close()
            self._sim = None
        super().close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass


def _sumo_errors(api: Any) -> tuple[type[Exception], ...]:
    """The exceptions a SUMO getter raises for an unknown vehicle: libsumo's (``api.TraCIException``) and
    traci's (over a socket; a process may hold both backends)."""
    from traci.exceptions import TraCIException

    own = getattr(api, "TraCIException", None)
    return (TraCIException,) if own is None or own is TraCIException else (own, TraCIException)


def make_ring_env(config: ScenarioConfig | dict[str, Any] | None = None, scenario: dict[str, Any] | None = None,
                  render_mode: str | None = None, **overrides: Any) -> LaneChangeEnv:  # fmt: skip
    """Entry point of ``der_ros/LaneChangeRing-v0``: ``gym.make(id, scenario={...})`` or field overrides."""
    return LaneChangeEnv(scenario_from_kwargs("ring", config if config is not None else scenario, **overrides),
                         render_mode=render_mode)  # fmt: skip


def make_urban_env(config: ScenarioConfig | dict[str, Any] | None = None, scenario: dict[str, Any] | None = None,
                   render_mode: str | None = None, **overrides: Any) -> LaneChangeEnv:  # fmt: skip
    """Entry point of ``der_ros/LaneChangeUrban-v0`` (same keyword arguments as the ring)."""
    return LaneChangeEnv(scenario_from_kwargs("urban", config if config is not None else scenario, **overrides),
                         render_mode=render_mode)  # fmt: skip


def make_scenario_env(config: ScenarioConfig | dict[str, Any] | str | None = None,
                      scenario: dict[str, Any] | str | None = None, render_mode: str | None = None,
                      **overrides: Any) -> LaneChangeEnv:  # fmt: skip
    """Entry point of ``der_ros/LaneChangeScenario-v0``: ``gym.make(id, scenario="path.yaml")`` or
    ``scenario={"file": "path.yaml", <ScenarioConfig field overrides>}`` (docs/scenarios.md)."""
    return LaneChangeEnv(scenario_from_kwargs("scenario", config if config is not None else scenario, **overrides),
                         render_mode=render_mode)  # fmt: skip

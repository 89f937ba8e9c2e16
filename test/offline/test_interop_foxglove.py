"""Our bags as a real client reads them (issue 45, finding 8): Foxglove's own JavaScript libraries.

``test/js/decode_bags.js`` decodes every message of a bag with ``@mcap/core`` (the indexed reader and
the stream reader, CRCs checked) and ``@foxglove/rosmsg`` + ``@foxglove/rosmsg2-serialization``, the
path Foxglove Studio takes, with the versions pinned in ``test/js/package-lock.json``
(``npm ci`` here when ``test/js/node_modules`` is missing; ``scripts/setup_env.sh`` does it too).
Two bags: a short ``der graph`` run's (the recorder's) and a greedy-episode bag
(:func:`der_ros.offline.episode_recording.record_episode`, what ``der graph`` writes at the end).
Checked: every message decodes, both readers count what ``der bag info`` and metadata.yaml
count, header stamps never go back on any topic, log times are real (not 1970), the ``map -> ego``
transform is on ``/tf`` once per ego pose, and ``bridge/diagnostics`` is recorded.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml
from ros_harness import ros_domain  # noqa: F401 - fixture

REPO = Path(__file__).resolve().parents[2]
JS = REPO / "test" / "js"
#: 2020-01-01 in ns: a log time before it is not a real one (a bag starting at 0 shows 1970)
REAL_TIME_NS = 1_577_836_800 * 1_000_000_000


def _node() -> str:
    node = shutil.which("node")
    if node is None or shutil.which("npm") is None:
        pytest.skip("node/npm not installed (node 20 is on the CI machines): Foxglove interop not checked")
    return node


def _decode(files: list[Path]) -> dict[str, Any]:
    node = _node()
    if not (JS / "node_modules" / "@mcap" / "core").is_dir():
        done = subprocess.run(["npm", "ci", "--no-audit", "--no-fund"], cwd=JS, capture_output=True, text=True,
                              timeout=600)  # fmt: skip
        assert done.returncode == 0, f"npm ci failed:\n{done.stdout}\n{done.stderr}"
    done = subprocess.run([node, "decode_bags.js", *map(str, files)], cwd=JS, capture_output=True, text=True,
                          timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def _replay_info_counts(bag: Path) -> dict[str, int]:
    done = subprocess.run([sys.executable, "-m", "der_ros.cli", "replay", "info", str(bag), "--json"], cwd=REPO,
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
    return {t["name"]: int(t["count"]) for t in json.loads(done.stdout)["topics"]}


def _metadata_counts(bag: Path) -> dict[str, int]:
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    return {t["topic_metadata"]["name"]: int(t["message_count"]) for t in meta["topics_with_message_count"]}


def _check_bag(bag: Path, decoded: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Both Foxglove readers agree with each other, with ``der bag info`` and with metadata.yaml;
    nothing fails to decode, no stamp goes back, log times are real. Returns the indexed view."""
    files = sorted(bag.glob("*.mcap"))
    assert len(files) == 1, files
    seen = decoded[str(files[0])]
    indexed, stream = seen["indexed"], seen["stream"]
    counts = {topic: t["count"] for topic, t in indexed.items()}
    assert counts == {topic: t["count"] for topic, t in stream.items()}
    assert counts == _replay_info_counts(bag) == _metadata_counts(bag)
    for view in (indexed, stream):
        assert {t: v["failures"] for t, v in view.items() if v["failures"]} == {}, "messages Foxglove cannot decode"
        assert {t: v["stamps_back"] for t, v in view.items() if v["stamps_back"]} == {}, "header stamps going back"
        early = {t: v["log_time_min"] for t, v in view.items() if int(v["log_time_min"]) < REAL_TIME_NS}
        assert early == {}, "log times before 2020 (shown as 1970)"
    return indexed


@pytest.fixture(scope="module")
def greedy_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from der_ros.offline.episode_recording import record_episode
    from sumo_bridge.lane_change_env import LaneChangeEnv

    path = tmp_path_factory.mktemp("greedy") / "greedy_episode"
    env = LaneChangeEnv()
    try:
        rec = record_episode(env, lambda _obs: 0, path, seed=11)  # keep lane: the whole horizon
    finally:
        env.close()
    assert rec.steps > 5
    return path


def test_a_greedy_episode_bag_decodes_in_foxglove_with_tf_and_real_log_times(greedy_bag: Path) -> None:
    indexed = _check_bag(greedy_bag, _decode([next(greedy_bag.glob("*.mcap"))]))
    assert indexed["/tf"]["frames"] == ["map->ego"]
    assert indexed["/tf"]["count"] == indexed["/state"]["count"]  # one ego pose per state


@pytest.mark.ros
def test_a_graph_bag_decodes_in_foxglove_with_tf_and_bridge_diagnostics(ros_domain: int, tmp_path: Path) -> None:  # noqa: F811
    run_dir = tmp_path / "run"
    env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "der_ros.cli", "graph", "--run-dir", str(run_dir), "--domain-id", str(ros_domain),
         "--steps", "60", "--seed", "5", "--no-plots", "--eval-interval", "0", "--final-eval-episodes", "0",
         "-p", "bridge_node:diagnostics_every=10",
         # learning from step 16 and metrics after every gradient step: clock-stamped metrics interleave with the
         # episode-stamped ones (where one went backwards)
         "-p", "agent_node:agent.learning_starts=16", "-p", "agent_node:agent.batch_size=16",
         "-p", "agent_node:metrics_every=1"],
        cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
    assert proc.returncode == 0, out
    bag = run_dir / "bag"
    indexed = _check_bag(bag, _decode([next(bag.glob("*.mcap"))]))
    assert indexed["/tf"]["frames"] == ["map->ego"]
    assert indexed["/tf"]["count"] == indexed["/ego/odom"]["count"] > 0  # one transform per recorded ego pose
    assert indexed["/bridge/diagnostics"]["count"] >= 6  # every 10 of 60 steps, and the final one
    assert indexed["/agent/metrics"]["count"] > 40  # ~44 gradient steps, the episode ends, the final one

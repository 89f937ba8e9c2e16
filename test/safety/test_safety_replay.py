"""Vetoed commands in recorded bags: ``der bag plot`` draws interventions per episode, ``der bag render``
marks the vetoed step (caption and a ring around the ego)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from der_ros import cli
from der_ros.bag.reader import BagReader
from der_ros.offline.episode_recording import record_episode
from der_ros.offline.episodes import scan_bag
from der_ros.offline.render import VETO, RenderOptions, caption_lines, frame_view
from der_ros.offline.scene_frames import read_scene
from der_ros.safety import RssChecker, SafetyConfig
from sumo_bridge.lane_change_env import LaneChangeEnv
from sumo_bridge.scenario import ScenarioConfig


def test_vetoes_reach_plot_and_render(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    env = LaneChangeEnv(ScenarioConfig.ring(max_episode_steps=30))
    checker = RssChecker(SafetyConfig(kind="rss", brake_min=4.5))  # conservative: vetoes occur at the start
    proposals: list[np.ndarray] = []

    def act(_obs: np.ndarray) -> int:
        return 1  # always "change left now" (the ring's target lane is the left one)

    def shield(points: np.ndarray) -> np.ndarray:
        proposals.append(points.copy())
        return checker.mask(points)

    try:
        rec = record_episode(env, act, bag, seed=1_500_000_003, shield=shield)
    finally:
        env.close()
    expected = sum(not checker.mask(p)[1] for p in proposals)
    assert expected > 0, "this seed should start with an occupied target lane"
    scan = scan_bag(BagReader(bag))
    (episode,) = scan.episodes
    assert episode.interventions == expected == len(scan.vetoes)
    # plot: the interventions figure exists only for bags with a safety record
    assert cli.main(["replay", "plot", str(bag), "--out", str(tmp_path / "plots")]) == 0
    assert (tmp_path / "plots" / "interventions.png").stat().st_size > 5_000
    # render: the vetoed frames name the veto in the caption and ring the ego
    recording = read_scene(BagReader(bag))
    frames = recording.episodes[0].frames
    vetoed = [f for f in frames if f.vetoed is not None]
    assert len(vetoed) == expected and all(f.vetoed == 1 and f.action == 0 for f in vetoed)
    assert "VETOED left (safety)" in caption_lines("t", recording.episodes[0], vetoed[0], 0.5)[1]
    clean = next(f for f in frames if f.vetoed is None)
    assert "VETOED" not in caption_lines("t", recording.episodes[0], clean, 0.5)[1]
    gif = tmp_path / "episode.gif"
    assert cli.main(["replay", "render", str(bag), "--to", str(gif)]) == 0
    opts = RenderOptions()

    def veto_pixels(index: int) -> int:
        with Image.open(gif) as im:
            im.seek(index)
            frame = np.asarray(im.convert("RGB"))
        return int(np.all(frame[opts.caption_height:] == VETO, axis=-1).sum())

    assert veto_pixels(vetoed[0].step) > 20
    assert veto_pixels(clean.step) == 0
    assert frame_view(recording, vetoed[0], opts) is not None and rec.steps == len(frames) - 1

"""``der bag render``: one frame per recorded step, the ego drawn where it was, ring and urban, GIF and
MP4, and clear errors for a bag without markers or a missing encoder."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from bag_helpers import record_env_bag
from PIL import Image

from der_ros import cli
from der_ros.bag.reader import BagError, BagReader
from der_ros.contract import ACTION_NAMES
from der_ros.offline import animation
from der_ros.offline.episode_recording import record_episode
from der_ros.offline.episodes import EpisodeSummary
from der_ros.offline.render import PALETTE, ROLE_RGB, RenderOptions, caption_lines, frame_view, render_bag
from der_ros.offline.scene_frames import read_scene, select_episodes
from sumo_bridge.lane_change_env import ACTION_MEANINGS, LaneChangeEnv
from sumo_bridge.scenario import ScenarioConfig

#: keep for three steps, change left, then keep: a lane change to see
ACTIONS = [0, 0, 0, 1] + [0] * 50


def record(path: Path, network: str, steps: int, rewards: list[float] | None = None) -> int:
    """A short episode of ``network`` recorded as der graph records its greedy episode; its steps.
    ``rewards``: filled with the env's reward of every step, as the env returned it."""
    cfg = (ScenarioConfig.ring if network == "ring" else ScenarioConfig.urban)(max_episode_steps=steps)
    env = LaneChangeEnv(cfg)
    actions = iter(ACTIONS)
    if rewards is not None:
        env_step = env.step

        def step(action: int):  # noqa: ANN202 - the env's own step, its reward noted
            out = env_step(action)
            rewards.append(float(out[1]))
            return out

        env.step = step  # type: ignore[method-assign]
    try:
        return record_episode(env, lambda _obs: next(actions), path, seed=7).steps
    finally:
        env.close()


def gif_frame(path: Path, index: int) -> Image.Image:
    with Image.open(path) as im:
        im.seek(index)
        return im.convert("RGB")


@pytest.mark.slow
@pytest.mark.parametrize("network", ["ring", "urban"])
def test_one_frame_per_step_with_the_ego_drawn_where_it_was(tmp_path: Path, network: str) -> None:
    bag, gif = tmp_path / "bag", tmp_path / "episode.gif"
    steps = record(bag, network, 8)
    assert cli.main(["bag", "render", str(bag), "--episode", "0", "--to", str(gif)]) == 0
    with Image.open(gif) as im:
        assert im.n_frames == steps + 1  # the episode's first state and one per decision
        assert im.size == (640, 64 + 640)
    recording = read_scene(BagReader(bag))
    (episode,) = recording.episodes
    assert [f.step for f in episode.frames] == list(range(steps + 1))
    assert [f.action for f in episode.frames[:-1]] == ACTIONS[:steps] and episode.frames[-1].action is None
    opts = RenderOptions()
    views = set()
    for k in (2, steps - 1):
        frame = episode.frames[k]
        ego = frame.ego()
        view = frame_view(recording, frame, opts)
        views.add(view)
        px, py = view.project(ego.x, ego.y)
        image = gif_frame(gif, k)
        assert image.getpixel((int(px), int(py))) == ROLE_RGB["ego"]
        # and a vehicle that is not the ego shows its own role's colour where it is
        other = next(v for v in frame.vehicles if v.role != "ego" and 0 < view.project(v.x, v.y)[0] < opts.width
                     and opts.caption_height < view.project(v.x, v.y)[1] < opts.caption_height + opts.height)
        ox, oy = view.project(other.x, other.y)
        assert image.getpixel((int(ox), int(oy))) == ROLE_RGB[other.role]
        if network == "urban":  # the view follows the ego: it stays in the middle of the map
            assert (px, py) == pytest.approx((opts.width / 2, opts.caption_height + opts.height / 2), abs=1)
    # the ring is drawn whole and still; the urban network in a window that moves with the ego
    assert len(views) == (1 if network == "ring" else 2)


def test_episode_choice_and_the_caption_numbers(tmp_path: Path) -> None:
    assert ACTION_NAMES == ACTION_MEANINGS  # the caption names actions as the env does
    summaries = [EpisodeSummary(i, 10 + i, 0, 0, 5, 0.0, 0, "success" if i < 2 else "incomplete", 0.0, "event")
                 for i in range(3)]  # fmt: skip
    assert [e.episode for e in select_episodes(summaries)] == [11]  # the last finished one
    assert [e.episode for e in select_episodes(summaries, episode=12)] == [12]
    assert [e.episode for e in select_episodes(summaries, span=(10, 11))] == [10, 11]
    with pytest.raises(ValueError, match="no episode 3 .*episodes 10-12"):
        select_episodes(summaries, episode=3)
    with pytest.raises(ValueError, match="no episode in 20-30"):
        select_episodes(summaries, span=(20, 30))


def test_the_caption_tells_step_action_reward_return_and_outcome(tmp_path: Path) -> None:
    """Each frame's caption, read back from the bag: the action taken from that state (the env's name
    for it), the reward the env returned for arriving there, the running return, and the outcome only
    on the last frame, where it is the one the bag's episode summary holds."""
    bag, rewards = tmp_path / "bag", []
    steps = record(bag, "ring", 6, rewards)
    assert len(rewards) == steps >= 2
    recording = read_scene(BagReader(bag))
    (ep,) = recording.episodes
    outcome = ep.summary.outcome
    assert outcome in ("time_limit", "success", "collision")
    for k, frame in enumerate(ep.frames):
        line1, line2 = caption_lines("ring", ep, frame, recording.step_seconds)
        assert line1 == f"ring   episode 0   step {k}/{steps}   t = {0.5 * k:.1f} s"
        action = ACTION_MEANINGS[ACTIONS[k]] if k < steps else "-"
        reward = "-" if k == 0 else f"{rewards[k - 1]:+.2f}"
        ret = sum(rewards[:k])
        assert line2 == (f"action {action}   reward {reward}   return {ret:+.2f}   "
                         f"outcome {outcome if k == steps else '...'}"), k  # fmt: skip


def test_a_bag_without_markers_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = tmp_path / "plain"
    record_env_bag(bag, episodes=1, max_episode_steps=3)  # state / reward / command / episode, no scene
    with pytest.raises(BagError, match=r"no scene/vehicles markers .*markers:=false .*record_scene:=false"):
        render_bag(bag, tmp_path / "x.gif")
    assert cli.main(["bag", "render", str(bag), "--to", str(tmp_path / "x.gif")]) == 1
    assert "no scene/vehicles markers in this bag" in capsys.readouterr().err
    assert not (tmp_path / "x.gif").exists()


def test_mp4_when_an_encoder_is_installed_else_an_error_that_suggests_gif(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg", reason="a requirement; the missing-package case is below")

    bag = tmp_path / "bag"
    steps = record(bag, "ring", 4)
    out = render_bag(bag, tmp_path / "episode.mp4")
    assert out.frames == steps + 1
    assert imageio_ffmpeg.count_frames_and_secs(str(tmp_path / "episode.mp4"))[0] == steps + 1

    def no_binary() -> str:
        raise RuntimeError("No ffmpeg exe could be found")

    monkeypatch.setattr(imageio_ffmpeg, "get_ffmpeg_exe", no_binary)
    with pytest.raises(animation.EncoderUnavailable, match=r"write a GIF instead: --to out\.gif"):
        render_bag(bag, tmp_path / "again.mp4")
    assert not (tmp_path / "again.mp4").exists()
    with pytest.raises(animation.AnimationError, match="unknown animation format '.avi'"):
        render_bag(bag, tmp_path / "episode.avi")


def test_mp4_without_the_encoder_package_is_one_line_that_suggests_gif(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """Without imageio-ffmpeg (``import`` fails), ``--to x.mp4`` stops before reading the bag, names the
    package and suggests a GIF; the same bag renders to GIF."""
    bag = tmp_path / "bag"
    steps = record(bag, "ring", 2)
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # import imageio_ffmpeg -> ImportError
    with pytest.raises(animation.EncoderUnavailable, match=r"imageio-ffmpeg .*not installed.*--to out\.gif"):
        render_bag(bag, tmp_path / "x.mp4")
    assert cli.main(["bag", "render", str(bag), "--to", str(tmp_path / "x.mp4")]) == 1
    err = capsys.readouterr().err
    assert "cannot write MP4" in err and "--to out.gif" in err and "Traceback" not in err
    assert not (tmp_path / "x.mp4").exists()
    assert render_bag(bag, tmp_path / "x.gif").frames == steps + 1


def test_gif_palette_keeps_the_drawn_colours_exact(tmp_path: Path) -> None:
    """Every colour a frame is drawn with survives the GIF's palette unchanged."""
    colours = PALETTE[:13]
    frame = Image.new("RGB", (16 * len(colours), 16))
    for i, rgb in enumerate(colours):
        frame.paste(rgb, (16 * i, 0, 16 * i + 16, 16))
    animation.write_animation([frame, frame.transpose(Image.Transpose.FLIP_LEFT_RIGHT)], tmp_path / "p.gif", 4.0,
                              palette=PALETTE)  # fmt: skip
    got = np.asarray(gif_frame(tmp_path / "p.gif", 0))
    assert [tuple(int(c) for c in got[8, 16 * i + 8]) for i in range(len(colours))] == colours

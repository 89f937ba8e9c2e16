"""Benchmark: ``der bag render`` of a 40-step episode against the episode's own simulated time.

A person watching an episode should not wait longer than it lasted. For the ring and the urban
network, records one 40-decision episode (20 simulated seconds; keep lane, one change left at
step 4) the way ``der graph`` records its greedy episode
(:func:`der_ros.offline.episode_recording.record_episode`), then renders it ``--repeat`` times to a
GIF and once to an MP4 (:func:`der_ros.offline.render.render_bag`), and times the parts of the best
GIF run: reading the scene from the bag (:func:`der_ros.offline.scene_frames.read_scene`), drawing the
frames, quantising + writing. Peer: the episode's simulated time (the ratio is render seconds per
simulated second; target well under 1).

Ends with one JSON line: per network ``gif_s``, ``mp4_s``, ``frames``, ``ms_per_frame``,
``read_s``, ``draw_s``, ``write_s``, ``sim_s``, ``ratio`` (gif_s / sim_s).

    .venv/bin/python bench/render.py [--steps 40] [--repeat 3] [--quick]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path


def record(network: str, steps: int, path: Path) -> float:
    """Record the episode; returns its simulated seconds."""
    from der_ros.offline.episode_recording import record_episode
    from sumo_bridge.lane_change_env import LaneChangeEnv
    from sumo_bridge.scenario import ScenarioConfig

    cfg = (ScenarioConfig.ring if network == "ring" else ScenarioConfig.urban)(max_episode_steps=steps)
    env = LaneChangeEnv(cfg)
    actions = iter([0, 0, 0, 0, 1] + [0] * steps)
    try:
        rec = record_episode(env, lambda _obs: next(actions), path, seed=1_000_000_000)
        return rec.steps * float(env.step_seconds)
    finally:
        env.close()


def parts(bag: Path, out: Path) -> dict[str, float]:
    """The render split into read / draw / write (same calls as render_bag)."""
    from der_ros.bag.reader import BagReader
    from der_ros.offline.animation import write_animation
    from der_ros.offline.render import PALETTE, Caption, RenderOptions, _font, draw_frame, frame_view
    from der_ros.offline.scene_frames import read_scene

    t0 = time.perf_counter()
    recording = read_scene(BagReader(bag))
    t1 = time.perf_counter()
    opts = RenderOptions()
    frames, view = [], None
    font, small = _font(14), _font(11)
    for ep in recording.episodes:
        cap = Caption(bag.name, ep, font, small, recording.step_seconds)
        for frame in ep.frames:
            view = frame_view(recording, frame, opts, view)
            frames.append(draw_frame(recording.lanes, frame, view, opts, cap))
    t2 = time.perf_counter()
    write_animation(frames, out, 2.0 / recording.step_seconds, palette=PALETTE)
    t3 = time.perf_counter()
    return {"read_s": t1 - t0, "draw_s": t2 - t1, "write_s": t3 - t2}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=40, help="decisions in the episode (default 40 = 20 s)")
    parser.add_argument("--repeat", type=int, default=3, help="GIF renders per network (best counts)")
    parser.add_argument("--quick", action="store_true", help="ring only, one repeat")
    args = parser.parse_args()
    from der_ros.offline.render import render_bag

    repeat = 1 if args.quick else args.repeat
    work = Path(tempfile.mkdtemp(prefix="der_bench_render_"))
    result: dict[str, object] = {"bench": "render", "steps": args.steps}
    for network in ("ring",) if args.quick else ("ring", "urban"):
        bag = work / network
        sim_s = record(network, args.steps, bag)
        gif_runs = [render_bag(bag, work / f"{network}.gif") for _ in range(repeat)]
        best = min(gif_runs, key=lambda r: r.seconds)
        mp4 = render_bag(bag, work / f"{network}.mp4")
        split = min((parts(bag, work / f"{network}_parts.gif") for _ in range(repeat)), key=lambda d: sum(d.values()))
        row = {
            "frames": best.frames,
            "sim_s": sim_s,
            "gif_s": round(best.seconds, 3),
            "mp4_s": round(mp4.seconds, 3),
            "ms_per_frame": round(1000 * best.seconds / best.frames, 1),
            **{k: round(v, 3) for k, v in split.items()},
            "ratio": round(best.seconds / sim_s, 3),
            "gif_kb": round((work / f"{network}.gif").stat().st_size / 1024),
        }
        result[network] = row
        print(f"{network}: {row['frames']} frames of a {sim_s:.0f} s episode: GIF {row['gif_s']:.2f} s "
              f"({row['ms_per_frame']} ms/frame; read {row['read_s']:.2f} s, draw {row['draw_s']:.2f} s, "
              f"write {row['write_s']:.2f} s), MP4 {row['mp4_s']:.2f} s; {row['ratio']:.3f} s per simulated s",
              file=sys.stderr)  # fmt: skip
    result["files"] = str(work)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())

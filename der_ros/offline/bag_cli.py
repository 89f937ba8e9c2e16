"""``der bag`` (old spelling: ``der replay``): inspect, plot, export, train from, render and play recorded MCAP bags.

    der bag info BAG [--json]
    der bag plot BAG [BAG...] [--out DIR] [--label NAME ...]
    der bag export BAG --to transitions.npz|transitions.parquet
    der bag train BAG [BAG...] --replay der --lam 0.9 [--steps N] [--eval-episodes K]
    der bag play BAG [--rate R] [--loop] [--topics T ...]
    der bag render BAG [--episode N | --episodes A-B] --to out.gif|out.mp4

Everything but ``play`` is ROS-free (``rosbags`` typestore for decoding). Read errors
(:class:`~der_ros.bag.reader.BagError`: corrupted file, missing topics) are reported as one
line naming the file and byte offset, exit status 1; a cut bag is read up to the cut, and a
damaged chunk is skipped, each with one warning (``info`` reports what was skipped).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import warnings
from pathlib import Path
from typing import Any

from der_ros.bag.reader import BagError, BagReader, DamagedChunk, DamagedChunkWarning, TruncatedBagWarning
from der_ros.configuration import load_yaml
from der_ros.contract import EPISODE_COLLISION, EPISODE_ENDS, EPISODE_SUCCESS, qos_text
from der_ros.offline.bag_plots import plot_bags
from der_ros.offline.episodes import scan_bag
from der_ros.offline.export import build_transitions, save_transitions
from der_ros.offline.render import RenderOptions, render_bag
from der_ros.offline.train_from_bags import add_train_arguments, run_train
from sumo_bridge.observation import ObservationConfig

__all__ = ["add_arguments", "run", "bag_info"]

log = logging.getLogger(__name__)

#: 2: added ``skipped`` (damaged chunks the reader stepped over)
INFO_SCHEMA_VERSION = 2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="replay_command", metavar="ACTION", required=True)

    p = sub.add_parser("info", help="topics, counts, duration and the per-episode table of a bag")
    p.add_argument("bag", type=Path, help="rosbag2 directory or .mcap file")
    p.add_argument("--json", action="store_true", help="print one JSON document instead of tables")
    p.add_argument("--last", type=int, default=None, metavar="N", help="show only the last N episodes in the table")
    p.add_argument("--namespace", default=None, help="graph namespace when a bag holds several (e.g. /run1)")

    p = sub.add_parser("plot", help="PNG figures: returns, outcome rates, speeds, DER replay statistics")
    p.add_argument("bags", type=Path, nargs="+", help="one or more bags (overlaid for comparison)")
    p.add_argument("--out", type=Path, default=Path("plots"), help="output directory (default: ./plots)")
    p.add_argument("--label", action="append", default=None, help="legend label per bag (default: bag name)")
    p.add_argument("--window", type=int, default=10, help="moving-average window in episodes")
    p.add_argument("--namespace", default=None, help="graph namespace when a bag holds several")

    p = sub.add_parser("export", help="transitions (s, a, r, s', terminated, truncated) as .npz or .parquet")
    p.add_argument("bag", type=Path)
    p.add_argument("--to", type=Path, required=True, help="output file, .npz or .parquet")
    p.add_argument("--obs-config", type=Path, default=None,
                   help="YAML with the ObservationConfig fields (default: recorded in the bag, else defaults)")
    p.add_argument("--namespace", default=None)

    p = sub.add_parser("train", help="train a DQN offline from recorded transitions, then evaluate it in SUMO")
    add_train_arguments(p)

    p = sub.add_parser("play", help="publish the recorded messages into a ROS 2 graph (needs rclpy)")
    p.add_argument("bag", type=Path, help="rosbag2 directory or .mcap file")
    p.add_argument("--rate", type=float, default=1.0, help="playback speed factor (2 = twice as fast)")
    p.add_argument("--loop", action="store_true", help="start again at the end (Ctrl-C stops)")
    p.add_argument("--topics", nargs="+", default=None, help="publish only these topics")
    p.add_argument("--clock", action="store_true", help="publish /clock from the log times if the bag has no /clock")
    p.add_argument("--wait-subscribers", type=float, default=0.0, metavar="SECONDS",
                   help="before playing, wait up to this long until every topic has a subscriber")
    p.add_argument("--delay", type=float, default=0.0, metavar="SECONDS", help="sleep this long before playing")

    p = sub.add_parser("render", help="top-down animation (GIF or MP4) of recorded episodes from the scene markers")
    p.add_argument("bag", type=Path, help="rosbag2 directory or .mcap file recorded with the scene markers on")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--episode", type=int, default=None, metavar="N",
                       help="the episode numbered N (the 'episode' column of der bag info; default: the last finished)")
    which.add_argument("--episodes", type=_episode_span, default=None, metavar="A-B",
                       help="episodes A to B (inclusive) one after the other")
    p.add_argument("--to", type=Path, required=True, help="output file: .gif (Pillow) or .mp4 (needs imageio-ffmpeg)")
    p.add_argument("--fps", type=float, default=None, help="frames per second (default: twice real time)")
    p.add_argument("--window", type=float, default=None, metavar="METRES",
                   help="side of the view that follows the ego (default: the whole network when it is under 300 m "
                   "across, as the ring, else 150 m); 0 = always the whole network")
    p.add_argument("--size", type=int, default=640, metavar="PIXELS", help="width and height of the map (multiple of 16)")
    p.add_argument("--namespace", default=None, help="graph namespace when a bag holds several")


def run(args: argparse.Namespace) -> int:
    handlers = {"info": _run_info, "plot": _run_plot, "export": _run_export, "train": _run_train, "play": _run_play,
                "render": _run_render}
    with warnings.catch_warnings():
        warnings.simplefilter("always", TruncatedBagWarning)
        warnings.simplefilter("always", DamagedChunkWarning)
        warnings.showwarning = _show_warning
        try:
            return handlers[args.replay_command](args)
        except BagError as exc:
            print(f"der bag {args.replay_command}: error: {exc}", file=sys.stderr)
            return 1


def _show_warning(message: Warning | str, category: type[Warning], *_a: Any, **_k: Any) -> None:
    print(f"warning: {message}", file=sys.stderr)


# -- info -----------------------------------------------------------------------------------------


def _finite(x: float) -> float | None:
    return x if isinstance(x, (int, float)) and math.isfinite(x) else None


def bag_info(path: Path, namespace: str | None = None) -> dict[str, Any]:
    """The ``der bag info --json`` document (schema version :data:`INFO_SCHEMA_VERSION`)."""
    reader = BagReader(path)
    scan = scan_bag(reader, namespace)
    conns = reader.topics()
    meta_counts: dict[str, int] = {}
    for entry in (reader.metadata or {}).get("topics_with_message_count") or []:
        meta_counts[str((entry.get("topic_metadata") or {}).get("name"))] = int(entry.get("message_count", 0))
    stale = bool(reader.metadata) and any(meta_counts.get(t, 0) != n for t, n in scan.counts.items())
    topics = []
    for topic in sorted(conns):
        c = conns[topic]
        topics.append({
            "name": topic,
            "type": c.msgtype,
            "count": scan.counts.get(topic, 0),
            "qos": list(c.offered_qos),
            "qos_text": qos_text(c.offered_qos),
            "role": next((r for r, t in scan.roles.items() if t == topic), None),
        })
    eps = [e.as_dict() for e in scan.episodes]
    for e in eps:
        e["mean_speed"] = _finite(e["mean_speed"])
    n_eps = len(eps)
    outcomes = {o: sum(1 for e in eps if e["outcome"] == o) for o in (*EPISODE_ENDS, "terminated", "incomplete")}
    finished = [e for e in eps if e["outcome"] != "incomplete"]
    return {
        "schema_version": INFO_SCHEMA_VERSION,
        "bag": str(path),
        "name": scan.name,
        "files": [str(f) for f in reader.files],
        "truncated": scan.truncated,
        "metadata_yaml": reader.metadata is not None,
        "metadata_stale": stale,
        "message_count": sum(scan.counts.values()),
        "start_ns": scan.first_ns,
        "end_ns": scan.last_ns,
        "duration_s": scan.duration_s,
        "topics": topics,
        "roles": scan.roles,
        "steps": scan.steps,
        "episodes": eps,
        "summary": {
            "episodes": n_eps,
            "finished_episodes": len(finished),
            "outcomes": outcomes,
            "success_rate": outcomes[EPISODE_SUCCESS] / len(finished) if finished else None,
            "collision_rate": outcomes[EPISODE_COLLISION] / len(finished) if finished else None,
            "mean_return": sum(e["return"] for e in finished) / len(finished) if finished else None,
        },
        "metrics": sorted(scan.metrics),
        "skipped": skipped_summary(reader.damaged),
    }


def skipped_summary(damaged: list[DamagedChunk]) -> dict[str, Any]:
    """What a damaged bag cost: chunks skipped, their bytes, the messages they held (None if any
    count is unknown), and each chunk's byte range and reason."""
    lost = [d.messages_lost for d in damaged]
    return {
        "chunks": len(damaged),
        "bytes": sum(d.bytes_lost for d in damaged),
        "messages_lost": None if any(n is None for n in lost) else sum(n for n in lost if n is not None),
        "ranges": [d.as_dict() for d in damaged],
    }


def _run_info(args: argparse.Namespace) -> int:
    info = bag_info(args.bag, args.namespace)
    if args.json:
        print(json.dumps(info, indent=1, default=str))
        return 0
    print(f"bag:       {info['bag']}{'  (TRUNCATED: read up to the cut)' if info['truncated'] else ''}")
    print(f"files:     {', '.join(Path(f).name for f in info['files'])}")
    if not info["metadata_yaml"]:
        print("metadata:  no metadata.yaml (read from the MCAP file)")
    elif info["metadata_stale"]:
        print("metadata:  metadata.yaml counts differ from the file (stale); showing the counts read")
    print(f"messages:  {info['message_count']}")
    skipped = info["skipped"]
    if skipped["chunks"]:
        lost = "an unknown number of" if skipped["messages_lost"] is None else skipped["messages_lost"]
        whole = [r for r in skipped["ranges"] if r.get("damaged_at") is None]
        placed = [r for r in skipped["ranges"] if r.get("damaged_at") is not None]
        parts = [f"{Path(r['file']).name} bytes {r['start']}-{r['end']} skipped" for r in whole]
        parts += [f"one byte at {r['damaged_at']}, {0 if r['dropped'] is None else 1} record dropped" for r in placed]
        print(f"DAMAGED:   {skipped['chunks']} chunk(s) damaged ({', '.join(parts)}): {lost} messages lost")
    print(f"duration:  {info['duration_s']:.3f} s")
    rows = [(t["name"], t["type"], str(t["count"]), t["qos_text"]) for t in info["topics"]]
    _table(("topic", "type", "count", "QoS"), rows)
    if info["episodes"]:
        print()
        shown = info["episodes"][-args.last:] if args.last else info["episodes"]
        if len(shown) < len(info["episodes"]):
            print(f"(last {len(shown)} of {len(info['episodes'])} episodes)")
        rows = [
            (str(e["index"]), "-" if e["episode"] is None else str(e["episode"]), str(e["steps"]), f"{e['return']:.3f}",
             str(e["lane_changes"]), e["outcome"], "-" if e["mean_speed"] is None else f"{e['mean_speed']:.2f}")
            for e in shown
        ]
        _table(("#", "episode", "steps", "return", "lane changes", "outcome", "mean speed (m/s)"), rows)
        s = info["summary"]
        if s["finished_episodes"]:
            print(f"\n{s['finished_episodes']} finished episodes: mean return {s['mean_return']:.3f}, "
                  f"success {s['success_rate']:.0%}, collision {s['collision_rate']:.0%}")
    else:
        print("\nno episodes (no state/reward/episode topics of the der_ros graph in this bag)")
    return 0


def _table(header: tuple[str, ...], rows: list[tuple[str, ...]]) -> None:
    widths = [max([len(h)] + [len(r[i]) for r in rows]) for i, h in enumerate(header)]
    print("  ".join(h.ljust(w) for h, w in zip(header, widths)))
    print("  ".join("-" * w for w in widths))
    for r in rows:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)))


# -- plot / export / train / play -----------------------------------------------------------------


def _run_plot(args: argparse.Namespace) -> int:
    if args.label and len(args.label) != len(args.bags):
        print(f"der bag plot: {len(args.label)} --label for {len(args.bags)} bags", file=sys.stderr)
        return 2
    files = plot_bags(args.bags, args.out, labels=args.label, window=args.window, namespace=args.namespace)
    for f in files:
        print(f)
    return 0


def _run_export(args: argparse.Namespace) -> int:
    if args.to.suffix not in (".npz", ".parquet"):
        print(f"der bag export: --to {args.to}: expected a .npz or .parquet file name", file=sys.stderr)
        return 2
    obs_cfg = None
    if args.obs_config is not None:
        obs_cfg = load_yaml(args.obs_config, ObservationConfig)
    tr = build_transitions(BagReader(args.bag), obs_cfg, args.namespace)
    out = save_transitions(tr, args.to)
    print(f"{out}: {len(tr)} transitions from {int(tr.episode.max()) + 1 if len(tr) else 0} episodes"
          + (f" (skipped: {tr.skipped})" if tr.skipped else ""))
    return 0


def _run_train(args: argparse.Namespace) -> int:
    return run_train(args)


def _episode_span(text: str) -> tuple[int, int]:
    """``A-B`` -> (A, B) for ``--episodes``."""
    first, sep, last = text.partition("-")
    try:
        if not sep:
            raise ValueError
        return int(first), int(last)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--episodes {text!r}: expected A-B, two episode numbers (e.g. 3-5)") from None


def _run_render(args: argparse.Namespace) -> int:
    try:
        opts = RenderOptions(width=args.size, height=args.size, fps=args.fps, window=args.window)
    except ValueError as exc:
        print(f"der bag render: {exc}", file=sys.stderr)
        return 2
    result = render_bag(args.bag, args.to, args.episode, args.episodes, opts, args.namespace)
    eps = result.episodes
    which = f"episode {eps[0]}" if len(eps) == 1 else f"episodes {eps[0]}-{eps[-1]}"
    print(f"{result.path}: {result.frames} frames of {which} in {result.seconds:.1f} s")
    return 0


def _run_play(args: argparse.Namespace) -> int:
    try:
        from der_ros.offline.play import run_play  # lazy: rclpy, which only play needs
    except ImportError as exc:  # the reading tools work without ROS; play does not
        print(f"der bag play needs rclpy (ROS 2 Jazzy): {exc}", file=sys.stderr)
        return 1
    return run_play(args)

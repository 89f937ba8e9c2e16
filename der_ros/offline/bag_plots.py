"""PNG figures of one or more recorded bags, overlaid for comparison (matplotlib, Agg backend).

Figures (each written only when the bags hold the data for it):

* ``returns.png`` -- return per episode (dots) with a moving average (line);
* ``outcomes.png`` -- success / collision / time-limit rates per bag (grouped bars);
* ``interventions.png`` -- commands the safety node vetoed per episode (bags with ``safety/interventions``);
* ``speed.png`` -- ego speed over episode time for the last few episodes of each bag;
* ``der_replay.png`` -- DER statistics from ``agent/metrics``: ``replay/h2_fraction`` and
  the H2 weight statistics (``replay/h2_weight_*``), over time;
* ``metrics.png`` -- TD loss and episodic return from ``agent/metrics`` when recorded;
* ``topic_rates.png`` -- messages per second of every topic (any bag, also foreign ones).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from der_ros.bag.reader import BagReader
from der_ros.contract import EPISODE_ENDS
from der_ros.offline.episodes import BagScan, scan_bag

__all__ = ["plot_bags", "plot_scans", "moving_average"]

log = logging.getLogger(__name__)

_OUTCOMES = EPISODE_ENDS


def moving_average(x: np.ndarray, window: int) -> np.ndarray:
    """Trailing mean over up to ``window`` values (the first values average what exists)."""
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return x
    c = np.cumsum(np.insert(x, 0, 0.0))
    idx = np.arange(1, x.size + 1)
    lo = np.maximum(idx - window, 0)
    return (c[idx] - c[lo]) / (idx - lo)


def plot_bags(paths: Sequence[str | Path], out_dir: str | Path, labels: Sequence[str] | None = None,
              window: int = 10, namespace: str | None = None) -> list[Path]:
    """Scan each bag once and write the figures to ``out_dir``; returns the files written."""
    paths = [Path(p) for p in paths]
    labels = list(labels) if labels else [BagReader(p).name if p.exists() else p.name for p in paths]
    scans = [scan_bag(BagReader(p), namespace) for p in paths]
    return plot_scans(scans, labels, out_dir, window=window)


def plot_scans(scans: Sequence[BagScan], labels: Sequence[str], out_dir: str | Path, window: int = 10) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []

    def save(fig: object, name: str) -> None:
        path = out / name
        fig.savefig(path, dpi=110)  # type: ignore[attr-defined]
        plt.close(fig)  # type: ignore[arg-type]
        written.append(path)

    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    pairs = list(zip(scans, labels))

    finished = [[e for e in s.episodes if e.outcome != "incomplete"] for s in scans]
    if any(finished):
        fig, ax = plt.subplots(figsize=(8, 4.5))
        for i, ((_s, label), eps) in enumerate(zip(pairs, finished)):
            if not eps:
                continue
            c = colors[i % len(colors)]
            x = np.arange(1, len(eps) + 1)
            r = np.array([e.ret for e in eps], dtype=np.float64)
            ax.plot(x, r, ".", color=c, alpha=0.35)
            ax.plot(x, moving_average(r, window), "-", color=c, label=f"{label} ({window}-episode mean)")
        ax.set_xlabel("episode")
        ax.set_ylabel("return")
        ax.set_title("Return per episode")
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        save(fig, "returns.png")

        fig, ax = plt.subplots(figsize=(7, 4.5))
        width = 0.8 / max(1, len(scans))
        for i, ((_s, label), eps) in enumerate(zip(pairs, finished)):
            n = max(1, len(eps))
            rates = [sum(1 for e in eps if e.outcome == o) / n for o in _OUTCOMES]
            ax.bar(np.arange(len(_OUTCOMES)) + (i - (len(scans) - 1) / 2) * width, rates, width,
                   label=f"{label} (n={len(eps)})", color=colors[i % len(colors)])
        ax.set_xticks(np.arange(len(_OUTCOMES)), [o.replace("_", " ") for o in _OUTCOMES])
        ax.set_ylim(0, 1)
        ax.set_ylabel("fraction of finished episodes")
        ax.set_title("Episode outcomes")
        ax.legend()
        fig.tight_layout()
        save(fig, "outcomes.png")

    if any(s.vetoes for s in scans):  # a safety node was recorded: its vetoes per episode
        fig, ax = plt.subplots(figsize=(8, 4.5))
        for i, ((_s, label), eps) in enumerate(zip(pairs, finished)):
            if not eps:
                continue
            c = colors[i % len(colors)]
            x = np.arange(1, len(eps) + 1)
            n = np.array([e.interventions for e in eps], dtype=np.float64)
            ax.plot(x, n, ".", color=c, alpha=0.35)
            ax.plot(x, moving_average(n, window), "-", color=c, label=f"{label} ({window}-episode mean)")
        ax.set_xlabel("episode")
        ax.set_ylabel("vetoed commands")
        ax.set_title("Safety interventions per episode (lane changes replaced by keep lane)")
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        save(fig, "interventions.png")

    if any(e.speed.size for s in scans for e in s.episodes):
        fig, ax = plt.subplots(figsize=(8, 4.5))
        for i, (s, label) in enumerate(pairs):
            eps = [e for e in s.episodes if e.speed.size][-3:]
            for j, e in enumerate(eps):
                ax.plot(e.speed_t, e.speed, color=colors[i % len(colors)], alpha=0.4 + 0.2 * j,
                        label=f"{label}: episode {e.index}")
        ax.set_xlabel("time since episode start (s)")
        ax.set_ylabel("ego speed (m/s)")
        ax.set_title("Ego speed (last episodes of each bag)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
        fig.tight_layout()
        save(fig, "speed.png")

    der_keys = sorted({k for s in scans for k in s.metrics if k.startswith("replay/h2_")})
    if der_keys:
        fig, axes = plt.subplots(len(der_keys), 1, figsize=(8, 2.4 * len(der_keys)), sharex=True, squeeze=False)
        for ax, key in zip(axes[:, 0], der_keys):
            for i, (s, label) in enumerate(pairs):
                if key in s.metrics:
                    t, v = s.metrics[key]
                    ax.plot(t - (t[0] if t.size else 0.0), v, color=colors[i % len(colors)], label=label)
            ax.set_ylabel(key.split("/", 1)[1], fontsize="small")
            ax.grid(alpha=0.3)
        axes[0, 0].set_title("DER replay statistics (agent/metrics)")
        axes[0, 0].legend(fontsize="small")
        axes[-1, 0].set_xlabel("time since first metrics message (s)")
        fig.tight_layout()
        save(fig, "der_replay.png")

    other = [k for k in ("losses/td_loss", "charts/episodic_return") if any(k in s.metrics for s in scans)]
    if other:
        fig, axes = plt.subplots(len(other), 1, figsize=(8, 2.8 * len(other)), sharex=True, squeeze=False)
        for ax, key in zip(axes[:, 0], other):
            for i, (s, label) in enumerate(pairs):
                if key in s.metrics:
                    t, v = s.metrics[key]
                    ax.plot(t - (t[0] if t.size else 0.0), v, color=colors[i % len(colors)], label=label)
            ax.set_ylabel(key, fontsize="small")
            ax.grid(alpha=0.3)
        axes[0, 0].legend(fontsize="small")
        axes[-1, 0].set_xlabel("time since first metrics message (s)")
        fig.tight_layout()
        save(fig, "metrics.png")

    if any(s.rates for s in scans):
        fig, axes = plt.subplots(len(scans), 1, figsize=(8, 2.8 * len(scans)), squeeze=False)
        for ax, (s, label) in zip(axes[:, 0], pairs):
            for topic in sorted(s.rates):
                bins = s.rates[topic]
                t = np.arange(min(bins), max(bins) + 1)
                ax.step(t, [bins.get(int(k), 0) for k in t], where="post", label=topic)
            ax.set_title(f"{label}: messages per second", fontsize="medium")
            ax.set_ylabel("messages / s")
            ax.grid(alpha=0.3)
            ax.legend(fontsize="x-small", ncol=2)
        axes[-1, 0].set_xlabel("log time since the first message (s)")
        fig.tight_layout()
        save(fig, "topic_rates.png")

    if not written:
        log.warning("no figure: the bags hold none of the der_ros topics (state, reward, episode, agent/metrics)")
    return written

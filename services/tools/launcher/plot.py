"""The run as a picture (`--plot FILE.png`): one timeline of the whole mission; and a campaign's
arena from above (`falconry campaign --plot DIR`, `plot_arena`).

Top: every target — when it was first detected (open circle) and destroyed or captured (cross).
Then per UAV: the job manager's state as a coloured band, detections per second (bars) and the
distance to the nearest flying partner from ground truth (line, right axis). Drawn from the run
monitor's records with matplotlib's Agg backend (no display needed).
"""
from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the backend)
from matplotlib.patches import Patch  # noqa: E402

from services.lib.runtime.errors import UsageError  # noqa: E402
from services.tools.launcher.monitor import RunMonitor  # noqa: E402
from services.tools.viz.style import OTHER_STATE, STATE_COLORS, uav_color  # noqa: E402


def _rgb(color) -> tuple[float, float, float]:
    return tuple(c / 255 for c in color[:3])


def _state_spans(states: list[tuple[float, str]], end: float) -> list[tuple[float, float, str]]:
    """(start, length, state) of each stretch of the job manager's state."""
    spans = []
    for (t, state), following in zip(states, states[1:] + [(end, "")]):
        if following[0] > t:
            spans.append((t, following[0] - t, state))
    return spans


def plot_timeline(monitor: RunMonitor, path: str | Path, title: str, duration: float = 0.0) -> None:
    end = max(duration, monitor.mission_time, monitor.latest, 1.0)
    names = sorted(monitor.uavs)
    rows = [1.2 + 0.25 * len(monitor.targets)] + [r for _ in names for r in (0.5, 2.0)]
    figure, axes = plt.subplots(len(rows), 1, sharex=True, figsize=(12, 1.2 + sum(rows) * 0.9),
                                gridspec_kw={"height_ratios": rows, "hspace": 0.15})
    axes = list(axes) if len(rows) > 1 else [axes]
    _targets(axes[0], monitor)
    seen_states: set[str] = set()
    for i, name in enumerate(names):
        band, data = axes[1 + 2 * i], axes[2 + 2 * i]
        seen_states |= _states(band, name, monitor.uavs[name].states, end)
        _activity(data, name, i, monitor, end)
        for t, _target, _by in monitor.destroyed:
            data.axvline(t, color="0.3", linewidth=0.8, linestyle=":")
    axes[-1].set_xlabel("mission time (s)")
    axes[-1].set_xlim(0, end)
    legend = [Patch(color=_rgb(STATE_COLORS.get(s, OTHER_STATE)), label=s) for s in STATE_COLORS if s in seen_states]
    if legend:
        figure.legend(handles=legend, loc="lower center", ncol=min(len(legend), 5), fontsize=8, frameon=False)
    figure.suptitle(title, fontsize=11)
    figure.subplots_adjust(left=0.09, right=0.91, top=0.93, bottom=0.06 + 0.02 * ((len(legend) + 4) // 5))
    _save(figure, path)


def _save(figure, path: str | Path) -> None:
    """Write the figure as a PNG (a path that cannot be written is one line) and free it."""
    try:
        figure.savefig(path, dpi=110)
    except OSError as exc:
        raise UsageError(f"cannot write the plot {path}: {exc.strerror or exc}") from None
    finally:
        plt.close(figure)


def _targets(ax, monitor: RunMonitor) -> None:
    ids = sorted(monitor.targets)
    done = {tid: (t, by) for t, tid, by in monitor.destroyed}
    for row, tid in enumerate(ids):
        kind = monitor.targets[tid][0]
        first = monitor.first_detected.get(tid)
        if first and tid in done:
            ax.plot([first[0], done[tid][0]], [row, row], color="0.6", linewidth=2)
        if first:
            ax.plot(first[0], row, "o", mfc="white", mec="0.2", ms=6)
        if tid in done:
            ax.plot(done[tid][0], row, "x", color="darkred", ms=8, mew=2)
            ax.annotate(f"{'destroyed' if kind == 'balloon' else 'captured'} by {done[tid][1]}", (done[tid][0], row),
                        xytext=(6, -3), textcoords="offset points", fontsize=7)
    ax.set_yticks(range(len(ids)), ids, fontsize=8)
    ax.set_ylim(-0.7, max(len(ids), 1) - 0.3)
    ax.set_title("targets: o first detected, x destroyed / captured", fontsize=8, loc="left")
    ax.grid(axis="x", alpha=0.3)


def _states(ax, name: str, states: list[tuple[float, str]], end: float) -> set[str]:
    spans = _state_spans(states, end)
    for start, length, state in spans:
        ax.broken_barh([(start, length)], (0, 1), color=_rgb(STATE_COLORS.get(state, OTHER_STATE)))
    ax.set_yticks([0.5], [f"{name} state"], fontsize=8)
    ax.set_ylim(0, 1)
    return {state for _, _, state in spans}


def _activity(ax, name: str, index: int, monitor: RunMonitor, end: float) -> None:
    u = monitor.uavs[name]
    per_second: dict[int, int] = defaultdict(int)
    for t, count in u.detection_counts:
        per_second[int(t)] += count
    color = _rgb(uav_color(index))
    if per_second:
        seconds = sorted(per_second)
        ax.bar(seconds, [per_second[s] for s in seconds], width=1.0, align="edge", color=color, alpha=0.45)
    ax.set_ylabel("detections/s", fontsize=8)
    ax.set_ylim(bottom=0, top=max(per_second.values(), default=0) * 1.1 + 1)
    ax.grid(axis="x", alpha=0.3)
    partner = ax.twinx()
    if u.nearest_partner:
        times, gaps = zip(*u.nearest_partner)
        partner.plot(times, gaps, color="black", linewidth=1.0)
        low = min(range(len(gaps)), key=gaps.__getitem__)
        partner.annotate(f"{gaps[low]:.1f} m", (times[low], gaps[low]), xytext=(3, 3), textcoords="offset points",
                         fontsize=7)
        partner.set_ylim(0, max(gaps) * 1.15)
    partner.set_ylabel("nearest partner (m)", fontsize=8)
    ax.set_xlim(0, end)


def plot_curves(path: str | Path, x, curves: dict[str, list[float]], xlabel: str, ylabel: str, title: str,
                ylim: tuple[float, float] | None = (0.0, 1.02)) -> None:
    """Curves over a common x axis, one per label (analyses and benchmarks)."""
    figure, ax = plt.subplots(figsize=(9, 5))
    for label, values in curves.items():
        ax.plot(x, values, marker="o", markersize=3, label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if ylim is not None:
        ax.set_ylim(*ylim)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=10)
    try:
        figure.savefig(path, dpi=110, bbox_inches="tight")
    except OSError as exc:
        raise UsageError(f"cannot write the plot {path}: {exc.strerror or exc}") from None
    finally:
        plt.close(figure)


def plot_arena(scenario, summaries: list[dict], path: str | Path, title: str) -> None:
    """The scenario's arena from above — outline, obstacles, balloons, the drones' paths, the
    starts — and every attack and interception the runs' summaries list, at the point it aimed at:
    a dot when it aimed at a target, a red cross when at none."""
    import numpy as np
    from matplotlib.patches import Circle, Polygon, Rectangle

    fig, ax = plt.subplots(figsize=(9, 7))
    ax.add_patch(Polygon(np.asarray(scenario.arena), closed=True, fill=False, edgecolor="black", linewidth=1.5))
    for o in scenario.obstacles:
        face = "0.55" if o.surveyed else "0.8"
        if o.kind == "box":
            ax.add_patch(Rectangle((o.center[0] - o.size[0] / 2, o.center[1] - o.size[1] / 2), o.size[0], o.size[1],
                                   facecolor=face, edgecolor="0.3"))
        else:
            ax.add_patch(Circle(o.center[:2], o.radius, facecolor=face, edgecolor="0.3"))
    for b in scenario.balloons:
        ax.plot(*b.pole, marker="o", color="tab:orange", markersize=6, linestyle="none")
    for d in scenario.drones:
        if d.center is not None and d.radius > 0:
            ax.add_patch(Circle(d.center[:2], d.radius, fill=False, edgecolor="tab:purple", linestyle="--"))
        if d.waypoints:
            w = np.asarray(d.waypoints)
            ax.plot(w[:, 0], w[:, 1], color="tab:purple", linestyle="--", linewidth=1)
    for k, start in enumerate(scenario.starts or []):
        ax.plot(start[0], start[1], marker="^", color=_rgb(uav_color(k)), markersize=9, linestyle="none")
    hits, misses = [], []
    for summary in summaries:
        for uav in summary.get("uavs", {}).values():
            for e in uav.get("engagements", []):
                (misses if e.get("target") is None else hits).append(e["aim"][:2])
    if hits:
        ax.plot(*np.asarray(hits).T, marker=".", color="tab:green", linestyle="none", label=f"aimed at a target ({len(hits)})")
    if misses:
        ax.plot(*np.asarray(misses).T, marker="x", color="red", markersize=9, linestyle="none",
                label=f"aimed at no target ({len(misses)})")
    ax.plot([], [], marker="o", color="tab:orange", linestyle="none", label="balloon")
    ax.plot([], [], color="tab:purple", linestyle="--", label="drone path")
    ax.plot([], [], marker="^", color="0.3", linestyle="none", label="start")
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel("x, m (east)")
    ax.set_ylabel("y, m (north)")
    ax.set_title(title)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    _save(fig, path)

"""Figures: space-time contours of PDE episodes, state trajectories of ODE episodes."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt
import numpy as np

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from .simulate import EpisodeRecord

from .fileio import new_file_mode

__all__ = ["STATE_LABELS", "draw_curves", "plot_episode", "plot_learning_curves", "plot_spacetime", "save_figure", "seed_band"]

STATE_LABELS = {
    "pimbrl/CartPole-v0": ["x", "x_dot", "theta", "theta_dot"],
    "pimbrl/Pendulum-v0": ["theta", "theta_dot"],
}


def save_figure(fig: Figure, path: str | os.PathLike, dpi: int = 110) -> Path:
    """Save ``fig`` as PNG atomically (temporary file, then rename) and close it.

    The caller lays the figure out (``fig.tight_layout()``, as every figure of pimbrl does); the save draws it
    once: ``bbox_inches="tight"`` would draw it a second time to crop what the layout already fitted (about a
    fifth of a learning-curve plot's time).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".png.tmp")
    if hasattr(os, "fchmod"):  # the mode of a new file (0o666 less the umask), not the temporary's 0600
        os.fchmod(fd, new_file_mode())
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=dpi, format="png")
        os.replace(tmp, path)
    finally:
        plt.close(fig)
        if os.path.exists(tmp):
            os.remove(tmp)
    return path


def plot_spacetime(
    ax: Axes,
    field: np.ndarray,
    x: np.ndarray,
    control_dt: float,
    title: str = "",
    vlim: float | None = None,
    cmap: str = "RdBu_r",
) -> None:
    """Filled contours of ``field`` (``(T+1, n)``, one row per control step) with time on the horizontal axis.

    A signed field gets symmetric levels on a diverging map (``vlim`` fixes them, to compare panels);
    a one-signed field its own range on a sequential map.
    """
    t = np.arange(field.shape[0]) * control_dt
    lo, hi = float(np.min(field)), float(np.max(field))
    if vlim is not None or (lo < 0 < hi):  # signed field: symmetric levels on a diverging map
        lim = max(abs(lo), abs(hi)) if vlim is None else vlim
        levels = np.linspace(-lim, lim, 41)
    else:  # one-signed field (e.g. Burgers velocity): its own range on a sequential map
        levels = np.linspace(lo, hi if hi > lo else lo + 1e-12, 41)
        cmap = "viridis"
    cs = ax.contourf(t, x, field.T, levels=levels, cmap=cmap, extend="both")
    ax.figure.colorbar(cs, ax=ax, pad=0.01)
    ax.set_xlabel("time")
    ax.set_ylabel("x")
    if title:
        ax.set_title(title)


def plot_episode(
    record: EpisodeRecord,
    path: str | os.PathLike,
    x: np.ndarray | None = None,
    field_offset: Sequence[float] | np.ndarray | None = None,
) -> Path:
    """Plot one episode to ``path`` and return the path written.

    The top panel is a space-time contour for fields (``x`` given), else state curves; actions and
    rewards are below. ``field_offset`` (per control step) is subtracted from a field, e.g. a reference
    to show the tracking error.
    """
    t_state = np.arange(record.states.shape[0]) * record.control_dt
    t_act = np.arange(record.length) * record.control_dt
    if x is not None:
        fig, axes = plt.subplots(3, 1, figsize=(10, 8), gridspec_kw={"height_ratios": [3, 1, 1]}, sharex=False)
        field = record.states if field_offset is None else record.states - np.asarray(field_offset)[:, None]
        plot_spacetime(axes[0], field, x, record.control_dt, title=f"{record.env_id}: return {record.total_return:.2f}")
    else:
        fig, axes = plt.subplots(3, 1, figsize=(10, 7), sharex=True)
        labels = STATE_LABELS.get(record.env_id, [f"s{i}" for i in range(record.states.shape[1])])
        for i in range(record.states.shape[1]):
            axes[0].plot(t_state, record.states[:, i], label=labels[i] if i < len(labels) else f"s{i}")
        axes[0].legend(loc="upper right", fontsize=8)
        axes[0].set_title(f"{record.env_id}: return {record.total_return:.2f}")
        axes[0].set_ylabel("state")
    actions = record.actions.reshape(record.length, -1) if record.length else np.zeros((0, 1))
    for i in range(actions.shape[1]):
        axes[1].step(t_act, actions[:, i], where="post", label=f"a{i + 1}", lw=1)
    axes[1].set_ylabel("action")
    if actions.shape[1] > 1:
        axes[1].legend(loc="upper right", fontsize=8, ncol=actions.shape[1])
    axes[2].plot(t_act, record.rewards, lw=1, color="k")
    axes[2].set_ylabel("reward")
    axes[2].set_xlabel("time")
    fig.tight_layout()
    return save_figure(fig, path)


def seed_band(
    label: str, curves: Sequence[dict[str, Sequence[float]]]
) -> tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One curve from several seeds' evaluations, as ``(label, steps, mean, low, high)``.

    Each evaluation is a dict with ``step``, ``return_mean``, ``return_min`` and ``return_max``. The curve
    is the mean over seeds of the mean return, and the band runs from the lowest to the highest test
    episode of any seed, over the steps all seeds reached.
    """
    n = min(len(c["step"]) for c in curves)
    return (
        f"{label} ({len(curves)} seed{'s' if len(curves) > 1 else ''})",
        np.asarray(curves[0]["step"][:n]),
        np.mean([np.asarray(c["return_mean"][:n]) for c in curves], axis=0),
        np.min([np.asarray(c["return_min"][:n]) for c in curves], axis=0),
        np.max([np.asarray(c["return_max"][:n]) for c in curves], axis=0),
    )


def draw_curves(
    ax: Axes,
    curves: Sequence[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    thresholds: Sequence[float] = (),
    colors: Sequence[Any] | None = None,
    legend_loc: str = "lower right",
) -> list[Any]:
    """Draw each ``(label, steps, mean, low, high)`` on ``ax`` as a line with a band; the colours used.

    ``colors`` (one per curve) fixes them, e.g. to match another panel; by default the axes' cycle picks.
    Each threshold is a dashed horizontal line; the grid and a legend (if anything is labelled) are added.
    """
    used = []
    for i, (label, steps, mean, low, high) in enumerate(curves):
        (line,) = ax.plot(steps, mean, label=label, lw=1.6, color=None if colors is None else colors[i])
        ax.fill_between(steps, low, high, color=line.get_color(), alpha=0.18, lw=0)
        used.append(line.get_color())
    for threshold in thresholds:
        ax.axhline(threshold, color="k", ls="--", lw=0.8, label=f"threshold {threshold:g}")
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc=legend_loc, fontsize=8)  # type: ignore[call-overload]  # loc: any matplotlib location string
    return used


def plot_learning_curves(
    curves: Sequence[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    path: str | os.PathLike,
    title: str = "",
    threshold: float | None = None,
    xlabel: str = "real environment steps",
    band: str = "band: lowest to highest test episode",
) -> Path:
    """Learning curves as the paper draws them, one per ``(label, steps, mean, low, high)``.

    The mean test return is drawn as a line and the min-max range of the test episodes as a band; ``band``
    says what the band is, under the axis.
    """
    fig, ax = plt.subplots(figsize=(8, 5))
    draw_curves(ax, curves, () if threshold is None else (threshold,))
    ax.set_xlabel(f"{xlabel}\n({band})" if band else xlabel)
    ax.set_ylabel("mean test return")
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return save_figure(fig, path)

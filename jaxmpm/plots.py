"""Plots and particle videos (matplotlib, off-screen)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def loss_curve(path: str | Path, losses, title: str = "fit") -> Path:
    """Loss per iteration on a log axis, saved as PNG."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=120)
    ax.semilogy(np.arange(len(losses)), np.maximum(np.asarray(losses, float), 1e-30), "o-", ms=3)
    ax.set_xlabel("accepted iteration")
    ax.set_ylabel("mean squared track error (m²)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


def iou_curves(path: str | Path, iou, times, title: str = "observed vs simulated silhouettes") -> Path:
    """Silhouette IoU ``(V, T)`` against time ``(T,)`` (s), one line per view, saved as PNG."""
    iou = np.asarray(iou, float)
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=120)
    for v, row in enumerate(iou):
        ax.plot(np.asarray(times, float), row, "o-", ms=3, label=f"view {v}")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("IoU")
    ax.set_ylim(min(0.5, float(np.nanmin(iou)) - 0.05) if iou.size else 0.5, 1.0)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


def particle_frames(positions: np.ndarray, model, overlay: np.ndarray | None = None, size: int = 360) -> np.ndarray:
    """Render particle positions ``(T, N, D)`` to RGB frames ``(T, H, W, 3)`` uint8.

    3D scenes are shown from the front (x right, y up), coloured by depth z; 2D as is.
    ``overlay`` (same shape) is drawn as hollow circles, e.g. a fitted simulation.
    """
    plt = _pyplot()
    lo, hi = np.asarray(model.grid.lo), np.asarray(model.grid.hi)
    frames = []
    dpi = 100
    for t in range(positions.shape[0]):
        fig = plt.figure(figsize=(size / dpi, size / dpi), dpi=dpi)
        ax = fig.add_axes([0, 0, 1, 1])
        p = positions[t]
        colour = p[:, 2] if p.shape[1] == 3 else "tab:blue"
        ax.scatter(p[:, 0], p[:, 1], s=3, c=colour, cmap="viridis", linewidths=0)
        if overlay is not None:
            q = overlay[t]
            ax.scatter(q[:, 0], q[:, 1], s=8, facecolors="none", edgecolors="tab:red", linewidths=0.4)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.text(0.02, 0.96, f"t = {t * model.frame_dt:.3f} s", transform=ax.transAxes, va="top", fontsize=8)
        fig.canvas.draw()
        image = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
        plt.close(fig)
        frames.append(image)
    return np.stack(frames)


def particle_video(path: str | Path, positions: np.ndarray, model, overlay: np.ndarray | None = None) -> Path:
    """A video of the particles (see :func:`particle_frames`)."""
    fps = max(1, round(1.0 / model.frame_dt))
    from .render import write_video

    return write_video(path, particle_frames(np.asarray(positions), model, overlay), fps=fps)

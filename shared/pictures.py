"""Pictures of a merged fleet map: a top-down overview and the overlap matrix (matplotlib,
no screen needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def n_cascade(report) -> int:
    """Keyframe pairs the place database verified (not those added once aligned)."""
    return sum(o.get("source", "cascade") == "cascade" for o in report["overlaps"])


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _top_down_basis(points: np.ndarray, downs) -> np.ndarray:
    """Two axes (3, 2) spanning the floor plane. Gravity: the mean image-down axis of the
    cameras, when they agree (upright cameras on robots or in hands); otherwise the
    points' axis of least spread."""
    c = points - points.mean(0)
    down = np.mean(downs, axis=0) if len(downs) else np.zeros(3)
    if np.linalg.norm(down) > 0.5:
        g = down / np.linalg.norm(down)
        flat = c - np.outer(c @ g, g)
        _, V = np.linalg.eigh(np.cov(flat.T))
        u = V[:, 2]
        return np.stack([u, np.cross(g, u)], axis=1)
    _, V = np.linalg.eigh(np.cov(c.T))
    return V[:, [2, 1]]


def overview(path, pts, tracks, names, colours, links, report, downs=(), title=None) -> None:
    """Top-down picture: map points per robot, trajectories, overlap links (grey). `path`:
    a file name or a binary file object (PNG)."""
    plt = _plt()
    allp = np.concatenate(pts)
    c = allp.mean(0)
    basis = _top_down_basis(allp, downs)
    fig, ax = plt.subplots(figsize=(8, 8), dpi=110)
    for p, name, colour in zip(pts, names, colours, strict=True):
        uv = (p[:: max(1, len(p) // 20000)] - c) @ basis
        ax.scatter(uv[:, 0], uv[:, 1], s=0.3, color=colour, alpha=0.4)
        tr = (tracks[name] - c) @ basis
        ax.plot(tr[:, 0], tr[:, 1], "-o", ms=2, color=colour * 0.7, label=name)
    for pa, pb in links:
        uv = (np.stack([pa, pb]) - c) @ basis
        ax.plot(uv[:, 0], uv[:, 1], "-", color="0.3", lw=0.6, alpha=0.6)
    ax.set_aspect("equal")
    ax.set_xlabel("m (floor plane, first axis)")
    ax.set_ylabel("m (floor plane, second axis)")
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.legend(loc="best")
    left = report.get("unmerged", [])  # the live map's has none
    unmerged = f" ({', '.join(left)} not: report.json says why)" if left else ""
    ax.set_title(
        title
        or f"fleetmap: {len(names)} of {len(names) + len(left)} robots merged{unmerged}, "
        f"{n_cascade(report)} verified + {len(report['overlaps']) - n_cascade(report)} "
        "co-visible keyframe pairs (verified in grey)\n"
        f"reference frame: {report['reference']}'s map",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, format="png")
    plt.close(fig)


def overlap_matrix(path: Path, names: list[str], report) -> None:
    """Verified keyframe pairs between every two robots, as a matrix (thesis Fig. 1.1)."""
    plt = _plt()
    k = {n: i for i, n in enumerate(names)}
    M = np.zeros((len(names), len(names)), int)
    for o in report["overlaps"]:
        i, j = k[o["robot_a"]], k[o["robot_b"]]
        M[i, j] += 1
        M[j, i] += 1
    fig, ax = plt.subplots(figsize=(1.2 + 0.6 * len(names), 1 + 0.6 * len(names)), dpi=110)
    ax.imshow(M, cmap="Blues")
    for i in range(len(names)):
        for j in range(len(names)):
            ax.text(
                j,
                i,
                str(M[i, j]),
                ha="center",
                va="center",
                color="white" if M[i, j] > M.max() / 2 else "black",
            )
    ax.set_xticks(range(len(names)), names, rotation=45, ha="right")
    ax.set_yticks(range(len(names)), names)
    ax.set_title("keyframe pairs: verified + co-visible once aligned", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)

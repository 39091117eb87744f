"""
Figures in the style of the paper's Fig. 3 and Fig. 4, from loop histories (no ROS).

matplotlib with the headless Agg backend.

``fig3(t, e, v, labels, path)``     feature errors and camera velocities (m/s, deg/s)
``fig4(runs, path)``                camera trajectory in the desired frame and image
                                    trajectories of b and the marks, one line per run
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from sphere_servo.sim.loop import LoopResult  # noqa: E402


def plot_errors(ax, t: np.ndarray, e: np.ndarray, labels, fontsize: int = 8) -> None:
    """Each column of ``e`` (N, n) against ``t``, labelled, with legend and grid."""
    for i in range(e.shape[1]):
        ax.plot(t, e[:, i], label=labels[i] if i < len(labels) else f'e{i}')
    ax.legend(fontsize=fontsize, ncol=2)
    ax.grid(alpha=0.3)


def plot_twist(ax, t: np.ndarray, v: np.ndarray, fontsize: int = 8):
    """
    Plot camera twists (N, 6): translation (m/s) on ``ax``, rotation on a twin axis.

    The rotation (deg/s) is dashed; one legend for both. Returns the twin axis.
    """
    names = ('v_x (m/s)', 'v_y (m/s)', 'v_z (m/s)', 'ω_x (deg/s)', 'ω_y (deg/s)', 'ω_z (deg/s)')
    axb = ax.twinx()
    for i in range(3):
        ax.plot(t, v[:, i], label=names[i])
        axb.plot(t, np.degrees(v[:, 3 + i]), '--', label=names[3 + i])
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = axb.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, fontsize=fontsize, ncol=2)
    ax.grid(alpha=0.3)
    return axb


def save(fig, path: str | Path, title: str = '', dpi: int = 110) -> Path:
    """Title, tight layout, write the PNG, close the figure."""
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def shrink_png(path: Path, colors: int = 96) -> Path:
    """Quantize a PNG to a palette (figures are line plots: 3–5× smaller, same look)."""
    from PIL import Image
    im = Image.open(path).convert('RGB')
    im.quantize(colors=colors, method=Image.Quantize.MEDIANCUT).save(path, optimize=True)
    return path


def fig3(t: np.ndarray, e: np.ndarray, v: np.ndarray, labels, path: str | Path,
         title: str = '') -> Path:
    """
    Draw the paper's Fig. 3: (a) feature error s − s* over time, (b) camera velocities.

    The velocities (translation m/s, rotation deg/s) are in the camera frame.
    """
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    plot_errors(ax1, t, e, labels)
    ax1.set_xlabel('time (s)')
    ax1.set_ylabel('s − s* (position parts: 1, rotation parts: rad)')
    ax1.set_title('(a) feature error')
    ax2b = plot_twist(ax2, t, v)
    ax2.set_xlabel('time (s)')
    ax2.set_ylabel('translational velocity (m/s)')
    ax2b.set_ylabel('rotational velocity (deg/s)')
    ax2.set_title('(b) camera velocities (camera frame)')
    return save(fig, path, title)


def _image_xy(u: np.ndarray) -> np.ndarray:
    """
    Map unit vectors (N, 3) to normalized image coordinates (N, 2).

    In metres at unit focal length: the paper plots image trajectories in m.
    """
    return u[:, :2] / u[:, 2:3]


@dataclass
class Trajectory:
    """
    What Fig. 4 draws for one run.

    The camera centre (N, 3) in the *desired camera frame*, and unit vectors (camera frame)
    of b and of the marks, by name.
    """

    positions: np.ndarray
    b: np.ndarray
    marks: dict


def trajectory_from_loop(res: LoopResult) -> Trajectory:
    """:class:`Trajectory` of a headless :class:`LoopResult`."""
    cdMo = np.linalg.inv(res.oMc_desired)
    pts = np.einsum('ij,nj->ni', cdMo[:3, :3], res.positions) + cdMo[:3, 3]
    return Trajectory(pts, res.b, res.q)


def fig4(runs: dict, path: str | Path, title: str = '') -> Path:
    """
    Draw the paper's Fig. 4 for each run (name → :class:`Trajectory` or LoopResult).

    (a) camera trajectory (m) in the desired camera frame, (b) image trajectory of b,
    (c) of P1, (d) of the second mark (P2 or P3).
    """
    fig = plt.figure(figsize=(13, 4))
    ax = fig.add_subplot(1, 4, 1, projection='3d')
    axes = [fig.add_subplot(1, 4, k) for k in (2, 3, 4)]
    second = None
    for name, run in runs.items():
        tr = trajectory_from_loop(run) if isinstance(run, LoopResult) else run
        pts = tr.positions
        ax.plot(pts[:, 0], pts[:, 1], pts[:, 2], label=name)
        ax.scatter(*pts[0], marker='o', s=15)
        ax.scatter(*pts[-1], marker='x', s=25)
        axes[0].plot(*_image_xy(tr.b).T, label=name)
        marks = sorted(tr.marks)
        if marks:
            axes[1].plot(*_image_xy(tr.marks[marks[0]]).T, label=name)
        if len(marks) > 1:
            second = marks[1]
            axes[2].plot(*_image_xy(tr.marks[marks[1]]).T, label=name)
    ax.set_xlabel('x (m)')
    ax.set_ylabel('y (m)')
    ax.set_zlabel('z (m)')
    ax.set_title('(a) camera trajectory\n(desired frame)')
    for a, lab in zip(axes, ('(b) b', '(c) P1', f'(d) {second or "P2/P3"}')):
        a.set_title(f'{lab} in the image')
        a.set_xlabel('x (m)')
        a.set_ylabel('y (m)')
        a.invert_yaxis()
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    return save(fig, path, title)

"""What a replay shows: its summary lines, and the plots of its errors, trajectory and matches."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io.outputs import save_figure, save_image
from .scoring import Run


def chain_trajectory(run: Run) -> tuple[np.ndarray, np.ndarray]:
    """Estimated and ground-truth camera positions; each estimated step scaled to the GT step length."""
    est, gt, T_est, T_gt_prev = [], [], None, None
    for s in run.steps:
        if (T := s.T) is None:
            continue
        if T_est is None:
            T_est = T.copy()
        else:
            step = np.eye(4)
            if s.R is not None and s.status in ("ok", "no_motion"):  # no_motion: the rotation, t = 0
                scale = np.linalg.norm((np.linalg.inv(T_gt_prev) @ T)[:3, 3])
                step[:3, :3] = s.R.T  # T_prev_cur = inv([R | t])
                step[:3, 3] = -s.R.T @ s.t * scale
            T_est = T_est @ step
        T_gt_prev = T
        est.append(T_est[:3, 3].copy())
        gt.append(T[:3, 3].copy())
    return np.array(est), np.array(gt)


PLOTS = ("errors", "trajectory", "matches")  # the plots' names, each a .png


def write_plots(runs: list[Run], overlay: np.ndarray | None, out_dir: Path, prefix: str = "") -> list[Path]:
    """Per-frame errors and trajectory (top view) where ground truth scored any pair, and the match overlay,
    as ``out_dir/<prefix>errors.png``, ``trajectory.png`` and ``matches.png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    scored = [run for run in runs if run.scores.errors]
    if scored:  # without ground truth there is nothing to draw: no empty figures
        fig, ax = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
        for run in scored:
            e = np.array(run.scores.errors)
            ax[0].plot(run.scores.stamps, e[:, 0], ".-", label=run.name)
            ax[1].plot(run.scores.stamps, e[:, 1], ".-", label=run.name)
        ax[0].set_ylabel("rotation error (deg)")
        ax[1].set_ylabel("translation dir. error (deg)")
        ax[1].set_xlabel("time (s)")
        for a in ax:
            a.grid(alpha=0.3)
            a.legend(fontsize=8)
        paths.append(save_figure(fig, out_dir / f"{prefix}errors.png"))

    chains = [(run, *chain_trajectory(run)) for run in runs]
    chains = [(run, est, gt) for run, est, gt in chains if len(gt) > 1]  # a path: two positions or more
    if chains:
        fig, ax = plt.subplots(figsize=(6, 5))
        gt = chains[0][2]
        ax.plot(gt[:, 0], gt[:, 2], "k-", lw=2, label="ground truth")
        for run, est, _ in chains:
            ax.plot(est[:, 0], est[:, 2], ".-", label=f"{run.name} (scale from GT)")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("z (m)")
        ax.axis("equal")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        paths.append(save_figure(fig, out_dir / f"{prefix}trajectory.png"))
    if overlay is not None:
        paths.append(save_image(out_dir / f"{prefix}matches.png", overlay))
    return paths


def print_summary(s: dict, name: str) -> None:
    """Human-readable summary of one run."""
    line = f"{name}: {s['processed']}/{s['frames']} frames at {s['fps']:.2f} fps, {s['matches_per_frame']:.0f} matches and " \
           f"{s['selected_per_frame']:.0f} selected per frame"
    print(line)
    print_tracks(s["tracks"])
    print_scores(s)


def print_tracks(t: dict) -> None:
    """The summary's feature tracks (``~/matches``' track_id), offline and live alike."""
    if t["count"]:
        print(f"   tracks: {t['count']}, seen in {t['mean_frames']:.1f} frames on average, {t['share_5_frames']:.1f} % in 5 "
              f"or more, the longest in {t['longest']}")


def print_scores(s: dict) -> None:
    """The summary's errors against ground truth (offline and live alike), when any pair was scored."""
    if s["median_rot_deg"] is not None:
        print(f"   vs ground truth ({s['scored_pairs']} pairs): median rotation error {s['median_rot_deg']:.3f} deg, translation "
              f"{s['median_trans_deg']:.2f} deg, AUC@5/10/20 {s['auc5']:.1f} / {s['auc10']:.1f} / {s['auc20']:.1f}")
        if s["fitted_pose_sigma_rotation_deg"] is not None:
            print(f"   the published covariance would fit these errors with pose_sigma_rotation_deg "
                  f"{s['fitted_pose_sigma_rotation_deg']:.3g} and pose_sigma_direction {s['fitted_pose_sigma_direction']:.3g}")
    if s["still_pairs"]:
        print(f"   without motion in the ground truth ({s['still_pairs']} pairs: standing, or turning on the spot): "
              f"median rotation error {s['median_still_rot_deg']:.3f} deg")

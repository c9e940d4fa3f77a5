"""EuRoC's ASL folder layout, read as a sequence folder, so that ``nmnet eval`` and ``train`` take a EuRoC MAV
download (or any dataset in that layout) as it is.

The layout: ``mav0/cam0/data.csv`` ('timestamp [ns],filename', the images in ``cam0/data/``),
``mav0/cam0/sensor.yaml`` (the calibration and ``T_BS``, the camera's pose on the body) and
``mav0/state_groundtruth_estimate0/data.csv`` (the body's pose in the world, stamped in nanoseconds, quaternion w
first). The camera's pose is the body's composed with ``T_BS``, as EuRoC defines it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from ..interface.params import yaml_problem
from .trajectory import DatasetError, Trajectory, Unfit, pose_problem, poses_from_xyzq, read_table

GROUND_TRUTH = Path("state_groundtruth_estimate0") / "data.csv"


def camera_folder(root: Path) -> Path | None:
    """The ASL camera folder under ``root`` (the download's folder, its ``mav0`` or ``mav0/cam0`` itself), or None."""
    return next((d for d in (root / "mav0" / "cam0", root / "cam0", root)
                 if (d / "data.csv").is_file() and (d / "data").is_dir()), None)


def read_frames(cam: Path) -> tuple[np.ndarray, list[Path]]:
    """The camera's stamps (seconds) and image paths from its data.csv."""
    rows = read_table(cam / "data.csv", "timestamp [ns],filename",
                      lambda r: (int(r[0]) * 1e-9, cam / "data" / r[1].strip()), sep=",")
    if not rows:
        raise DatasetError(f"{cam / 'data.csv'}: no frames listed")
    return np.array([s for s, _ in rows]), [p for _, p in rows]


def body_to_camera(sensor_yaml: Path) -> np.ndarray:
    """``T_BS`` of a camera's sensor.yaml (4x4): the camera's pose on the body whose poses the ground truth gives."""
    try:
        data = yaml.safe_load(sensor_yaml.read_text())["T_BS"]["data"]
        T = np.array(data, np.float64).reshape(4, 4)
    except yaml.YAMLError as e:
        raise DatasetError(f"{sensor_yaml}: not valid YAML ({yaml_problem(e)})") from e
    except (OSError, KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{sensor_yaml}: no T_BS (the camera's pose on the body, 16 numbers) to place the camera "
                           f"on the ground truth's body ({type(e).__name__}: {e})") from e
    if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-4):
        raise DatasetError(f"{sensor_yaml}: T_BS is not a rigid transform (a rotation and a translation, last row "
                           "0 0 0 1)")
    return T


def _body_row(fields: list[str]) -> list[float]:
    """A ground-truth row: stamp in seconds, then 'tx ty tz qx qy qz qw' (TUM's order; ASL writes qw first)."""
    if len(fields) < 8:
        raise ValueError(f"{len(fields)} fields")
    ns, x, y, z, qw, qx, qy, qz = (float(f) for f in fields[:8])
    if (why := pose_problem([x, y, z, qx, qy, qz, qw])) is not None:
        raise Unfit(why)
    return [ns * 1e-9, x, y, z, qx, qy, qz, qw]


def read_ground_truth(mav: Path, sensor_yaml: Path) -> Trajectory | None:
    """The camera's poses from ``mav/state_groundtruth_estimate0/data.csv``, the body's composed with the camera's
    ``T_BS`` (None when the folder has no ground truth)."""
    path = mav / GROUND_TRUTH
    if not path.is_file():
        return None
    T_BS = body_to_camera(sensor_yaml)
    rows = read_table(path, "timestamp [ns], p_RS_R x y z [m], q_RS w x y z, ...", _body_row, sep=",")
    if not rows:
        raise DatasetError(f"{path}: no poses")
    a = np.array(rows, np.float64)
    return Trajectory(a[:, 0], poses_from_xyzq(a[:, 1:8])).moved(T_BS)

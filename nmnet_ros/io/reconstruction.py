"""Camera poses of an unlabeled recording, by structure from motion: COLMAP (global or incremental) through pycolmap.

What ``nmnet label`` builds on: a robot team rarely has ground-truth poses, but epipolar labels need poses up to
scale only, which a reconstruction of the recording's own frames gives. The calibration is held fixed (the
robot's camera_info; or refined, and returned with the poses), COLMAP's SIFT features are matched between
neighbouring keyframes, and the largest connected model is kept. :func:`quality_problem` says when a
reconstruction cannot be trusted.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..core.geometry import Camera


class ReconstructionError(ValueError):
    """A recording that cannot be reconstructed, or whose reconstruction cannot be trusted: says why and what to do."""


@dataclass
class Reconstruction:
    """The largest model COLMAP made of the keyframes."""

    poses: dict[str, np.ndarray]  # image name -> T_WC, the camera-to-world pose (4x4); registered images only
    images: int  # keyframes given
    mean_reprojection_px: float
    points: int
    models: int  # connected models COLMAP made (the largest is kept)
    camera: Camera  # the calibration the poses are in: the one given, or as the mapper refined it

    @property
    def registered(self) -> int:
        return len(self.poses)


def colmap_camera(camera: Camera) -> tuple[str, list[float]]:
    """COLMAP's camera model and parameters for a camera_info calibration (the same lens model, no refit)."""
    fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
    d = list(camera.dist) + [0.0] * max(0, 8 - len(camera.dist))
    if camera.model == "equidistant":
        return "OPENCV_FISHEYE", [fx, fy, cx, cy, *(list(camera.dist) + [0.0] * 4)[:4]]
    if not camera.dist.any():
        return "PINHOLE", [fx, fy, cx, cy]
    if camera.dist.size <= 4 or not any(d[4:8]):
        return "OPENCV", [fx, fy, cx, cy, *d[:4]]
    return "FULL_OPENCV", [fx, fy, cx, cy, *d[:8]]  # k1 k2 p1 p2 k3 k4 k5 k6, as rational_polynomial's first eight


def refined_camera(camera: Camera, params: Sequence[float]) -> Camera:
    """``camera`` with the intrinsics COLMAP refined, ``params`` in :func:`colmap_camera`'s order for its model. A
    plumb_bob calibration COLMAP fitted as FULL_OPENCV comes back rational_polynomial (its k4..k6 refined too)."""
    fx, fy, cx, cy, *extra = (float(v) for v in params)
    dist = np.zeros(max(camera.dist.size, len(extra)))
    dist[:camera.dist.size] = camera.dist
    dist[:len(extra)] = extra
    model = "rational_polynomial" if camera.model == "plumb_bob" and dist.size > 5 else camera.model
    K = np.array([[fx, camera.K[0, 1], cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return replace(camera, K=K, dist=dist, model=model)


MAPPERS = ("global", "incremental")


STAGES = ("features", "matching", "mapping")  # what reconstruct() says it starts, in order


def reconstruct(image_dir: Path, names: list[str], camera: Camera, work_dir: Path, refine_intrinsics: bool = False,
                overlap: int = 10, threads: int = 0, mapper: str = "global",
                stage: Callable[[str], object] = lambda _name: None) -> Reconstruction:
    """COLMAP SIFT features, sequential matching of each keyframe with its ``overlap`` successors, and a mapper with
    ``camera``'s calibration fixed (refined too with ``refine_intrinsics``): ``global`` (GLOMAP: rotation averaging,
    then global positioning; the default, as on a driving sequence the incremental mapper bent the first half of
    KITTI-07 0-59 by up to 70 degrees) or ``incremental``. ``stage`` is told each of STAGES as it starts (a progress
    bar). ReconstructionError when no model comes out."""
    import pycolmap

    pycolmap.logging.minloglevel = 2  # COLMAP logs every image at INFO; warnings and errors still show
    work_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    if database.exists():
        database.unlink()
    model, params = colmap_camera(camera)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = model
    reader.camera_params = ",".join(f"{p:.12g}" for p in params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads or os.cpu_count() or 1
    extraction.use_gpu = False
    stage(STAGES[0])
    pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = overlap
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    stage(STAGES[1])
    pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
    stage(STAGES[2])
    if mapper == "global":
        options = pycolmap.GlobalPipelineOptions()
        ba = options.mapper.bundle_adjustment
        ba.refine_focal_length = ba.refine_extra_params = refine_intrinsics
        ba.refine_principal_point = False
        options.random_seed = 0
        options.num_threads = threads or os.cpu_count() or 1
        models = pycolmap.global_mapping(database, image_dir, work_dir / "sparse", options)
    elif mapper == "incremental":
        options = pycolmap.IncrementalPipelineOptions()
        options.ba_refine_focal_length = options.ba_refine_extra_params = refine_intrinsics
        options.ba_refine_principal_point = False
        options.random_seed = 0
        options.num_threads = threads or os.cpu_count() or 1
        models = pycolmap.incremental_mapping(database, image_dir, work_dir / "sparse", options)
    else:
        raise ValueError(f"unknown mapper {mapper!r}; use one of {', '.join(MAPPERS)}")
    if not models:
        raise ReconstructionError("COLMAP made no model of the keyframes: the camera may not move enough between them "
                                  "(a standing or only turning camera has no baseline), or the scene has too little "
                                  "texture; record while the robot moves through a textured scene, or give more frames")
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    poses = {}
    for image in rec.images.values():
        if image.has_pose:
            T = np.eye(4)
            T[:3] = image.cam_from_world().matrix()
            poses[image.name] = np.linalg.inv(T)
    (colmap,) = rec.cameras.values()  # one camera for every keyframe (CameraMode.SINGLE)
    return Reconstruction(poses, len(names), float(rec.compute_mean_reprojection_error()), rec.num_points3D(),
                          len(models), refined_camera(camera, colmap.params) if refine_intrinsics else camera)


MIN_REGISTERED_SHARE = 0.6  # of the keyframes
MIN_REGISTERED = 10
MAX_REPROJECTION_PX = 2.0
MIN_CONSECUTIVE_SHARE = 0.6  # of consecutive keyframe pairs with both frames registered


def quality_problem(rec: Reconstruction, names: list[str]) -> str | None:
    """Why the reconstruction of the keyframes ``names`` (in order) cannot be trusted as ground truth, with what to
    do; None when it can: enough frames registered, a small reprojection error, consecutive keyframes covered. (A
    standing camera is refused before, from the images' parallax: its model may look fine, its poses are noise.)"""
    n = len(names)
    if rec.registered < max(MIN_REGISTERED, MIN_REGISTERED_SHARE * n):
        return (f"only {rec.registered} of {n} keyframes were registered (at least {MIN_REGISTERED} and "
                f"{MIN_REGISTERED_SHARE:.0%} are needed): the frames overlap too little or lack texture; give frames "
                "closer together (--interval) or a longer recording")
    if rec.mean_reprojection_px > MAX_REPROJECTION_PX:
        return (f"mean reprojection error {rec.mean_reprojection_px:.2f} px is over {MAX_REPROJECTION_PX} px: the "
                "calibration does not fit the images (check camera_info, or try --refine-intrinsics)")
    both = sum(a in rec.poses and b in rec.poses for a, b in zip(names, names[1:], strict=False))
    if n > 1 and both < MIN_CONSECUTIVE_SHARE * (n - 1):
        return (f"only {both} of {n - 1} consecutive keyframe pairs have both frames registered: the model is in "
                "pieces; give frames closer together (--interval) or a recording without gaps")
    return None

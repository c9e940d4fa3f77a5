"""Where a frame's time goes at 1 thread per stage, as the node runs (README Speed, "Where the time goes").

An analysis, not part of the package. Part 1 runs the front end serially over KITTI-07 frames
120-159 (native 1241x376) with matching in the detection stage and prints the median ms of its
parts: ``detect`` + ``match`` is the node's first stage, ``select+pose`` (neighbours, NM-Net,
MAGSAC++, pose polish) its second. Part 2 splits the fast detector's time at 2000 keypoints.

    python docs/analysis/stage_times.py ../shared/data        # about 1.5 minutes
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from nmnet_ros.datasets import Sequence
from nmnet_ros.fast_hessaff import FastHessianAffine, _Pyramid
from nmnet_ros.features import to_gray_float
from nmnet_ros.pipeline import Frontend


def frontend_parts(seq: Sequence, images: list[np.ndarray]) -> None:
    """Median ms of detect / match / select+pose per keypoint budget and NM-Net arithmetic."""
    print("| keypoints | precision | detect | match | select+pose |\n|---|---|---|---|---|")
    for n in (1000, 2000):
        for precision in ("bfloat16", "float32"):
            fe = Frontend(seq.camera, {"max_keypoints": n, "precision": precision, "match_stage": "first"})
            parts: dict[str, list[float]] = {}
            for rep in range(2):  # the first pass warms the caches and oneDNN's kernels
                fe.reset()
                for i, image in enumerate(images):
                    timings = fe.process(image, 0.1 * i).timings_ms
                    for key, ms in timings.items():
                        if rep:
                            parts.setdefault(key, []).append(ms)
            med = {key: float(np.median(v)) for key, v in parts.items()}
            print(f"| {n} | {precision} | {med['detect']:.1f} | {med['match']:.1f} | {med['select+pose']:.1f} |")


def detector_parts(images: list[np.ndarray], n: int = 2000) -> None:
    """Median ms of the fast detector's steps (the same calls as FastHessianAffine.__call__)."""
    det = FastHessianAffine({"max_keypoints": n})
    c = det.config
    parts: dict[str, list[float]] = {}
    for rep in range(2):
        for image in images:
            t = [time.perf_counter()]
            gray = to_gray_float(image)
            xy, sigma, _ = det.detect(gray)
            t.append(time.perf_counter())
            pyr = _Pyramid(gray, min(c["affine_patch"], c["orientation_patch"], c["patch_size"]))
            f = (c["mr_size"] * sigma)[:, None, None] * np.eye(2, dtype=np.float32)
            for _ in range(c["affine_iterations"]):
                f = det.adapt_shape(pyr, f, xy)
            t.append(time.perf_counter())
            f = det.orient(pyr, f, xy)
            t.append(time.perf_counter())
            det.describe(pyr, f, xy)
            t.append(time.perf_counter())
            if rep:
                for key, a, b in zip(("scale space", "affine steps", "orientation", "RootSIFT"), t, t[1:], strict=False):
                    parts.setdefault(key, []).append(1000 * (b - a))
                parts.setdefault("whole", []).append(1000 * (t[-1] - t[0]))
    print(f"fast detector, {n} keypoints: " + ", ".join(f"{k} {np.median(v):.1f} ms" for k, v in parts.items()))


def main(data: Path) -> None:
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    seq = Sequence.load(data / "kitti-07")
    images = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in seq.paths[120:160]]
    frontend_parts(seq, images)
    detector_parts(images)


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "../shared/data"))

"""Where the fast detector's time goes at 1 thread, the node's detection stage (README Speed, "Where the time goes").

An analysis, not part of the package; the front end's stages at 1 thread come from
``nmnet bench --pipeline --threads 1``. This runs the detector itself over KITTI-07 frames 120-159
(native 1241x376) with its steps timed in place (the scale space, the Baumberg affine steps,
orientation, RootSIFT) and prints the median ms of each.

    python docs/analysis/stage_times.py ../shared/data        # about 20 s
"""

from __future__ import annotations

import functools
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from nmnet_ros.core.fast_hessaff import FastHessianAffine
from nmnet_ros.io.datasets import Sequence

STEPS = {"detect": "scale space", "adapt_shape": "affine steps", "orient": "orientation", "describe": "RootSIFT"}


def timed_steps(det: FastHessianAffine, spent: dict[str, float]) -> None:
    """Wrap the detector's step methods on this instance so that each call adds its ms to ``spent``."""
    for name, label in STEPS.items():
        step = getattr(det, name)

        @functools.wraps(step)
        def wrapper(*args, _step=step, _label=label, **kwargs):
            t = time.perf_counter()
            out = _step(*args, **kwargs)
            spent[_label] = spent.get(_label, 0.0) + 1000 * (time.perf_counter() - t)
            return out

        setattr(det, name, wrapper)


def main(data: Path, keypoints: int = 2000) -> None:
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    seq = Sequence.load(data / "kitti-07")
    images = [seq.image(i) for i in range(120, 160)]
    det = FastHessianAffine({"max_keypoints": keypoints})
    spent: dict[str, float] = {}
    timed_steps(det, spent)
    per_frame: dict[str, list[float]] = {}
    for rep in range(2):  # the first pass warms the caches
        for image in images:
            spent.clear()
            t = time.perf_counter()
            det(image)
            spent["whole"] = 1000 * (time.perf_counter() - t)
            for label, ms in spent.items():
                if rep:
                    per_frame.setdefault(label, []).append(ms)
    print(f"fast detector, {keypoints} keypoints, 1 thread, median ms per frame: "
          + ", ".join(f"{label} {np.median(v):.1f}" for label, v in per_frame.items()))


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "../shared/data"))

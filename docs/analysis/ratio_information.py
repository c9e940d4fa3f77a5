"""How much does the descriptor ratio add to NM-Net's score? A logistic fit of [logit, logit(ratio)].

An analysis behind docs/accuracy.md ("the descriptor distance ratio as a fifth network input"), not
part of the package. Fits label ~ a * logit + b * logit(ratio) + c by Newton's method on training
pairs (kitti-07 frames 0-60 and strecha-fountain-p11, gaps 1, 4, 8; shipped weights), then prints
the ratio's spread for inliers and outliers and the mean per-pair F-measure on validation pairs
(kitti-07 frames 120-159 and strecha-herz-jesus-p25, gaps 1, 3, 5, 7, 9) of the logit alone and of
the fitted combination, at cuts from -1 to 3 (logit units). If the combination barely beats the
logit, the network already knows what the ratio says.

    python docs/analysis/ratio_information.py ../shared/data [--detector hessian-affine]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from nmnet_ros.core.detectors import make_detector
from nmnet_ros.core.metrics import prf
from nmnet_ros.core.model import NMNet, load_model
from nmnet_ros.io.cache import FeatureCache
from nmnet_ros.io.pairs import load_pairs
from nmnet_ros.tools.train import pair_input


def scored(model: NMNet, specs: list[str], cache: FeatureCache, gaps: tuple[int, ...]) -> list[tuple]:
    """(logits, ratios, labels) of every pair of ``specs``."""
    out = []
    for p in load_pairs(specs, gaps, cache, min_inliers=5, log=lambda _: None):
        x, nb = pair_input(p, model.config)
        with torch.inference_mode():
            out.append((model(x, nb)[0].double().numpy(), p.matches.ratio.astype(np.float64), p.labels))
    return out


def design(logits: np.ndarray, ratio: np.ndarray) -> np.ndarray:
    r = np.clip(ratio, 1e-3, 1 - 1e-3)
    return np.c_[logits, np.log(r / (1 - r)), np.ones_like(logits)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", help="the ../shared/data folder")
    ap.add_argument("--detector", default="hessian-affine-fast")
    args = ap.parse_args()
    torch.set_num_threads(1)
    cache = FeatureCache(make_detector(args.detector))
    model = load_model()
    train = scored(model, [f"{args.data}/kitti-07:0-60", f"{args.data}/strecha-fountain-p11"], cache, (1, 4, 8))
    val = scored(model, [f"{args.data}/kitti-07:120-159", f"{args.data}/strecha-herz-jesus-p25"], cache, (1, 3, 5, 7, 9))
    A = np.concatenate([design(lg, r) for lg, r, _ in train])
    y = np.concatenate([t for *_, t in train]).astype(np.float64)
    r, lab = np.concatenate([r for _, r, _ in train]), y > 0
    print(f"ratio on {len(train)} training pairs, percentiles 5/25/50/75/95: inliers "
          f"{np.round(np.percentile(r[lab], [5, 25, 50, 75, 95]), 2)}, outliers {np.round(np.percentile(r[~lab], [5, 25, 50, 75, 95]), 2)}")
    w = np.array([1.0, 0.0, 0.0])
    for _ in range(25):  # Newton's method on the logistic loss
        p = 1 / (1 + np.exp(-A @ w))
        w -= np.linalg.solve((A * (p * (1 - p))[:, None]).T @ A + 1e-6 * np.eye(3), A.T @ (p - y))
    print(f"fit: {w[0]:.3f} * logit + {w[1]:.3f} * logit(ratio) + {w[2]:.3f}")
    for cut in np.arange(-1.0, 3.01, 0.5):
        f_logit = np.mean([prf(lg > cut, t)["f1"] for lg, _, t in val])
        f_both = np.mean([prf(design(lg, r) @ w > cut, t)["f1"] for lg, r, t in val])
        print(f"cut {cut:+.1f}: F on {len(val)} validation pairs, logit {f_logit:.1f}, logit + ratio {f_both:.1f}")


if __name__ == "__main__":
    main()

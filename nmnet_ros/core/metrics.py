"""Correspondence-selection metrics: precision, recall, F-measure (the paper's P/R/F) and the average precision of a ranking."""

from __future__ import annotations

import numpy as np


def prf(pred: np.ndarray, labels: np.ndarray) -> dict[str, float]:
    """Precision, recall and F-measure in percent of a boolean selection against labels."""
    pred = np.asarray(pred, bool)
    labels = np.asarray(labels, bool)
    if pred.shape != labels.shape:
        raise ValueError(f"selection {pred.shape} and labels {labels.shape} differ in shape")
    tp = float(np.sum(pred & labels))
    p = tp / max(pred.sum(), 1)
    r = tp / max(labels.sum(), 1)
    f = 2 * p * r / max(p + r, 1e-12)
    return {"precision": 100 * p, "recall": 100 * r, "f1": 100 * f}


def average_precision(scores: np.ndarray, labels: np.ndarray) -> float:
    """Average precision (%) of ranking the matches by ``scores`` (higher first) against the labels: the mean of the
    precision at each labelled inlier's rank. How well an order puts the inliers first, whatever the cut; NaN
    without a labelled inlier. Tied scores keep the matches' order."""
    scores, labels = np.asarray(scores), np.asarray(labels, bool)
    if scores.shape != labels.shape:
        raise ValueError(f"scores {scores.shape} and labels {labels.shape} differ in shape")
    ranked = labels[np.argsort(-scores, kind="stable")]
    if not ranked.any():
        return float("nan")
    hits = np.cumsum(ranked)
    return float(100 * np.mean(hits[ranked] / (np.flatnonzero(ranked) + 1)))

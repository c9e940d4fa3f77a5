"""Correspondence-selection metrics: precision, recall, F-measure (the paper's P/R/F)."""

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

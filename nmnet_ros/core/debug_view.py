"""Match overlay for ~/debug_image and the docs pictures: selected matches green, rejected red."""

from __future__ import annotations

import cv2
import numpy as np


def draw_matches(img: np.ndarray, k0: np.ndarray, k1: np.ndarray, mask: np.ndarray, max_rejected: int = 150) -> np.ndarray:
    """Flow lines from the previous keypoint to the current one on the current image (BGR uint8)."""
    out = img if img.ndim == 3 else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if out.dtype != np.uint8:
        out = cv2.convertScaleAbs(out, alpha=255.0 / max(float(out.max()), 1.0))
    out = out.copy()
    mask = np.asarray(mask, bool)
    rej = np.flatnonzero(~mask)
    if len(rej) > max_rejected:
        rej = rej[np.linspace(0, len(rej) - 1, max_rejected).astype(int)]
    for idx, colour in ((rej, (0, 0, 255)), (np.flatnonzero(mask), (0, 220, 0))):
        for i in idx:
            p0 = (int(round(k0[i, 0])), int(round(k0[i, 1])))
            p1 = (int(round(k1[i, 0])), int(round(k1[i, 1])))
            cv2.line(out, p0, p1, colour, 1, cv2.LINE_AA)
            cv2.circle(out, p1, 2, colour, -1, cv2.LINE_AA)
    cv2.rectangle(out, (0, 0), (330, 34), (0, 0, 0), -1)
    cv2.putText(out, f"selected {int(mask.sum())} / {len(mask)}", (8, 25), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2)
    return out

"""Registry of local-feature frame sources, by the name the CLI, the node and the config use."""

from __future__ import annotations

from .fast_hessaff import FastHessianAffine
from .features import Detector, HessianAffine, SiftSimilarity
from .settings import FRONTEND_DEFAULTS

DETECTORS: dict[str, type] = {
    "hessian-affine-fast": FastHessianAffine,  # batched OpenCV/torch Hessian-affine (default; NM-Net fine-tuned on it last)
    "hessian-affine": HessianAffine,  # kornia reference path (NM-Net trained on it first, see the model card)
    "sift": SiftSimilarity,  # OpenCV SIFT with similarity frames (the classic baseline's features)
}
DEFAULT_DETECTOR = FRONTEND_DEFAULTS["detector"]  # what the node runs, and so what `nmnet train` trains on unless told


def make_detector(name: str, config: dict | None = None) -> Detector:
    """The named detector, or a ValueError listing the choices."""
    if name not in DETECTORS:
        raise ValueError(f"unknown detector {name!r}; use one of {', '.join(DETECTORS)}")
    return DETECTORS[name](config)

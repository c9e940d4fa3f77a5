"""Hessian-affine local features: keypoints, local affine frames, RootSIFT descriptors.

The reference detector is kornia's scale-space pipeline: Hessian-determinant blobs in a
scale pyramid, Baumberg affine adaptation (iterated second-moment normalisation), dominant
orientation, and RootSIFT on the normalised patch. A frame ``A`` (2x2) maps the unit disc of
the normalised patch to the image ellipse, so ``T = [[A, k], [0, 0, 1]]`` is the local frame
NM-Net's compatibility score is built from (paper Eq. 3).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

DEFAULT_CONFIG: dict = {
    "max_keypoints": 2000,
    "affine_iterations": 3,  # Baumberg steps; 0 gives similarity frames
    "patch_size": 32,
    "mr_size": 6.0,  # measurement-region multiplier of the detection scale
    "upright": False,  # skip orientation estimation
}


@dataclass
class Features:
    """Local features of one image (all arrays share the first axis N)."""

    keypoints: np.ndarray  # (N, 2) float32 pixel coordinates (x, y)
    frames: np.ndarray  # (N, 2, 2) float32 local affine frames A
    descriptors: np.ndarray  # (N, 128) float32, L2-normalised RootSIFT
    responses: np.ndarray  # (N,) float32 detector response

    def __len__(self) -> int:
        return len(self.keypoints)

    @classmethod
    def empty(cls) -> Features:
        """No features (blank or tiny image)."""
        z = np.zeros
        return cls(z((0, 2), np.float32), z((0, 2, 2), np.float32),
                   z((0, 128), np.float32), z((0,), np.float32))

    def subset(self, idx: np.ndarray) -> Features:
        """Features at the given indices."""
        return Features(self.keypoints[idx], self.frames[idx], self.descriptors[idx], self.responses[idx])

    def to_npz(self) -> dict[str, np.ndarray]:
        """Arrays for ``np.savez`` (feature cache)."""
        return {"keypoints": self.keypoints, "frames": self.frames,
                "descriptors": self.descriptors, "responses": self.responses}

    @classmethod
    def from_npz(cls, data: Mapping[str, np.ndarray]) -> Features:
        """Inverse of :meth:`to_npz`."""
        return cls(*(np.asarray(data[k], np.float32) for k in ("keypoints", "frames", "descriptors", "responses")))


class Detector(Protocol):
    """What every frame source (detectors.py) is: image -> features, plus the settings key of on-disk caches."""

    @property
    def cache_key(self) -> str: ...

    def __call__(self, image: np.ndarray) -> Features: ...


def to_gray_float(image: np.ndarray) -> np.ndarray:
    """Mono or colour (H,W[,C]) uint8/uint16/float image -> (H,W) float32 in [0,1]."""
    img = np.asarray(image)
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[..., 0]
        elif img.shape[2] in (3, 4):
            img = img[..., :3].astype(np.float32) @ np.array([0.114, 0.587, 0.299], np.float32)  # BGR
        else:
            raise ValueError(f"image has {img.shape[2]} channels; expected 1, 3 or 4")
    elif img.ndim != 2:
        raise ValueError(f"image must be (H,W) or (H,W,C), got shape {img.shape}")
    return np.ascontiguousarray(img, dtype=np.float32) / np.float32(full_scale(image))


SENSOR_BITS = (8, 10, 12, 14, 16)  # the bit depths cameras deliver in 16-bit containers


def full_scale(image: np.ndarray) -> float:
    """The value of white: 255 for uint8, 1 for float; for uint16 the top of the bits in use.

    A 10-, 12- or 14-bit camera publishes mono16 with white at 1023, 4095 or 16383; read as 16 bits
    its frames would be 16-64x too dark for the detectors' contrast thresholds (SIFT found no
    keypoints on a 12-bit KITTI frame). So a uint16 image is scaled by 2**b - 1 for the smallest
    sensor depth b (:data:`SENSOR_BITS`) holding its brightest pixel: one camera's frames share a scale
    whatever their exposure (any bit count would scale a 12-bit frame peaking at 2000 by 2047 and the
    next, peaking at 3000, by 4095), unless a frame stays below a quarter of the camera's range.
    """
    if image.dtype == np.uint8:
        return 255.0
    if image.dtype == np.uint16:
        peak = int(image.max()) if image.size else 0
        return float(2 ** next(b for b in SENSOR_BITS if peak < 2**b) - 1)
    return 1.0


class HessianAffine:
    """Hessian-affine detector + RootSIFT descriptor on kornia (the faithful reference path)."""

    min_size = 32  # smaller images yield no features

    def __init__(self, config: dict | None = None) -> None:
        import kornia.feature as KF

        self.config = {**DEFAULT_CONFIG, **(config or {})}
        c = self.config
        ps = c["patch_size"]
        self.detector = KF.ScaleSpaceDetector(
            num_features=c["max_keypoints"], mr_size=c["mr_size"], resp_module=KF.BlobHessian(),
            ori_module=KF.PassLAF(), aff_module=KF.PassLAF())
        self.affine = KF.LAFAffineShapeEstimator(ps, preserve_orientation=False)
        self.orienter = KF.LAFOrienter(ps)
        self.descriptor = KF.SIFTDescriptor(ps, rootsift=True)
        self._laf_descriptors = KF.get_laf_descriptors

    @property
    def cache_key(self) -> str:
        """Identifies the settings, for on-disk feature caches."""
        c = self.config
        return f"hesaff-k{c['max_keypoints']}-a{c['affine_iterations']}-p{c['patch_size']}-m{c['mr_size']}-u{int(c['upright'])}"

    @torch.inference_mode()
    def __call__(self, image: np.ndarray) -> Features:
        """Detect and describe; a blank, tiny or empty image gives empty features."""
        gray = to_gray_float(image)
        if min(gray.shape) < self.min_size or float(gray.max() - gray.min()) < 1e-3:
            return Features.empty()
        img = torch.from_numpy(gray)[None, None]
        lafs, resp = self.detector(img)
        keep = resp[0] > 0 if resp.numel() else resp[0].bool()
        lafs, resp = lafs[:, keep], resp[:, keep]
        if lafs.shape[1] == 0:
            return Features.empty()
        for _ in range(self.config["affine_iterations"]):
            lafs = self.affine(lafs, img)
        if not self.config["upright"]:
            lafs = self.orienter(lafs, img)
        desc = self._laf_descriptors(img, lafs, self.descriptor, self.config["patch_size"])
        desc = torch.nn.functional.normalize(desc, dim=-1)
        return Features(
            keypoints=lafs[0, :, :, 2].numpy().astype(np.float32),
            frames=lafs[0, :, :, :2].numpy().astype(np.float32),
            descriptors=desc[0].numpy().astype(np.float32),
            responses=resp[0].numpy().astype(np.float32),
        )


class SiftSimilarity:
    """OpenCV SIFT keypoints with similarity frames A = size * R(angle) and RootSIFT descriptors.

    The classic baseline's features, and a cheaper frame source for the compatibility score
    (exact only for zoom + rotation; see DESIGN.md).
    """

    min_size = 16

    def __init__(self, config: dict | None = None) -> None:
        import cv2

        self.config = {**DEFAULT_CONFIG, **(config or {})}
        self._sift = cv2.SIFT_create(self.config["max_keypoints"])

    @property
    def cache_key(self) -> str:
        return f"sift-k{self.config['max_keypoints']}"

    def __call__(self, image: np.ndarray) -> Features:
        """Detect and describe; blank or tiny images give empty features."""
        gray = to_gray_float(image)
        if min(gray.shape) < self.min_size or float(gray.max() - gray.min()) < 1e-3:
            return Features.empty()
        kps, desc = self._sift.detectAndCompute((gray * 255).astype(np.uint8), None)
        if not kps:
            return Features.empty()
        kps, desc = kps[: self.config["max_keypoints"]], desc[: self.config["max_keypoints"]]
        ang = np.radians([k.angle for k in kps])
        size = np.array([k.size for k in kps])
        c, s = np.cos(ang), np.sin(ang)
        frames = size[:, None, None] * np.stack([np.stack([c, -s], 1), np.stack([s, c], 1)], 1)
        d = np.sqrt(desc / np.maximum(desc.sum(1, keepdims=True), 1e-12))  # RootSIFT: L1, then sqrt (unit L2)
        return Features(np.array([k.pt for k in kps], np.float32), frames.astype(np.float32), d.astype(np.float32),
                        np.array([k.response for k in kps], np.float32))


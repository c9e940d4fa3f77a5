"""On-disk feature cache, keyed by detector settings, sequence and image file (training, evaluation)."""

from __future__ import annotations

import contextlib
import hashlib
import os
import warnings
from pathlib import Path

import numpy as np

from ..core.features import Detector, Features
from .datasets import Sequence


def default_cache_dir() -> Path:
    """$NMNET_CACHE, else ~/.cache/nmnet_ros."""
    return Path(os.environ.get("NMNET_CACHE", Path.home() / ".cache" / "nmnet_ros"))


class FeatureCache:
    """Computes features of a sequence frame once and reuses them from ``root``."""

    def __init__(self, detector: Detector, root: Path | None = None) -> None:
        self.detector = detector
        self.root = Path(root) if root is not None else default_cache_dir()
        self._memo: dict[Path, Features] = {}  # one object per frame, shared by all its pairs
        self.writable = True  # until a write fails

    def path(self, seq: Sequence, i: int) -> Path:
        """Cache file of frame i; the folder's absolute path is hashed so equal names do not collide, and the image
        file's path, size and time (:meth:`Sequence.image_version`) so a changed image is detected again."""
        tag = hashlib.sha1(str(seq.root.resolve()).encode()).hexdigest()[:8]
        version = hashlib.sha1(seq.image_version(i).encode()).hexdigest()[:10]
        return self.root / self.detector.cache_key / f"{seq.name}-{tag}" / f"{seq.paths[i].stem}-{version}.npz"

    def __call__(self, seq: Sequence, i: int) -> Features:
        """Features of frame i of ``seq``, from the cache when present."""
        p = self.path(seq, i)
        if p not in self._memo:
            self._memo[p] = self._load_or_compute(seq, i, p)
        return self._memo[p]

    def fill(self, seq: Sequence, frames: list[int]) -> int:
        """Compute and store the features of ``frames`` that the cache lacks, without keeping them in memory (a
        worker preparing features for a later run); returns how many were computed."""
        missing = [i for i in frames if not self.path(seq, i).is_file()]
        for i in missing:
            self._load_or_compute(seq, i, self.path(seq, i))
        return len(missing)

    def _load_or_compute(self, seq: Sequence, i: int, p: Path) -> Features:
        if p.is_file():
            try:
                with np.load(p) as d:
                    return Features.from_npz(d)
            except (OSError, ValueError, KeyError):
                p.unlink(missing_ok=True)  # a torn write from an interrupted run: recompute
        f = self.detector(seq.image(i))
        if self.writable:
            self._save(f, p)
        return f

    def _save(self, f: Features, p: Path) -> None:
        """Write ``f`` to ``p`` through a temporary file; a cache that cannot be written (a file in its place, a
        read-only home, a full disk) is said once and the work goes on uncached: it is only a cache."""
        tmp = p.with_name(p.stem + f".{os.getpid()}.tmp.npz")
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
            np.savez(tmp, **f.to_npz())
            tmp.replace(p)
        except OSError as e:
            with contextlib.suppress(OSError):  # a part written before the disk filled
                tmp.unlink(missing_ok=True)
            self.writable = False
            warnings.warn(f"feature cache {self.root}: cannot write it ({e.strerror or e}); features are computed again "
                          "each run: give a writable folder with --cache or NMNET_CACHE", stacklevel=2)

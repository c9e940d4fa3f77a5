"""Labelled correspondence sets of image pairs: the unit NM-Net trains and is evaluated on."""

from __future__ import annotations

import re
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..core.features import Features
from ..core.matching import Matches, match_descriptors
from .cache import FeatureCache
from .datasets import LABEL_THRESHOLD, MAX_VIEW_ANGLE_DEG, Sequence, epipolar_labels, has_baseline
from .progress import progress

if TYPE_CHECKING:
    from ..core.selectors import Correspondences


@dataclass
class PairData:
    """Putative matches of one pair with everything the selectors and metrics need."""

    seq: Sequence
    i: int
    j: int
    feats0: Features
    feats1: Features
    matches: Matches
    labels: np.ndarray  # (M,) bool ground-truth inliers
    R: np.ndarray
    t: np.ndarray

    @property
    def k0(self) -> np.ndarray:
        return self.feats0.keypoints[self.matches.idx[:, 0]]

    @property
    def k1(self) -> np.ndarray:
        return self.feats1.keypoints[self.matches.idx[:, 1]]

    @property
    def a0(self) -> np.ndarray:
        return self.feats0.frames[self.matches.idx[:, 0]]

    @property
    def a1(self) -> np.ndarray:
        return self.feats1.frames[self.matches.idx[:, 1]]

    def normalized(self) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted normalised coordinates of both sides."""
        return self.seq.camera.normalize(self.k0), self.seq.camera.normalize(self.k1)


def view_angle_deg(seq: Sequence, i: int, j: int) -> float:
    """Angle between the two cameras' optical axes (co-visibility proxy for unordered sets)."""
    R, _ = seq.relative_pose(i, j)
    return float(np.degrees(np.arccos(np.clip(R[2, 2], -1.0, 1.0))))




def select_pairs(seq: Sequence, gaps: tuple[int, ...], frames: range | None = None,
                 max_view_angle: float = MAX_VIEW_ANGLE_DEG) -> list[tuple[int, int]]:
    """Pairs by frame gap (or pairs.txt) that have a baseline and are co-visible.

    Pairs without translation (a static camera) have no epipolar geometry to label against
    and are excluded, not labelled by noise; so are pairs with a frame the ground truth has no pose for.
    """
    out = []
    for i, j in seq.pairs(gaps, frames):
        if seq.poses is None or (seq.has_pose(i) and seq.has_pose(j) and has_baseline(seq, i, j)
                                 and view_angle_deg(seq, i, j) <= max_view_angle):
            out.append((i, j))
    return out


def pair_frames(spec: str, gaps: tuple[int, ...], max_view_angle: float = MAX_VIEW_ANGLE_DEG) -> tuple[Sequence, list[int]]:
    """The frames that 'PATH[:a-b]''s pairs (:func:`select_pairs`, every start frame) use, and its sequence."""
    path, frames = parse_seq_spec(spec)
    seq = Sequence.load(path)
    return seq, sorted({k for pair in select_pairs(seq, gaps, frames, max_view_angle) for k in pair})


def no_pairs_reason(seq: Sequence, spec: str, gaps: tuple[int, ...], frames: range | None = None,
                    max_view_angle: float = MAX_VIEW_ANGLE_DEG) -> str:
    """Why ``select_pairs`` gave ``spec`` no pairs: its frames make none (at these gaps), or none has what labels need."""
    n = len(seq.pairs(gaps, frames))
    by = "pairs.txt" if seq.pairs_file is not None else f"gaps {','.join(map(str, gaps))}"
    if not n:
        return f"{spec}: its frames make no pairs ({by})"
    return (f"{spec}: none of its {n} frame pairs ({by}) has a ground-truth pose on both frames, motion between them "
            f"(epipolar labels need a baseline) and views within {max_view_angle:g} degrees")


def make_pair(seq: Sequence, i: int, j: int, cache: FeatureCache, match_config: dict | None = None,
              label_threshold: float = LABEL_THRESHOLD) -> PairData:
    """Features (cached), nearest-neighbour matches and ground-truth labels of pair (i, j)."""
    f0, f1 = cache(seq, i), cache(seq, j)
    m = match_descriptors(f0.descriptors, f1.descriptors, match_config)
    k0, k1 = f0.keypoints[m.idx[:, 0]], f1.keypoints[m.idx[:, 1]]
    labels, _ = epipolar_labels(seq, i, j, k0, k1, label_threshold)
    R, t = seq.relative_pose(i, j)
    return PairData(seq, i, j, f0, f1, m, labels, R, t)


def to_stderr(line: str) -> None:
    """A note line on stderr (the loaders' default log)."""
    print(line, file=sys.stderr)


def load_pairs(specs: list[str], gaps: tuple[int, ...], cache: FeatureCache, *, stride: int = 1,
               max_pairs: int | None = None, min_inliers: int = 0, label_threshold: float = LABEL_THRESHOLD,
               skip_empty: bool = False, log: Callable[[str], None] = to_stderr, tool: str = "eval",
               max_view_angle: float = MAX_VIEW_ANGLE_DEG) -> list[PairData]:
    """Labelled pairs of every 'PATH[:a-b]', the one loader of eval, train and the studies.

    pairs.txt's pairs (within a-b) when the folder has one, else every ``stride``-th frame's pairs at ``gaps``; at
    most ``max_pairs`` per folder, spread evenly; pairs with fewer than ``min_inliers`` labelled inliers dropped, and
    pairs whose cameras' optical axes are more than ``max_view_angle`` degrees apart.
    The folder's notes go to ``log`` as warnings, then one line per folder naming ``tool``. A folder without pairs
    is a ValueError saying why, or with ``skip_empty`` (training: other folders may have pairs) is a warning.
    """
    pairs = []
    for spec in specs:
        path, frames = parse_seq_spec(spec)
        seq = Sequence.load(path)
        for note in seq.notes():
            log(f"warning: {note}")
        selected = select_pairs(seq, gaps, frames, max_view_angle)
        chosen = selected if seq.pairs_file is not None else [(i, j) for i, j in selected if i % stride == 0]
        if not chosen:
            why = no_pairs_reason(seq, spec, gaps, frames, max_view_angle) if not selected else (
                f"{spec}: none of its pairs starts at a multiple of --stride {stride} (give a smaller one)")
            if not skip_empty:
                raise ValueError(f"no pairs to evaluate: {why}")
            log(f"warning: {why}")
            continue
        if max_pairs and len(chosen) > max_pairs:
            chosen = [chosen[k] for k in np.linspace(0, len(chosen) - 1, max_pairs).round().astype(int)]
        t0 = time.perf_counter()
        made = [make_pair(seq, i, j, cache, label_threshold=label_threshold)
                for i, j in progress(chosen, f"features {seq.name}", "pair")]  # minutes on a fresh cache
        kept = [p for p in made if p.labels.sum() >= min_inliers]
        dropped = (f" (of {len(made)}; {len(made) - len(kept)} with fewer than {min_inliers} inliers dropped)"
                   if len(kept) < len(made) else "")
        ratio = 100 * np.mean([p.labels.mean() for p in kept]) if kept else 0.0
        log(f"{tool}: {spec_label(spec)}: {len(kept)} pairs{dropped}, mean inlier ratio {ratio:.1f}%, ready in "
            f"{time.perf_counter() - t0:.0f} s")
        pairs += kept
    return pairs


def parse_seq_spec(spec: str) -> tuple[str, range | None]:
    """'PATH' or 'PATH:a-b' (frames a..b inclusive) -> (path, frames); a suffix of digits and dashes that is not
    a-b (``:5``, ``:-5-10``), or any other suffix after an existing folder (``:10..20``), is a ValueError saying
    the form."""
    path, _, rng = spec.rpartition(":")
    if not path or Path(spec).is_dir() or not (rng.replace("-", "").isdigit() or Path(path).is_dir()):
        return spec, None
    if (m := re.fullmatch(r"(\d+)-(\d+)", rng)) is None:
        raise ValueError(f"{spec}: a frame range is PATH:a-b, frames a to b (e.g. {path}:0-119), got {rng!r}")
    return path, range(int(m[1]), int(m[2]) + 1)


def _range_suffix(frames: range | None) -> str:
    """':a-b' for frames a..b, '' for every frame: a spec's range as it is written."""
    return f":{frames.start}-{frames.stop - 1}" if frames is not None else ""


def absolute_spec(spec: str) -> str:
    """'PATH[:a-b]' with PATH absolute: for a worker that may run in another folder."""
    path, frames = parse_seq_spec(spec)
    return str(Path(path).resolve()) + _range_suffix(frames)


def spec_label(spec: str) -> str:
    """A 'PATH[:a-b]' as the tables and progress lines name it: the folder's name and range (kitti-07:120-159), also
    when PATH ends in a slash (a shell's completion adds one: the name was ':120-159')."""
    path, frames = parse_seq_spec(spec)
    return Path(path).name + _range_suffix(frames)


def shared_frames(specs: list[str], others: list[str], at_least: int = 1) -> list[str]:
    """Where two lists of 'PATH[:a-b]' specs take the same ``at_least`` frames or more of one folder ('NAME frames
    a-b', 'NAME, every frame'): training frames given as validation make its F-measure reward memorising them, and a
    pair in two evaluated ranges counts twice."""
    found = []
    for spec in specs:
        path, frames = parse_seq_spec(spec)
        for other in others:
            other_path, other_frames = parse_seq_spec(other)
            if Path(path).resolve() != Path(other_path).resolve():
                continue
            if frames is None and other_frames is None:
                found.append(f"{Path(path).name}, every frame")
                continue
            lo = max(r.start for r in (frames, other_frames) if r is not None)
            hi = min(r.stop for r in (frames, other_frames) if r is not None) - 1
            if hi - lo + 1 >= at_least:
                found.append(f"{Path(path).name} frames {lo}-{hi}")
    return found


def to_correspondences(pair: PairData, with_labels: bool = True) -> Correspondences:
    """The selectors' view of a pair (imported lazily: selectors pull in the network)."""
    from ..core.selectors import Correspondences

    x0, x1 = pair.normalized()
    cam = pair.seq.camera
    size = (cam.width, cam.height)
    return Correspondences(pair.k0, pair.k1, pair.a0, pair.a1, x0, x1, pair.matches.ratio, pair.matches.mutual,
                           cam.focal, size, size, pair.labels if with_labels else None)

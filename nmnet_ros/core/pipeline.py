"""Frontend: one camera frame in, selected matches and relative pose to the previous frame out.

The node, the bag tools and the demo are thin shells around this object. It keeps the previous
frame's features so each frame is detected once. Work comes in two stages that may run on two
threads (the node's schedule): :meth:`Frontend.prepare` detects a frame and matches it to the frame
prepared before it, :meth:`Frontend.process_prepared` relates it to the previous frame (NM-Net,
pose). The matches are used only when they were made against the very features the second stage
holds as its previous frame, with the current matching settings; otherwise it matches again.
Where matching runs is decided from the measured stage costs (``match_stage: auto``): in the first
stage when that shortens the slower stage (2000 keypoints: matching grows with N^2), else in the second.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import cv2
import numpy as np

from .detectors import make_detector
from .features import Detector, Features
from .geometry import Camera, PoseEstimate, fit_rotation, sampson_px, scale_pixels
from .matching import Matches, match_descriptors
from .matching import warm_up as warm_up_matching
from .planes import one_of_a_plane
from .selectors import GROUND_TRUTH, METHODS, Correspondences, Selection, build
from .settings import FRONTEND_DEFAULTS, POSE_ESTIMATORS, inert, problem
from .tracks import NO_TRACK, continue_tracks

DEFAULT_CONFIG: dict = dict(FRONTEND_DEFAULTS)  # the settings vocabulary's front-end settings (core/settings.py)

DETECTOR_KEYS = ("detector", "max_keypoints")  # resize_width restarts the chain by itself: another frame size
SELECTOR_CONFIG = ("score_threshold", "k", "pose_threshold_px", "pose_refine_iterations", "nmnet_precision",
                   "fallback_min_inliers")
SELECTOR_KEYS = ("pose_estimator", "weights", *SELECTOR_CONFIG)


def selector_name(pose_estimator: str) -> str:
    """The selector (``nmnet eval``'s method) a pose_estimator runs: the node's four names, or offline any method."""
    return POSE_ESTIMATORS.get(pose_estimator, pose_estimator)


def _detector(c: dict) -> Detector:
    return make_detector(c["detector"], {"max_keypoints": c["max_keypoints"]})


def _selector(c: dict) -> Callable[[Correspondences], Selection]:
    return build(selector_name(c["pose_estimator"]), {key: c[key] for key in SELECTOR_CONFIG},
                 {"nmnet": c["weights"]} if c["weights"] else None)


# statuses of a frame that starts a new chain: nothing to relate it to (its relative_pose says "no estimate")
RESTARTS = ("first_frame", "size_changed", "time_jump")


def _settled(config: dict) -> dict:
    """``config`` over the defaults, checked (ValueError naming the setting and its range, or an unknown name)
    before any frame, not on the first one; weights as a string ('' = shipped)."""
    if unknown := sorted(set(config) - set(DEFAULT_CONFIG)):
        raise ValueError(f"unknown front-end setting(s) {unknown}; known: {', '.join(DEFAULT_CONFIG)}")
    c = {**DEFAULT_CONFIG, **config}
    c["weights"] = str(c["weights"] or "")
    for key, value in c.items():
        if key == "pose_estimator" and value in METHODS:  # offline (replay --pose-estimator): any nmnet eval method
            if value in GROUND_TRUTH:  # they read ground-truth labels, which only sequence folders have (nmnet eval)
                raise ValueError(f"pose_estimator {value!r} needs each match's ground-truth label, which only `nmnet eval` "
                                 "on sequence folders has: on frames it would select nothing; choose another (see nmnet eval)")
            continue
        if (why := problem(key, value, strict=False)) is not None:
            raise ValueError(why)
    for line in inert(c):
        warnings.warn(line, stacklevel=3)
    return c


def downscaled(image: np.ndarray, width: int) -> np.ndarray:
    """``image`` shrunk to ``width`` pixels wide, aspect kept (area averaging), when wider and ``width`` > 0."""
    h, w = image.shape[:2]
    if width <= 0 or w <= width:
        return image
    return cv2.resize(image, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA)


def to_frame_pixels(k: np.ndarray, size: tuple[int, int], full: tuple[int, int]) -> np.ndarray:
    """Keypoints detected at ``size`` in the pixels of the frame as it came (``full``)."""
    return k if size == full else scale_pixels(k, full[0] / size[0], full[1] / size[1]).astype(k.dtype)


def match_first(detect_ms: float, match_ms: float, rest_ms: float) -> bool:
    """Whether matching in the first stage (beside detection) makes the slower of two pipelined stages
    faster than matching in the second (beside NM-Net and the pose)."""
    return max(detect_ms + match_ms, rest_ms) < max(detect_ms, match_ms + rest_ms)


def stamp_order(last: float | None, stamp: float, time_jump_s: float) -> str | None:
    """How a frame's stamp follows the last frame taken: ``None`` (later, or the first), ``"time_jump"``
    (more than ``time_jump_s`` earlier: a bag loop or a clock reset; a new chain starts from it), else
    ``"duplicate_stamp"`` / ``"out_of_order_stamp"``: the frame is skipped, as relating it would give a
    pose for no time step or one backwards in time. ``"negative_stamp"``: skipped too, as ROS time cannot
    be negative (rclpy refuses it, and a recording cannot log it); ``"invalid_stamp"`` (NaN, from
    :func:`~nmnet_ros.interface.posemsg.stamp_seconds`): nanosec outside 0 .. 999,999,999 is no ROS time either. The node and
    the replay apply the same rule."""
    if stamp != stamp:
        return "invalid_stamp"
    if stamp < 0:
        return "negative_stamp"
    if last is None or stamp > last:
        return None
    if stamp < last - time_jump_s:
        return "time_jump"
    return "duplicate_stamp" if stamp == last else "out_of_order_stamp"


def stamp_warning(kind: str, last: float | None, stamp: float, arrival: str = "stamp_source:=arrival") -> str:
    """What the node and the replay say about a frame :func:`stamp_order` did not take in order; ``arrival``: how to
    stamp frames by their arrival instead, where they say so (the node's parameter; the replay's option)."""
    if kind == "time_jump":
        return (f"frame stamp {stamp:.6f} is {last - stamp:.1f} s before the previous one (a bag played in a loop, or "
                "the clock was reset): restarting from this frame")
    if kind == "invalid_stamp":
        return ("frame stamp is not a ROS time (its nanosec is not below 1,000,000,000): skipped; check how the driver "
                "fills header.stamp (sec and nanosec, as rclpy's Time.to_msg() does)")
    if kind == "negative_stamp":
        return (f"frame stamp {stamp:.6f} is negative: skipped (ROS time starts at 0; check the driver's clock, or how "
                "the bag was restamped)")
    unstamped = f" (a stamp of 0: does the camera driver stamp its frames? If not, {arrival} stamps them on arrival)" \
        if stamp == 0 else ""
    return f"frame stamp {stamp:.6f} is not after the previous {last:.6f} ({kind}): skipped{unstamped}"


@dataclass
class FrameResult:
    """What the front end has to say about one frame (relative to the previous one)."""

    stamp: float
    status: str  # ok | too_few_matches | no_motion | pose_failed, or one of RESTARTS
    k0: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))  # previous frame, pixels
    k1: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))  # current frame, pixels
    scores: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    mask: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    track_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # per match; NO_TRACK if not selected
    pose: PoseEstimate | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    num_keypoints: int = 0
    pose_matches: int = 0  # the matches the pose rests on (the robust fit's inliers): the published covariance's n
    tracks_continued: int = 0  # selected matches that continue a track of the frame before

    @property
    def num_selected(self) -> int:
        return int(self.mask.sum())

    @property
    def plane_ambiguous(self) -> bool:
        """The matches lie on a plane two poses fit alike; the pose carries the other (planes.py)."""
        return self.pose is not None and self.pose.alternative is not None


@dataclass
class Prepared:
    """A frame after the first stage: its features, and its matches to the frame prepared before it."""

    feats: Features
    size: tuple[int, int]  # (width, height) detected on
    timings_ms: dict[str, float]
    full: tuple[int, int]  # (width, height) of the frame as it came (larger when resize_width shrank it)
    matches: Matches | None = None
    against: Features | None = None  # the features ``matches`` were made against
    match_key: tuple = ()  # the matching settings they were made with
    detector: Detector | None = None  # the detector that made ``feats``: frames of two detectors are never related
    camera: Camera | None = None  # the front end's camera when the frame was prepared (fitted to its size in the node)
    track_ids: np.ndarray | None = None  # per keypoint, once related (see tracks.py); None: in no track

    def camera_detected(self, fallback: Camera) -> Camera:
        """The camera of the frame as detected on: its own (set when prepared, else ``fallback``), scaled when
        resize_width shrank the frame. Each frame has its own: a zoom camera's K changes frame to frame."""
        cam = self.camera if self.camera is not None else fallback
        return cam if self.size == self.full else cam.resized(*self.size, self.full)


def related(a: Prepared, b: Prepared) -> bool:
    """Whether two prepared frames can be matched: made by the same detector, at the same sizes."""
    return a.detector is b.detector and (a.size, a.full) == (b.size, b.full)


@dataclass(frozen=True)
class Settings:
    """The front end's settings and what is built from them, swapped whole by :meth:`Frontend.reconfigure`: each
    stage reads them once per frame, so a frame never mixes the settings before and after a change."""

    config: dict
    detector: Detector
    select: Callable[[Correspondences], Selection]

    def match_key(self) -> tuple:
        """The matching settings, as recorded with matches made in the first stage."""
        c = self.config
        return (("ratio", 0.8 if c["matching"] == "ratio" else None), ("mutual", c["matching"] == "mutual"),
                ("gemm", c["match_gemm"]))


class Frontend:
    """Hessian-affine + NN matching + NM-Net (or another selector) + relative pose, frame to frame."""

    def __init__(self, camera: Camera | None = None, config: dict | None = None) -> None:
        c = _settled(config or {})
        self.camera = camera
        self.settings = Settings(c, _detector(c), _selector(c))
        warm_up_matching()  # like the detector's and NM-Net's kernels: compiled before the first frame
        self.prev: tuple[float, Prepared] | None = None  # the previous frame: stamp, the first stage's output
        self._last_prepared: Prepared | None = None  # the first stage's own previous frame
        self._cost_ms: dict[str, float] = {}  # running means of the stages' parts, for match_stage: auto
        self._next_track = 0  # the first unused track id (ids are never reused, not even after a restart)
        self._motion: np.ndarray | None = None  # the last pair's translation direction, when that pair had a pose

    @property
    def config(self) -> Mapping:
        """The current settings, read-only (change them with :meth:`reconfigure`); a view, not a copy: the node reads
        it for every frame."""
        return MappingProxyType(self.settings.config)

    @property
    def detector(self) -> Detector:
        return self.settings.detector

    @property
    def select(self) -> Callable[[Correspondences], Selection]:
        return self.settings.select

    def reconfigure(self, changes: dict) -> None:
        """Apply config changes while running (the node's ``ros2 param set``), from the next frame of each stage.

        The new detector and selector are built before anything is swapped, so a change that fails
        (an unreadable weights file, an unknown name) raises and leaves the front end as it was. The settings are
        swapped whole (:class:`Settings`) and each stage reads them once per frame, so a frame in flight finishes
        with the settings it started with. A new detector restarts the chain: each frame carries its detector, and
        one detected before the swap is never related to one after.
        """
        old = self.settings
        c = _settled({**old.config, **changes})
        detector = _detector(c) if any(c[key] != old.config[key] for key in DETECTOR_KEYS) else old.detector
        select = _selector(c) if any(c[key] != old.config[key] for key in SELECTOR_KEYS) else old.select
        self.settings = Settings(c, detector, select)
        if detector is not old.detector:
            self._cost_ms.clear()  # other features, other costs

    def _continue_tracks(self, before: Prepared, p: Prepared, idx: np.ndarray, mask: np.ndarray,
                         scores: np.ndarray) -> tuple[np.ndarray, int]:
        """Track ids of the selected matches (one per match, NO_TRACK for the others) and how many of them continue a
        track (the ids handed out before this pair); keeps ``p``'s ids for its successor."""
        prev_ids = before.track_ids if before.track_ids is not None else np.full(len(before.feats), NO_TRACK, np.int64)
        first_new = self._next_track
        p.track_ids, selected, self._next_track = continue_tracks(prev_ids, idx[mask], scores[mask], len(p.feats),
                                                                  first_new)
        ids = np.full(len(idx), NO_TRACK, np.int64)
        ids[mask] = selected
        return ids, int((selected < first_new).sum())

    def reset(self) -> None:
        """Forget the previous frame (the next frame starts a new chain)."""
        self.prev = self._last_prepared = None

    def detect(self, image: np.ndarray) -> Features:
        """Features of one image (the expensive stage)."""
        return self.detector(image)

    def _note_cost(self, part: str, ms: float) -> None:
        old = self._cost_ms.get(part)
        self._cost_ms[part] = ms if old is None else 0.8 * old + 0.2 * ms

    def _match_in_first_stage(self, s: Settings) -> bool:
        where = s.config["match_stage"]
        if where != "auto":
            return where == "first"
        cost = [self._cost_ms.get(part) for part in ("detect", "match", "rest")]
        return None not in cost and match_first(*cost)

    def _match(self, s: Settings, f0: Features, f1: Features, timings: dict[str, float]) -> Matches:
        """Putative matches with the settings ``s``, timed (and noted as a stage cost)."""
        t = time.perf_counter()
        m = match_descriptors(f0.descriptors, f1.descriptors, dict(s.match_key()))
        timings["match"] = 1000 * (time.perf_counter() - t)
        self._note_cost("match", timings["match"])
        return m

    def prepare(self, image: np.ndarray) -> Prepared:
        """First stage: detect, then match to the frame prepared before this one (when of the same size)."""
        t = time.perf_counter()
        s = self.settings  # read once: reconfigure may swap them meanwhile
        full = (image.shape[1], image.shape[0])
        image = downscaled(image, s.config["resize_width"])
        p = Prepared(s.detector(image), (image.shape[1], image.shape[0]), {}, full, detector=s.detector, camera=self.camera)
        p.timings_ms["detect"] = 1000 * (time.perf_counter() - t)  # with the downscaling, if any
        self._note_cost("detect", p.timings_ms["detect"])
        last, self._last_prepared = self._last_prepared, p
        if last is not None and related(last, p) and self._match_in_first_stage(s):
            p.match_key, p.against = s.match_key(), last.feats
            p.matches = self._match(s, last.feats, p.feats, p.timings_ms)
        return p

    def process(self, image: np.ndarray, stamp: float) -> FrameResult:
        """Detect, then relate to the previous frame; always keeps this frame as the next reference."""
        return self.process_prepared(self.prepare(image), stamp)

    def process_prepared(self, p: Prepared, stamp: float, timings: dict[str, float] | None = None) -> FrameResult:
        """Second stage: relate a prepared frame to the previous one (its matches reused when they were
        made against that very frame with the current settings). The frame's own camera is the one set when it
        was prepared: in the node the first stage sets the next frame's while this one is being related."""
        s = self.settings  # read once: reconfigure may swap them meanwhile
        c = s.config
        camera = p.camera if p.camera is not None else self.camera
        if camera is None:
            raise RuntimeError("Frontend has no camera: set .camera (from CameraInfo or parameters) first")
        feats, size = p.feats, p.size
        timings = {**(timings or {}), **p.timings_ms}
        prev, self.prev = self.prev, (stamp, p)
        motion, self._motion = self._motion, None  # the motion before this pair; set again below if it gets a pose
        if prev is None or prev[1].detector is not p.detector:  # the first frame, or the first of a new detector
            return FrameResult(stamp, "first_frame", timings_ms=timings, num_keypoints=len(feats))
        if not related(prev[1], p):
            return FrameResult(stamp, "size_changed", timings_ms=timings, num_keypoints=len(feats))
        if stamp_order(prev[0], stamp, c["time_jump_s"]) == "time_jump":
            return FrameResult(stamp, "time_jump", timings_ms=timings, num_keypoints=len(feats))
        before = prev[1].feats
        fits = p.against is before and p.match_key == s.match_key()
        m = p.matches if fits else self._match(s, before, feats, timings)
        k0, k1 = before.keypoints[m.idx[:, 0]], feats.keypoints[m.idx[:, 1]]
        cam0, cam = prev[1].camera_detected(camera), p.camera_detected(camera)
        base = dict(k0=to_frame_pixels(k0, size, p.full), k1=to_frame_pixels(k1, size, p.full), timings_ms=timings,
                    num_keypoints=len(feats), scores=np.zeros(len(m), np.float32), mask=np.zeros(len(m), bool),
                    track_ids=np.full(len(m), NO_TRACK, np.int64))
        if len(m) < c["min_matches"]:
            return FrameResult(stamp, "too_few_matches", **base)
        corr = Correspondences(k0, k1, before.frames[m.idx[:, 0]], feats.frames[m.idx[:, 1]],
                               cam0.normalize(k0), cam.normalize(k1), m.ratio, m.mutual, cam.focal, size, size)
        t = time.perf_counter()
        sel = s.select(corr)
        timings["select+pose"] = 1000 * (time.perf_counter() - t)
        self._note_cost("rest", timings["select+pose"])
        status, pose = self._status(c, sel, corr, k0, k1, cam.focal)
        if status == "ok":
            pose = one_of_a_plane(pose, corr.x0[sel.mask], corr.x1[sel.mask], cam.focal, motion)
            self._motion = pose.t
        mask = self._published(c, sel, pose, corr) if status == "ok" else sel.mask
        base["scores"] = sel.scores.astype(np.float32) if sel.scores is not None else mask.astype(np.float32)
        base["mask"] = mask
        base["pose_matches"] = int(sel.mask.sum())
        base["track_ids"], base["tracks_continued"] = self._continue_tracks(prev[1], p, m.idx, mask, base["scores"])
        return FrameResult(stamp, status, pose=pose, **base)

    @staticmethod
    def _status(c: dict, sel: Selection, corr: Correspondences, k0: np.ndarray, k1: np.ndarray, focal: float
                ) -> tuple[str, PoseEstimate | None]:
        """What the selection ``sel`` makes of the pair with the settings ``c``: (status, pose)."""
        if sel.mask.sum() < c["min_matches"]:
            return "too_few_matches", None
        # No measurable baseline: the camera stood (flow below static_flow_px) or only turned (the rotation fitted
        # alone leaves less than static_parallax_px: keypoint noise). The essential matrix is undefined then (MAGSAC++
        # fails, or returns a direction drawn from noise), and the rotation alone is the estimate. The parallax bound is
        # low (0.25 px): a small sideways step before a distant scene also looks much like a turn, and the rotation
        # would absorb it.
        flow = np.median(np.linalg.norm(k1[sel.mask] - k0[sel.mask], axis=1))  # in the pixels detected on
        R, angles = fit_rotation(corr.x0[sel.mask], corr.x1[sel.mask])
        if flow < c["static_flow_px"] or np.median(angles) * focal < c["static_parallax_px"]:
            return "no_motion", PoseEstimate(R, np.zeros(3), np.zeros((3, 3)), sel.mask)
        return ("pose_failed", None) if sel.pose is None else ("ok", sel.pose)

    @staticmethod
    def _published(c: dict, sel: Selection, pose: PoseEstimate, corr: Correspondences) -> np.ndarray:
        """The matches ~/matches carries: the pose fit's inliers, or with ``matches_within_px`` every match the fit
        was given that lies within that Sampson distance of the final pose (more matches, longer tracks)."""
        px = c["matches_within_px"]
        if not px:
            return sel.mask
        candidates = sel.candidates if sel.candidates is not None else sel.mask
        return candidates & (sampson_px(pose, corr.x0, corr.x1, corr.focal) < px)

"""The settings vocabulary: every setting of the node and the front end, with one name, default, range and help.

The node's declared parameters and ``--help``, ``config/nmnet.yaml``, the tools' options (``--max-keypoints`` on
replay, eval, train, ...), the :class:`~nmnet_ros.core.pipeline.Frontend`'s config keys and the docs' parameter table
are all made from :data:`SETTINGS`, so a setting has the same name everywhere. Pure data: importing it costs nothing
(``nmnet --help`` answers at once).
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass

Value = bool | int | float | str

# Mirrors of registries that import torch (tested equal): the names a setting may take.
DETECTOR_NAMES = ("hessian-affine", "hessian-affine-fast", "sift")
PRECISION_NAMES = ("auto", "float32", "bfloat16")  # auto = bfloat16 where the CPU has it natively
# the correspondence selectors (core/selectors.py), as nmnet eval names them
METHODS = ("nmnet", "nmnet-sp", "ratio", "ratio+magsac", "ratio+poselib", "ratio+prosac", "nn+ransac", "nn+magsac", "gms", "lpm",
           "nmnet+magsac", "nmnet+ratio+magsac", "nmnet+prosac", "oracle", "oracle-pool", "oracle+prosac")
POSE_ESTIMATORS = {  # the node's pose_estimator names and the selector (nmnet eval's method) each runs
    "prosac": "nmnet+prosac", "ratio_magsac": "nmnet+ratio+magsac", "magsac": "nmnet+magsac", "weighted8": "nmnet",
    "classic": "ratio+magsac"}


@dataclass(frozen=True)
class Setting:
    """One setting: its name (the node's parameter, the Frontend's key, ``--name-with-dashes`` in the tools)."""

    name: str
    default: Value
    help: str  # one line for YAML comments and tables; ``details`` adds the rest
    choices: tuple[str, ...] = ()
    range: tuple[float, float] | None = None
    details: str = ""
    node: bool = True  # a parameter of nmnet_node
    frontend: bool = True  # a key of the Frontend's config (else the node's ROS side: topics, QoS, messages)
    tools: tuple[str, ...] = ()  # the nmnet subcommands that take it as an option
    startup_only: bool = False  # fixed once the node runs (subscriptions, thread pools, the start-up camera)
    methods: tuple[str, ...] = ()  # the selectors (nmnet eval's methods) that read it; empty: every one

    @property
    def option(self) -> str:
        """The tools' option for it."""
        return "--" + self.name.replace("_", "-")

    @property
    def full_help(self) -> str:
        return f"{self.help}; {self.details}" if self.details else self.help

    def allowed(self) -> str:
        """Its range or choices, as the docs and errors say them ('' for a bool or a free string)."""
        if self.choices:
            return " | ".join(self.choices)
        if self.range is not None:
            return f"{self.range[0]:g} .. {self.range[1]:g}"
        return ""


FEATURES = ("replay", "eval", "train", "neighbors")  # the tools that detect features
SELECTING = ("replay", "eval")  # the tools that run NM-Net and a pose estimator as the node does
NETWORK_CUT = ("nmnet", "nmnet-sp", "nmnet+magsac", "nmnet+ratio+magsac")  # keep what NM-Net scores above its cut
MAGSAC_FITS = ("ratio+magsac", "nn+ransac", "nn+magsac", "nmnet+magsac", "nmnet+ratio+magsac", "oracle", "oracle-pool")  # OpenCV's fits

SETTINGS: tuple[Setting, ...] = (
    Setting("weights", "", "NM-Net weights file; empty = the weights shipped with the package", tools=SELECTING),
    Setting("detector", "hessian-affine-fast", "local feature frames", DETECTOR_NAMES, tools=FEATURES,
            details="hessian-affine-fast (batched, default), hessian-affine (kornia reference, far slower), sift "
                    "(similarity frames)"),
    Setting("max_keypoints", 2000, "keypoints detected per frame", range=(100, 8000), tools=FEATURES),
    Setting("resize_width", 0, "frames wider than this are downscaled to it before detection (0 = full resolution)",
            range=(0, 20000), tools=("replay",),
            details="aspect kept, K scaled; published matches stay in the image's own pixels"),
    Setting("k", 8, "compatibility neighbours per correspondence (the shipped network is trained with 8)",
            range=(2, 16), tools=("replay", "neighbors")),
    Setting("score_threshold", -1.0, "NM-Net inlier probability above which a match is kept; -1 = the threshold "
            "calibrated with the weights", range=(-1.0, 1.0), tools=SELECTING, methods=NETWORK_CUT),
    Setting("nmnet_precision", "auto", "NM-Net arithmetic", PRECISION_NAMES, tools=SELECTING,
            details="auto (bfloat16 where the CPU has native bfloat16, else float32), float32 (the exact network), "
                    "bfloat16 (faster on CPUs with native bfloat16, the same decisions to rounding)"),
    Setting("matching", "nn", "putative matches: nn (paper), mutual, ratio (Lowe 0.8)", ("nn", "mutual", "ratio"),
            tools=("replay",)),
    Setting("pose_estimator", "prosac", "how the pose is fitted", tuple(POSE_ESTIMATORS), tools=("replay",),
            details="prosac: PoseLib's LO-RANSAC (1 px) sampling the mutual matches of ratio < 0.9 in NM-Net's order, "
                    "the consensus counted over all of them; ratio_magsac: MAGSAC++ on the matches NM-Net and mutual "
                    "NN + ratio 0.8 both keep; magsac: MAGSAC++ "
                    "on NM-Net's selection; weighted8: eight-point weighted by NM-Net scores (the paper's; no robust "
                    "fit, far less accurate); classic: mutual NN + ratio 0.8 + MAGSAC++ without the network"),
    Setting("pose_threshold_px", 0.15, "MAGSAC++ inlier threshold (px), chosen on training pairs", range=(0.05, 10.0),
            tools=SELECTING, details="raise it for a poorly calibrated or rolling-shutter camera; also the pose "
                                     "polish's scale; prosac's PoseLib fit keeps the matches within 1 px, or within it above 1 px"),
    Setting("pose_refine_iterations", 5, "Levenberg-Marquardt steps polishing the pose after MAGSAC++ (0 = off)",
            range=(0, 50), tools=SELECTING, methods=MAGSAC_FITS, details="on the Cauchy-robust Sampson error; "
                                                                         "prosac's PoseLib fit refines its own pose"),
    Setting("fallback_min_inliers", 30, "when MAGSAC++ on NM-Net's selection keeps fewer matches, the pose is fitted "
            "on mutual NN + ratio 0.8's matches instead (0 = never)", range=(0, 100000), tools=SELECTING,
            details="the pairs NM-Net leaves too little of (few inliers, wide baselines), where the classic "
                    "pre-filter's pose is far better; ratio_magsac and magsac", methods=("nmnet+magsac", "nmnet+ratio+magsac")),
    Setting("min_matches", 8, "fewer selected matches give no pose estimate (identity, variance 1e6)",
            range=(8, 100000), tools=("replay",)),
    Setting("static_flow_px", 1.0, "median flow (px) below which the camera counts as standing", range=(0.0, 1000.0),
            tools=("replay",), details="status no_motion: the rotation alone, zero translation"),
    Setting("static_parallax_px", 0.25, "median parallax (px) below which the camera counts as turning on the spot",
            range=(0.0, 1000.0), tools=("replay",),
            details="parallax: the flow the rotation fitted alone does not explain; status no_motion, the rotation "
                    "alone with zero translation"),
    Setting("matches_within_px", 0.0, "0: ~/matches carries the pose fit's inliers; > 0: every match the fit "
            "was given within this Sampson distance (px) of the pose", range=(0.0, 100.0), tools=("replay",),
            details="for a back end that wants more matches and longer tracks (ratio_magsac at 0.5: 1.5x the matches)"),
    Setting("time_jump_s", 1.0, "a frame stamped this many seconds before the previous one restarts the chain",
            range=(0.0, 86400.0), tools=("replay",), details="a bag played in a loop, a clock reset"),
    Setting("match_gemm", "auto", "descriptor similarities: auto (bfloat16 screen + float32 re-check where native), "
            "float32", PRECISION_NAMES, node=False),
    Setting("match_stage", "auto", "where matching runs: auto (the split with the shorter slower stage), first, second",
            ("auto", "first", "second"), node=False),
    # the node's ROS side (also read from a parameters file by nmnet replay where it applies)
    Setting("pose_sigma_rotation_deg", 0.5, "published rotation sigma per axis (deg) at 200 selected matches",
            range=(1e-4, 90.0), frontend=False, details="scaled by sqrt(200 / n); a conservative bound: nmnet replay "
                    "with ground truth prints the value that fits a recording"),
    Setting("pose_sigma_direction", 0.05, "published sigma of the unit translation direction at 200 selected matches",
            range=(1e-5, 2.0), frontend=False, details="per component, scaled as the rotation's"),
    Setting("stamp_source", "header", "a frame's time: header (its stamp) or arrival (the node's clock on arrival)",
            ("header", "arrival"), frontend=False, tools=("replay",),
            details="arrival: for a driver that leaves stamps at 0 or stamps on another clock; the outputs carry that time"),
    Setting("qos", "auto", "input QoS: auto (reliable when every image publisher offers it), sensor_data, reliable",
            ("auto", "sensor_data", "reliable"), frontend=False, startup_only=True,
            details="auto is re-checked every second; sensor_data: best effort, depth 5; reliable: depth 10"),
    Setting("rectified", False, "the image topic carries rectified frames (image_rect): use camera_info's P, no "
            "distortion", frontend=False, tools=("replay",)),
    Setting("max_image_pixels", 20_000_000, "larger frames, or over 4x camera_info's size, are bad_image, never "
            "decoded", range=(10_000, 1_000_000_000), frontend=False, tools=("replay",),
            details="a compressed frame's size is read from its header: bounds what one frame may cost in memory and time"),
    Setting("use_compressed", False, "subscribe image/compressed (sensor_msgs/CompressedImage) instead of image",
            frontend=False, startup_only=True),
    Setting("threads", 1, "CPU threads per pipeline stage (torch and OpenCV); the two stages run in parallel",
            range=(1, 64), frontend=False, startup_only=True),
    Setting("publish_debug_image", True, "draw matches on ~/debug_image (only built when someone subscribes)",
            frontend=False),
    Setting("fx", 0.0, "focal length x (px) used until camera_info arrives; 0 = wait for camera_info", range=(0.0, 1e5),
            frontend=False, startup_only=True),
    Setting("fy", 0.0, "focal length y (px), see fx", range=(0.0, 1e5), frontend=False, startup_only=True),
    Setting("cx", 0.0, "principal point x (px), see fx", range=(0.0, 1e5), frontend=False, startup_only=True),
    Setting("cy", 0.0, "principal point y (px), see fx", range=(0.0, 1e5), frontend=False, startup_only=True),
)

BY_NAME: dict[str, Setting] = {s.name: s for s in SETTINGS}
NODE: tuple[Setting, ...] = tuple(s for s in SETTINGS if s.node)
FRONTEND_DEFAULTS: dict[str, Value] = {s.name: s.default for s in SETTINGS if s.frontend}
DEFAULT_METHOD = POSE_ESTIMATORS[str(FRONTEND_DEFAULTS["pose_estimator"])]  # the default's selector, as eval names it

_TYPE_NAMES = {bool: "a bool", int: "an integer", float: "a float", str: "a string"}


def problem(name: str, value: object, strict: bool = True) -> str | None:
    """Why setting ``name`` cannot take ``value`` (None: it can). ``strict``: types as rclpy declares them (a float
    setting refuses an integer: write ``1.0``); otherwise an integer passes for a float, as in Python."""
    s = BY_NAME[name]
    kind = type(s.default)
    ok = type(value) is kind or (not strict and kind is float and type(value) is int)
    if not ok and not strict and kind is int and not isinstance(value, bool):
        ok = hasattr(value, "__index__")  # numpy integers
    if not ok:
        hint = f" (write {float(value)!r})" if kind is float and type(value) is int else ""
        return f"{name}: {value!r} is {_TYPE_NAMES.get(type(value), type(value).__name__)}, the setting {_TYPE_NAMES[kind]}{hint}"
    if s.choices:
        return None if value in s.choices else f"{name}: {value!r} is not one of {', '.join(s.choices)}"
    if s.range is not None and not s.range[0] <= value <= s.range[1]:
        return f"{name}: {value!r} is out of range {s.range[0]} .. {s.range[1]}"
    return None


def unread(config: Mapping[str, Value], methods: Collection[str]) -> list[Setting]:
    """The settings ``config`` moves from their defaults that none of ``methods`` (nmnet eval's names) reads."""
    return [s for s in SETTINGS
            if s.methods and not set(methods) & set(s.methods) and config.get(s.name, s.default) != s.default]


def inert(config: Mapping[str, Value]) -> list[str]:
    """A warning for each setting that ``config`` (a Frontend's, defaults filled in) moves from its default and its
    pose_estimator does not read: a change that would otherwise do nothing, silently."""
    estimator = str(config["pose_estimator"])
    method = POSE_ESTIMATORS.get(estimator, estimator)  # offline, pose_estimator may name an nmnet eval method
    return [f"{s.name} {config[s.name]!r} has no effect with pose_estimator {estimator!r}: only "
            f"{', '.join(name for name, m in POSE_ESTIMATORS.items() if m in s.methods)} read it"
            for s in unread(config, (method,))]


def for_tool(command: str) -> tuple[Setting, ...]:
    """The settings that ``nmnet COMMAND`` takes as options."""
    return tuple(s for s in SETTINGS if command in s.tools)

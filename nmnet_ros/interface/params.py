"""The node's parameters (names, defaults, ranges, what they do) and the front-end config they map to.

ROS-free, so the offline tools read the same parameters files as the node: ``nmnet replay
--params-file config/nmnet.yaml`` replays a bag with the settings the robot runs.
"""

from __future__ import annotations

import difflib
import fnmatch
import re
from collections.abc import Callable, Iterable
from pathlib import Path

import yaml

from ..core.bf16 import PRECISIONS
from ..core.detectors import DEFAULT_DETECTOR, DETECTORS
from ..core.selectors import DEFAULT_CONFIG as SELECTOR_DEFAULTS
from .imgconv import MAX_PIXELS
from .posemsg import DIR_SIGMA, ROT_SIGMA_DEG

PARAMS: dict[str, tuple] = {
    # name: (default, description, range or choices)
    "weights": ("", "NM-Net weights file; empty = the weights shipped with the package", None),
    "detector": (DEFAULT_DETECTOR, "local feature frames: hessian-affine-fast (batched, default), hessian-affine "
                 "(kornia reference, ~1 s/frame), sift (similarity frames)", tuple(DETECTORS)),
    "max_keypoints": (2000, "Hessian-affine keypoints per frame", (100, 8000)),
    "resize_width": (0, "frames wider than this many pixels are downscaled to it before detection (aspect kept, K scaled); "
                        "0 = full resolution. Published matches stay in the image's own pixels", (0, 20000)),
    "k": (8, "compatibility neighbours per correspondence (the shipped network is trained with 8)", (2, 16)),
    "score_threshold": (-1.0, "NM-Net inlier probability above which a match is published; -1 = the threshold "
                              "calibrated on validation and stored with the weights", (-1.0, 1.0)),
    "nmnet_precision": ("auto", "NM-Net arithmetic: auto (bfloat16 where the CPU has native bfloat16, else float32), "
                        "float32 (the exact network), bfloat16 (1.7x faster NM-Net with AVX512-BF16; same accuracy on "
                        "validation)", PRECISIONS),
    "matching": ("nn", "putative matches: nn (paper), mutual, ratio (Lowe 0.8)", ("nn", "mutual", "ratio")),
    "pose_estimator": ("ratio_magsac", "ratio_magsac: MAGSAC++ on the matches NM-Net and mutual NN + ratio 0.8 both keep; "
                       "magsac: MAGSAC++ on NM-Net's selection; weighted8: eight-point weighted by NM-Net scores (the paper's; no robust "
                       "fit, far less accurate: AUC@5 19 against 89 on validation); "
                       "classic: mutual NN + ratio 0.8 + MAGSAC++ without the network",
                       ("ratio_magsac", "magsac", "weighted8", "classic")),
    "pose_threshold_px": (SELECTOR_DEFAULTS["threshold_px"], "MAGSAC++ inlier threshold in pixels (chosen on training "
                          "pairs; raise it for a poorly calibrated or rolling-shutter camera)", (0.05, 10.0)),
    "pose_refine_iterations": (SELECTOR_DEFAULTS["refine_iterations"], "Levenberg-Marquardt steps polishing the pose "
                               "on the Cauchy-robust Sampson error after MAGSAC++ (0 = off)", (0, 50)),
    "min_matches": (8, "fewer selected matches than this give no pose estimate (identity, variance 1e6)", (8, 100000)),
    "static_flow_px": (1.0, "median flow of the selected matches (px) below which the camera counts as standing: "
                            "no_motion, the rotation alone with zero translation", (0.0, 1000.0)),
    "static_parallax_px": (0.25, "median parallax of the selected matches (px; the flow the rotation fitted alone does "
                                 "not explain) below which the camera counts as turning on the spot: no_motion, the "
                                 "rotation alone with zero translation", (0.0, 1000.0)),
    "matches_within_px": (0.0, "0: ~/matches carries the matches the pose rests on (MAGSAC++'s inliers at "
                              "pose_threshold_px); > 0: every match MAGSAC++ was given that lies within this Sampson "
                              "distance (px) of the final pose, for a back end that wants more matches and longer tracks "
                              "(0.5: 1.5x the matches)", (0.0, 100.0)),
    "time_jump_s": (1.0, "a frame stamped this many seconds before the previous one restarts the chain (bag loop, "
                         "clock reset)", (0.0, 86400.0)),
    "pose_sigma_rotation_deg": (ROT_SIGMA_DEG, "published rotation sigma per axis (degrees) at 200 selected matches, "
                                "scaled by sqrt(200 / n); the default is a conservative bound", (1e-4, 90.0)),
    "pose_sigma_direction": (DIR_SIGMA, "published sigma per component of the unit translation direction at 200 "
                             "selected matches, scaled as the rotation's", (1e-5, 2.0)),
    "stamp_source": ("header", "a frame's time: header (its stamp) or arrival (the node's clock when it arrives, for a "
                     "driver that leaves stamps at 0 or stamps on another clock; the outputs carry that time)",
                     ("header", "arrival")),
    "qos": ("auto", "input QoS: auto (images reliable when every image publisher offers it, else best effort, "
                    "re-checked every second), sensor_data (best effort, depth 5) or reliable (depth 10)",
            ("auto", "sensor_data", "reliable")),
    "rectified": (False, "the image topic carries rectified frames (image_proc's image_rect): the camera is camera_info's "
                         "P, without distortion (K and D describe the raw frames)", None),
    "max_image_pixels": (MAX_PIXELS, "frames with more pixels than this, or than 4x camera_info's width x height, are "
                         "refused as bad_image (a compressed one from its header, before decoding): bounds what one "
                         "frame may cost in memory and time", (10_000, 1_000_000_000)),
    "use_compressed": (False, "subscribe image/compressed (sensor_msgs/CompressedImage) instead of image", None),
    "threads": (1, "CPU threads per pipeline stage (torch and OpenCV); detection and the rest run in parallel, "
                   "so 1 fills 2 cores", (1, 64)),
    "publish_debug_image": (True, "draw matches on ~/debug_image (only built when someone subscribes)", None),
    "fx": (0.0, "focal length x (px) used until camera_info arrives; 0 = wait for camera_info", (0.0, 1e5)),
    "fy": (0.0, "focal length y (px), see fx", (0.0, 1e5)),
    "cx": (0.0, "principal point x (px), see fx", (0.0, 1e5)),
    "cy": (0.0, "principal point y (px), see fx", (0.0, 1e5)),
}

SELECTORS = {"weighted8": "nmnet", "magsac": "nmnet+magsac", "ratio_magsac": "nmnet+ratio+magsac", "classic": "ratio+magsac"}
# Fixed once the node runs (subscriptions, thread pools, the start-up camera); every other parameter
# can be changed with `ros2 param set` and takes effect from the next frame.
STARTUP_ONLY = ("qos", "use_compressed", "threads", "fx", "fy", "cx", "cy")


def frontend_config(p: dict) -> dict:
    """The front end's config for the node's parameter values."""
    return {
        "detector": p["detector"], "max_keypoints": p["max_keypoints"], "resize_width": p["resize_width"],
        "selector": SELECTORS[p["pose_estimator"]],
        "weights": p["weights"] or None, "score_threshold": p["score_threshold"] if p["score_threshold"] >= 0 else None,
        "mutual": p["matching"] == "mutual", "ratio": 0.8 if p["matching"] == "ratio" else None, "k": p["k"],
        "threshold_px": p["pose_threshold_px"], "refine_iterations": p["pose_refine_iterations"],
        "precision": p["nmnet_precision"], "min_matches": p["min_matches"], "static_flow_px": p["static_flow_px"],
        "static_parallax_px": p["static_parallax_px"], "time_jump_s": p["time_jump_s"],
        "matches_within_px": p["matches_within_px"],
    }


def pose_sigmas(p: dict) -> tuple[float, float]:
    """(rotation degrees, direction) sigmas of the published covariance at 200 matches, for ``posemsg``."""
    return p["pose_sigma_rotation_deg"], p["pose_sigma_direction"]


def check_choices(p: dict) -> None:
    """ValueError for a string parameter outside its choices (rclpy checks only types and ranges)."""
    for name, (_, _, rng) in PARAMS.items():
        if isinstance(rng, tuple) and isinstance(rng[0], str) and (why := check_value(name, p[name])) is not None:
            raise ValueError(f"parameter {why}")


NODE_NAME = "nmnet_node"
ROS_COMMON = ("use_sim_time",)  # parameters every ROS 2 node has: allowed in a file, nothing to do offline
ROS_BUILTIN = ("start_type_description_service",)  # rclpy declares it too (and qos_overrides.*)


_TYPE_NAMES = {bool: "a bool", int: "an integer", float: "a float", str: "a string"}


class ParamsFileError(ValueError):
    """A parameters file that cannot be read, or holds a value the node would refuse."""


def check_value(name: str, value: object) -> str | None:
    """Why the node would refuse ``value`` for parameter ``name`` (None: it takes it), as rclpy and the node check.

    Types are strict, as rclpy's: a float parameter given an integer is refused (write ``1.0``).
    """
    default, _, rng = PARAMS[name]
    kind = type(default)
    if type(value) is not kind:  # bool is not int, int is not float: as rclpy's declared types
        hint = f" (write {float(value)!r})" if kind is float and type(value) is int else ""
        return f"{name}: {value!r} is {_TYPE_NAMES.get(type(value), type(value).__name__)}, the parameter {_TYPE_NAMES[kind]}{hint}"
    if isinstance(rng, tuple) and isinstance(rng[0], str):
        return None if value in rng else f"{name}: {value!r} is not one of {rng}"
    if isinstance(rng, tuple) and not rng[0] <= value <= rng[1]:
        return f"{name}: {value!r} is out of range {rng[0]} .. {rng[1]}"
    return None


def _sections(doc: object, path: Path) -> list[dict]:
    """The ``ros__parameters`` mappings of a ROS 2 parameters file that apply to the node in some namespace (a replay
    is one camera's: ``/**``, ``nmnet_node``, ``/front/nmnet_node``, ``/front/*``), in file order."""
    if not isinstance(doc, dict):
        raise ParamsFileError(f"{path}: not a ROS 2 parameters file (a mapping of node names to ros__parameters)")
    found, nodes = [], set()
    for name, params in file_sections(doc):
        last = name.rsplit("/", 1)[-1]
        if last == "**" or fnmatch.fnmatchcase(NODE_NAME, last):
            found.append(params)
            if "*" not in name:
                nodes.add(name)
    if not found:
        raise ParamsFileError(f"{path}: no ros__parameters for /** or {NODE_NAME} (found: {', '.join(map(str, doc)) or 'nothing'})")
    if len(nodes) > 1:  # a robot's file for several cameras: which one's values a replay takes is not for us to guess
        raise ParamsFileError(f"{path}: sections for several nodes ({', '.join(sorted(nodes))}); a replay is one camera's: "
                              "give a file with that camera's section (and /** for what they share)")
    return found


def not_parameters(names: Iterable[str]) -> list[str]:
    """What to say of names given to the node as parameters (``-p``, a parameters file) that it does not have: rclpy
    ignores them without a word, so a misspelt one (``max_keypoint``) left the default in force unseen."""
    said = []
    for name in names:
        if name in PARAMS or name in ROS_COMMON or name in ROS_BUILTIN or name.startswith("qos_overrides."):
            continue
        near = difflib.get_close_matches(name, PARAMS, n=1)
        said.append(f"{name!r} is not an {NODE_NAME} parameter: ignored" + (f"; did you mean {near[0]!r}?" if near else "")
                    + " (the list: nmnet_node --help)")
    return said


def file_sections(doc: object) -> list[tuple[str, dict]]:
    """(node name, ``ros__parameters``) of every section of a ROS 2 parameters file; nested namespaces are joined."""
    found: list[tuple[str, dict]] = []

    def walk(name: str, body: object) -> None:
        if not isinstance(body, dict):
            return
        if isinstance(body.get("ros__parameters"), dict):
            found.append((name, body["ros__parameters"]))
        for key, inner in body.items():
            if key != "ros__parameters":
                walk(f"{name}/{str(key).strip('/')}", inner)

    for key, body in (doc.items() if isinstance(doc, dict) else ()):
        walk("/" + str(key).strip("/"), body)
    return found


def section_applies(name: str, node: str) -> bool:
    """Whether a parameters file's section (``/**``, ``nmnet_node``, ``/front/*``) applies to the node of fully
    qualified name ``node``, as rcl matches them: ``*`` stands for one name, ``**`` for any number."""
    def match(pattern: list[str], names: list[str]) -> bool:
        if not pattern:
            return not names
        if pattern[0] == "**":
            return any(match(pattern[1:], names[i:]) for i in range(len(names) + 1))
        return bool(names) and fnmatch.fnmatchcase(names[0], pattern[0]) and match(pattern[1:], names[1:])

    return match([t for t in name.split("/") if t], [t for t in node.split("/") if t])


def params_file_misses(path: Path, node: str) -> str | None:
    """What to say when a parameters file given to the node has no section for it (rclpy applies none of it, silently:
    a section keyed ``nmnet`` or another node's name); None when one applies or the file cannot be read (rcl said)."""
    try:
        sections = file_sections(yaml.safe_load(Path(path).read_text()))
    except (OSError, yaml.YAMLError):
        return None
    if any(section_applies(name, node) for name, _ in sections):
        return None
    return (f"{path}: no section applies to {node} (sections: {', '.join(n for n, _ in sections) or 'none'}): none of its "
            f"parameters are in force; key them /** or {node} (config/nmnet.yaml's form)")


def read_params_file(path: Path, warn: Callable[[str], None] = print) -> dict:
    """Every node parameter's value from a ROS 2 parameters file (``config/nmnet.yaml``'s form), defaults for the rest.

    Sections for ``/**`` and for the node (``nmnet_node``, any namespace, only one) apply in file order. A value the
    node would refuse raises :class:`ParamsFileError` naming the file and the parameter; a name the node
    does not have is reported through ``warn`` and ignored, as the node ignores it.
    """
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except OSError as e:
        raise ParamsFileError(f"{path}: cannot read the parameters file ({e.strerror or e})") from e
    except yaml.YAMLError as e:
        raise ParamsFileError(f"{path}: not valid YAML ({str(e).splitlines()[0]})") from e
    values = {name: default for name, (default, _, _) in PARAMS.items()}
    for section in _sections(doc, path):
        for said in not_parameters(section):  # as the node says it (and as rclpy, ignores the name)
            warn(f"{path}: {said}")
        for name, value in section.items():
            if name not in PARAMS:
                continue
            if (why := check_value(name, value)) is not None:
                raise ParamsFileError(f"{path}: {why}")
            values[name] = value
    return values


def rcl_arguments_error(message: str) -> str:
    """rcl's refusal of the ROS arguments (a --params-file it cannot open or parse, a malformed -p or -r), without
    its C source locations, and the forms it takes: rclpy raised it from ``rclpy.init`` as a traceback."""
    said = re.sub(r",? at /\S+:\d+", "", message).replace("failed to initialize rcl: ", "").replace(". Error: error not set", "")
    return f"{said} (the forms: -p name:=value, -r from:=to, --params-file FILE; see nmnet_node --help)"

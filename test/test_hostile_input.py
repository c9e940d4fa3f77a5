"""Hostile and malformed input to the tools and the core: nothing of the user's is written over, one frame's cost
is bounded, calibrations that cannot be true and stamps that are no ROS time are refused, each named.

The node's side of the same cases, over real DDS, is in test_node.py.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from nmnet_ros.core.geometry import Camera, CameraError
from nmnet_ros.core.pipeline import stamp_order, stamp_warning
from nmnet_ros.interface.caminfo import camera_from_info
from nmnet_ros.interface.imgconv import ImageError, decode_compressed, decode_message, pixel_cap
from nmnet_ros.interface.posemsg import stamp_seconds
from nmnet_ros.io.bags import BagReader, read_frames
from nmnet_ros.io.outputs import written_here
from nmnet_ros.tools.make_bag import make_bag

from .conftest import data_dir

ROOT = Path(__file__).resolve().parents[1]


def nmnet(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "nmnet_ros.tools.cli", *args], capture_output=True, text=True, cwd=ROOT,
                          timeout=600)


@pytest.fixture(scope="module")
def ros2_bag(tmp_path_factory) -> Path:
    """A ROS 2 bag folder (metadata.yaml + .mcap) of three KITTI frames, JPEG-compressed."""
    path = tmp_path_factory.mktemp("hostile") / "bag"
    assert make_bag(data_dir("kitti-07"), path, "mcap", compressed=True, frames=range(60, 63)) == 3
    return path


def contents(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_replay_writes_nothing_into_its_bag_or_over_a_users_file(ros2_bag, tmp_path):
    """`--json BAG/metadata.yaml` rewrote the bag's metadata (exit 0), so ros2 bag and rosbags could no longer open
    it; --json and the plots also replaced any existing file. Each is refused before any work, naming the path."""
    bag = tmp_path / "bag"
    shutil.copytree(ros2_bag, bag)
    before = contents(bag)
    user_json, user_png = tmp_path / "mine.json", tmp_path / "plots" / "errors.png"
    user_json.write_text('{"my": "results"}\n')
    user_png.parent.mkdir()
    cv2.imwrite(str(user_png), np.zeros((4, 4), np.uint8))
    beside = tmp_path / "o_matches.png"  # the default plots are named after --out, beside it
    cv2.imwrite(str(beside), np.zeros((4, 4), np.uint8))
    out = str(tmp_path / "o.mcap")
    cases = [(("--out", out, "--json", str(bag / "metadata.yaml")), f"--json {bag / 'metadata.yaml'} lies inside an input"),
             (("--out", out, "--json", str(bag / "new.json")), "lies inside an input of this command"),
             (("--out", str(bag / "o.mcap")), "lies inside an input of this command"),
             (("--out", out, "--plots", str(bag / "plots")), "--plots"),
             (("--out", out, "--json", str(user_json)), f"--json {user_json} exists and was not written by nmnet"),
             (("--out", out, "--plots", str(user_png.parent)), f"{user_png} exists and was not written by nmnet"),
             (("--out", out), f"{beside} exists and was not written by nmnet")]
    for args, said in cases:
        r = nmnet("replay", str(bag), *args, "--no-progress")
        assert r.returncode == 2 and said in r.stderr and "frames at" not in r.stdout, (args, r.stderr)
    assert contents(bag) == before and user_json.read_text() == '{"my": "results"}\n'
    assert BagReader(bag).topics  # the bag still opens
    beside.unlink()
    for _ in range(2):  # its own outputs it replaces: a rerun of the same command
        r = nmnet("replay", str(bag), "--out", out, "--json", str(tmp_path / "s.json"), "--no-progress")
        assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "s.json").read_text())["written_by"].startswith("nmnet_ros")
    assert written_here(tmp_path / "o_matches.png") and not written_here(user_png)
    assert not list(tmp_path.glob(".*.tmp")), "a temporary file was left"


def test_eval_make_bag_and_train_write_nothing_into_their_inputs(tmp_path):
    seq = tmp_path / "seq"
    src = data_dir("kitti-07")
    seq.mkdir()
    shutil.copy(src / "camera.yaml", seq)
    rows = [r for r in (src / "images.txt").read_text().splitlines() if r and not r.startswith("#")][:4]
    (seq / "images.txt").write_text("".join(f"{r.split()[0]} {src.resolve() / r.split(maxsplit=1)[1]}\n" for r in rows))
    shutil.copy(src / "groundtruth.txt", seq)
    before = contents(seq)
    r = nmnet("eval", str(seq), "--gaps", "1", "--methods", "ratio", "--json", str(seq / "groundtruth.txt"))
    assert r.returncode == 2 and f"--json {seq / 'groundtruth.txt'} lies inside an input" in r.stderr, r.stderr
    r = nmnet("eval", str(seq), "--gaps", "1", "--methods", "ratio", "--plot", str(seq / "curves.png"))
    assert r.returncode == 2 and "--plot" in r.stderr and "lies inside an input" in r.stderr, r.stderr
    mine = tmp_path / "mine.json"
    mine.write_text("[1, 2, 3]\n")
    r = nmnet("eval", str(seq), "--gaps", "1", "--methods", "ratio", "--json", str(mine))
    assert r.returncode == 2 and "exists and was not written by nmnet" in r.stderr, r.stderr
    r = nmnet("make-bag", str(seq), str(seq / "bag"))
    assert r.returncode == 2 and "lies inside an input" in r.stderr, r.stderr
    r = nmnet("train", "--train", str(seq), "--val", str(seq), "--out", str(seq / "run"), "--epochs", "1")
    assert r.returncode == 2 and f"--out {seq / 'run'} lies inside an input" in r.stderr, r.stderr
    assert contents(seq) == before and mine.read_text() == "[1, 2, 3]\n"


@pytest.mark.parametrize("stamp", ["inf", "1e300", "-0.5", "nan"])
def test_make_bag_names_the_file_and_line_of_a_stamp_no_bag_can_hold(tmp_path, stamp):
    """inf, 1e300 and a negative first stamp ended in struct.error (ros1) or OverflowError (mcap), nan in another
    traceback, none naming the file or the line."""
    src = data_dir("kitti-07")
    seq = tmp_path / "seq"
    seq.mkdir()
    shutil.copy(src / "camera.yaml", seq)
    rows = [r for r in (src / "images.txt").read_text().splitlines() if r and not r.startswith("#")][:6]
    rows[1] = f"{stamp} {rows[1].split(maxsplit=1)[1]}"
    (seq / "images.txt").write_text("# timestamp path\n" + "".join(f"{r.split()[0]} {src.resolve() / r.split(maxsplit=1)[1]}\n"
                                                                  for r in rows))
    for fmt, out in (("ros1", tmp_path / "o.bag"), ("mcap", tmp_path / "o")):
        r = nmnet("make-bag", str(seq), str(out), "--format", fmt)
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert f"{seq / 'images.txt'}:3: timestamp {stamp} is no ROS time" in r.stderr, r.stderr
        assert not out.exists()


def big_png(width: int, height: int) -> bytes:
    """A PNG of ``width`` x ``height`` black pixels: a few hundred KB that decode to width x height bytes."""
    return cv2.imencode(".png", np.zeros((height, width), np.uint8))[1].tobytes()


def test_a_frame_over_the_pixel_cap_is_refused_from_its_header_before_decoding():
    """A 0.05 MB PNG decoded to 12260x3700 (2 GB through the node); now its header is read and it is refused."""
    data = big_png(12260, 3700)
    assert len(data) < 100_000
    cap = pixel_cap(50_000_000, (1226, 370))
    assert cap == 4 * 1226 * 370
    with pytest.raises(ImageError, match=r"png frame is 12260x3700 = 45.4 MP, over the cap of 1.8 MP"):
        decode_compressed("png", data, cap)
    jpeg = cv2.imencode(".jpg", np.zeros((2000, 2000), np.uint8))[1].tobytes()
    with pytest.raises(ImageError, match=r"jpeg frame is 2000x2000 = 4.0 MP, over the cap of 1.8 MP"):
        decode_compressed("jpeg", jpeg, cap)
    assert decode_compressed("jpeg", jpeg, 50_000_000).shape == (2000, 2000)  # under the cap: decoded
    assert pixel_cap(50_000_000) == pixel_cap(50_000_000, (0, 0)) == 50_000_000  # no calibrated size: the parameter

    class Raw:  # a raw Image's fields: over the cap, refused before its pixels are touched
        height, width, encoding, step, is_bigendian, data = 3000, 3000, "mono8", 3000, 0, b""

    with pytest.raises(ImageError, match="image is 3000x3000 = 9.0 MP, over the cap"):
        decode_message(Raw(), cap)


@pytest.mark.parametrize("ext", [".pfm", ".hdr", ".tiff", ".webp"])
def test_compressed_data_other_than_jpeg_or_png_is_a_bad_image(ext):
    """A float PFM/HDR/TIFF was decoded and reached the detector (internal_error: IndexError)."""
    img = np.random.default_rng(0).random((40, 60, 3)).astype(np.float32)
    data = cv2.imencode(ext, img if ext != ".webp" else (255 * img).astype(np.uint8))[1].tobytes()
    with pytest.raises(ImageError, match="neither JPEG nor PNG"):
        decode_compressed("png", data)


def test_truncated_headers_are_bad_images():
    for data, said in ((b"\x89PNG\r\n\x1a\n\x00\x00", "IHDR"), (b"\xff\xd8\xff\xe0\x00\x10JFIF", "frame header")):
        with pytest.raises(ImageError, match=said):
            decode_compressed("png", data)


class Info:
    """The CameraInfo fields camera_from_info reads, as a KITTI-07 camera of 1226x370."""

    def __init__(self, **changes) -> None:
        self.k = [707.0912, 0.0, 601.8873, 0.0, 707.0912, 183.1104, 0.0, 0.0, 1.0]
        self.d, self.distortion_model, self.width, self.height = [0.0] * 5, "plumb_bob", 1226, 370
        self.binning_x = self.binning_y = 0
        self.roi = type("Roi", (), {"x_offset": 0, "y_offset": 0, "width": 0, "height": 0})()
        for k, v in changes.items():
            setattr(self, k, v)


@pytest.mark.parametrize("changes, said", [
    ({"k": [0.577, 0, 0.49, 0, 1.74, 0.49, 0, 0, 1]}, "fx = 0.577 px cannot be a 1226x370 camera's"),  # normalised
    ({"k": [4.0, 0, 3.4, 0, 4.0, 1.0, 0, 0, 1]}, "fx = 4 px cannot be a 1226x370 camera's"),  # millimetres
    ({"k": [707.0, 0, 1e6, 0, 707.0, 183.0, 0, 0, 1]}, "principal point cx = 1e+06 px lies far outside"),
    ({"binning_x": 1000, "binning_y": 1000}, "binning 1000x1000 leaves 1x0 of the 1226x370 sensor"),
    ({"roi": type("Roi", (), {"x_offset": 2000, "y_offset": 0, "width": 600, "height": 300})()},
     "roi (600x300 at 2000,0) reaches outside the 1226x370 sensor"),
    ({"d": [-2.0, 0.0, 0.0, 0.0, 0.0]}, "distortion D = [-2.0, 0.0, 0.0, 0.0, 0.0] folds back"),
    ({"d": [0.0, 0.0, 0.0, -10.0], "distortion_model": "equidistant"}, "equidistant distortion"),
])
def test_a_calibration_that_cannot_be_true_is_refused_naming_what_is_wrong(changes, said):
    """Each gave poses with a confidence they did not have (no_motion with variance 1e-6, an 89-degree rotation
    with sigma 0.4 degrees) and no bad_camera_info."""
    with pytest.raises(CameraError, match=said.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[").replace("+", r"\+")):
        camera_from_info(Info(**changes))


def test_real_calibrations_stay_plausible():
    """The shipped data's cameras, EuRoC's strong barrel lens and a T265-like fisheye pass the checks."""
    for name in ("kitti-07", "euroc-v101-cam0", "strecha-fountain-p11"):
        from nmnet_ros.io.datasets import Sequence

        assert Sequence.load(data_dir(name)).camera.width > 0
    Camera(np.array([[285.7, 0, 425.0], [0, 285.7, 398.0], [0, 0, 1]]), np.array([-0.0067, 0.0433, -0.0415, 0.0079]),
           848, 800, "equidistant")
    Camera(np.array([[458.7, 0, 367.2], [0, 457.3, 248.4], [0, 0, 1]]), np.array([-0.2834, 0.0740, 1.9e-4, 1.8e-5, 0]),
           752, 480)
    binned = camera_from_info(Info(binning_x=2, binning_y=2))
    assert (binned.width, binned.height) == (613, 185) and binned.K[0, 0] == pytest.approx(353.5456)


def test_a_stamp_that_is_no_ros_time_is_refused_like_a_negative_one():
    """nanosec >= 1e9 was processed and republished as is."""
    bad = type("Time", (), {"sec": 5, "nanosec": 1_500_000_000})()
    good = type("Time", (), {"sec": 5, "nanosec": 999_999_999})()
    assert stamp_order(4.0, stamp_seconds(bad), 1.0) == "invalid_stamp"
    assert stamp_order(4.0, stamp_seconds(good), 1.0) is None
    assert "not a ROS time" in stamp_warning("invalid_stamp", 4.0, stamp_seconds(bad))


def test_replay_skips_frames_over_the_pixel_cap_and_with_invalid_stamps(tmp_path):
    """The replay reads frames as the node does: an oversized PNG is a bad image, never decoded; a stamp whose nanosec
    is 1e9 or more is skipped as invalid_stamp."""
    from rosbags.rosbag2 import Writer

    from nmnet_ros.interface.caminfo import info_fields
    from nmnet_ros.io.bags import typestore
    from nmnet_ros.io.datasets import Sequence

    seq = Sequence.load(data_dir("kitti-07"))
    ts = typestore()
    T = ts.types
    bag = tmp_path / "hostile"
    with Writer(bag, version=9) as w:
        img_c = w.add_connection("/cam/image_raw/compressed", "sensor_msgs/msg/CompressedImage", typestore=ts)
        info_c = w.add_connection("/cam/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        frames = [(cv2.imencode(".png", seq.image(60))[1], 0), (np.frombuffer(big_png(12260, 3700), np.uint8), 0),
                  (cv2.imencode(".png", seq.image(61))[1], 2_000_000_000), (cv2.imencode(".png", seq.image(62))[1], 0)]
        for n, (data, nanosec) in enumerate(frames):
            hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=10 + n, nanosec=nanosec), frame_id="cam")
            info = T["sensor_msgs/msg/CameraInfo"](header=hdr, **info_fields(seq.camera, 1226, 370), binning_x=0, binning_y=0,
                                                  roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0,
                                                                                              width=0, do_rectify=False))
            msg = T["sensor_msgs/msg/CompressedImage"](header=hdr, format="png", data=np.ascontiguousarray(data).ravel())
            t = (10 + n) * 10**9
            w.write(info_c, t, ts.serialize_cdr(info, "sensor_msgs/msg/CameraInfo"))
            w.write(img_c, t + 1, ts.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))
    frames, _ = read_frames(BagReader(bag))
    got = list(frames)
    assert len(got) == 4 and got[1].image is None and "over the cap of 1.8 MP" in got[1].error
    assert got[2].stamp != got[2].stamp  # NaN: no ROS time
    r = nmnet("replay", str(bag), "--out", str(tmp_path / "o.mcap"), "--json", str(tmp_path / "s.json"), "--no-progress")
    assert r.returncode == 0, r.stderr
    s = json.loads((tmp_path / "s.json").read_text())
    assert s["warnings"] == {"bad_image": 1, "invalid_stamp": 1} and s["processed"] == 2, s


def test_a_training_folder_with_a_users_file_of_trains_names_is_refused_and_checkpoints_are_marked(tmp_path):
    """train writes history.json and summary.json into --out: a user's file of that name is refused before any work;
    a checkpoint nmnet wrote carries its mark, another .pt does not."""
    import torch

    from nmnet_ros.io.outputs import output_folder, written_by

    (tmp_path / "history.json").write_text('{"mine": 1}\n')
    with pytest.raises(FileExistsError, match="history.json exists and was not written by nmnet"):
        output_folder(tmp_path, "--out", "the checkpoints", (), ("history.json", "summary.json"))
    torch.save({"state_dict": {}, "written_by": written_by()}, tmp_path / "ours.pt")
    torch.save({"state_dict": {}}, tmp_path / "theirs.pt")
    assert written_here(tmp_path / "ours.pt") and not written_here(tmp_path / "theirs.pt")


@pytest.mark.slow
@pytest.mark.parametrize("closed", [("stdout",), ("stdout", "stderr")])
def test_a_reader_that_goes_away_leaves_the_tool_to_write_its_files(tmp_path, closed):
    """``nmnet eval ... --json r.json | head -1``: eval prints its tables before writing the JSON and the plot; the
    closed pipe ended it at the next line ("error: [Errno 32] Broken pipe", exit 2, nothing written)."""
    out = tmp_path / "r.json"
    proc = subprocess.Popen([sys.executable, "-m", "nmnet_ros.tools.cli", "eval", f"{data_dir('strecha-fountain-p11')}:0-3",
                             "--gaps", "1", "--methods", "ratio+magsac", "--json", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
    for name in closed:  # the reader is gone before the tool's first line
        getattr(proc, name).close()
    said = b"" if "stderr" in closed else proc.stderr.read()
    assert proc.wait(timeout=600) == 0, said
    assert b"Broken pipe" not in said and b"Exception ignored" not in said
    assert json.loads(out.read_text())["methods"]["ratio+magsac"]
    assert out.with_suffix(".png").is_file()

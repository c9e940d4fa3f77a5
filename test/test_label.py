"""nmnet label: ground truth for an unlabeled recording by reconstruction (real COLMAP through pycolmap, real data)."""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest

from nmnet_ros.core.geometry import Camera
from nmnet_ros.io.datasets import Sequence, write_camera_yaml
from nmnet_ros.io.outputs import written_here
from nmnet_ros.tools.label import frames_of, pick_keyframes, truth_check
from nmnet_ros.tools.make_bag import make_bag
from nmnet_ros.tools.options import SAMPLE_BAG

from .conftest import ROOT, data_dir

CAMERA = Camera(np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]]), width=320, height=240)


def nmnet(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "nmnet_ros.tools.cli", *args], capture_output=True, text=True, cwd=ROOT,
                          timeout=900)


@pytest.mark.slow
@pytest.mark.parametrize("scene, frames", [("strecha-fountain-p11", ""), ("kitti-07", ":0-59")])
def test_labels_of_a_reconstruction_agree_with_the_real_ground_truth(tmp_path, scene, frames):
    """The mapper never sees the ground truth; the consecutive keyframes' relative poses it gives agree with it to
    under 0.1 degree in rotation and 1 degree in translation direction, and the epipolar labels of the network's
    input matches agree on >= 97 %. The folder it writes reads as a sequence folder, its poses said to be a
    reconstruction."""
    out, summary = tmp_path / "labelled", tmp_path / "label.json"
    r = nmnet("label", f"{data_dir(scene)}{frames}", str(out), "--interval", "0", "--truth", str(data_dir(scene)),
              "--json", str(summary))
    assert r.returncode == 0, r.stderr
    check = json.loads(summary.read_text())["truth_check"]
    assert check["median_rot_deg"] < 0.1 and check["median_trans_deg"] < 1.0, check
    assert check["label_agreement_percent"] >= 97.0, check
    seq = Sequence.load(out)
    n = len(seq.paths)
    assert n == (11 if scene.startswith("strecha") else 60) and seq.poses is not None and seq.has_pose(0)
    note = json.loads((out / "reconstruction.json").read_text())
    assert note["registered"] == n and "reconstructed" in note["what"] and written_here(out / "reconstruction.json")
    assert "reconstruction" in (out / "groundtruth.txt").read_text().splitlines()[0]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # nothing left of the build


@pytest.mark.slow
def test_a_bag_is_labelled_with_its_camera_info_and_a_standing_camera_is_refused(tmp_path):
    """A bag (as replay reads it) gives its frames and its camera_info; a standing camera (EuRoC's MAV on the
    ground) or too few keyframes is refused with the reason and what to do, and leaves no output; so is a folder of
    someone else's."""
    bag = tmp_path / "run"
    assert make_bag(data_dir("kitti-07"), bag, "mcap", frames=range(60, 80)) == 20
    r = nmnet("label", str(bag), "--out", str(tmp_path / "from_bag"))  # the other tests: the output's former place
    assert r.returncode == 0, r.stderr
    seq = Sequence.load(tmp_path / "from_bag")
    truth = Sequence.load(data_dir("kitti-07"))
    assert np.allclose(seq.camera.K, truth.camera.K) and len(seq.paths) == 20
    assert np.allclose(seq.stamps, truth.stamps[60:80], atol=1e-6)  # the bag's header stamps
    unposed = tmp_path / "unposed"  # --truth without ground truth: refused before any work
    unposed.mkdir()
    for name in ("camera.yaml", "images.txt"):
        (unposed / name).write_text((tmp_path / "from_bag" / name).read_text())
    (unposed / "images").symlink_to(tmp_path / "from_bag" / "images")
    r = nmnet("label", str(bag), str(tmp_path / "checked"), "--truth", str(unposed))
    assert r.returncode == 2 and "has no groundtruth.txt" in r.stderr and not (tmp_path / "checked").exists(), r.stderr
    few = tmp_path / "few.mcap"  # 3 keyframes: "only 3 of 3 registered: the frames overlap too little", after COLMAP
    assert make_bag(data_dir("kitti-07"), few, frames=range(60, 63)) == 3
    r = nmnet("label", str(few), str(tmp_path / "from_few"))
    assert r.returncode == 2 and "reconstructing" not in r.stderr and not (tmp_path / "from_few").exists(), r.stderr
    assert f"{few}: 3 keyframe(s), and a reconstruction needs at least 10; give a longer recording" in r.stderr
    r = nmnet("label", str(data_dir("euroc-v101-cam0")), str(tmp_path / "still"))
    assert r.returncode == 2 and "barely moves" in r.stderr and "record while the robot moves" in r.stderr, r.stderr
    assert not (tmp_path / "still").exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "notes.txt").write_text("mine")
    r = nmnet("label", str(bag), str(theirs))
    assert r.returncode == 2 and "did not write" in r.stderr and (theirs / "notes.txt").read_text() == "mine"
    cut = tmp_path / "cut"  # a recording cut short: its readable part is labelled, and the cut is said
    shutil.copytree(bag, cut)
    mcap = next(cut.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size * 2 // 3])
    r = nmnet("label", str(cut), str(tmp_path / "from_cut"))
    assert r.returncode == 0 and "truncated" in r.stderr, r.stderr
    assert 2 <= len(Sequence.load(tmp_path / "from_cut").paths) < 20
    r = nmnet("label", str(bag), "--out", "/proc/nmnet/labelled")  # not writable, even by root
    assert r.returncode == 2 and "--out /proc/nmnet/labelled: cannot write in /proc/nmnet" in r.stderr, r.stderr
    images = tmp_path / "images"
    images.mkdir()
    (images / "a.png").write_bytes((data_dir("kitti-07") / "images" / "000000.png").read_bytes())
    r = nmnet("label", str(images), str(tmp_path / "x"))
    assert r.returncode == 2 and "needs --camera" in r.stderr


def textured(shift: int, size: tuple[int, int] = (240, 320)) -> np.ndarray:
    """A gray image of blobs, moved ``shift`` pixels to the right."""
    noise = np.random.default_rng(0).integers(0, 256, (size[0], size[1] + 64), dtype=np.uint8)
    return cv2.GaussianBlur(noise, (7, 7), 2)[:, 64 - shift:64 - shift + size[1]].copy()


@pytest.mark.parametrize("start", [0.0, 1.7e9])
def test_frames_at_the_keyframe_interval_are_every_one_a_keyframe(start):
    """At 10 Hz stamps (a folder of images at the default --fps, a bag's) and the default --interval 0.1 s, frames were
    dropped where float rounding put two stamps under 0.1 s apart (0.7 - 0.6): 6 of 10 kept."""
    frames = [(start + k / 10, textured(k)) for k in range(20)]
    assert len(list(pick_keyframes(iter(frames), 0.1, 0.0, 400, CAMERA, []))) == 20
    assert [s for s, _ in pick_keyframes(iter(frames), 0.2, 0.0, 400, CAMERA, [])] == [s for s, _ in frames[::2]]


def test_keyframes_that_run_out_before_the_recording_ends_are_said(capsys):
    """--max-frames stopped reading the recording without a word: a long run was labelled for its first minute."""
    frames = [(k / 10, textured(k)) for k in range(20)]
    assert len(list(pick_keyframes(iter(frames), 0.1, 0.0, 20, CAMERA, []))) == 20
    assert capsys.readouterr().err == ""
    assert len(list(pick_keyframes(iter(frames), 0.1, 0.0, 12, CAMERA, []))) == 12
    assert ("warning: --max-frames 12 keyframes reached 1.1 s into the recording; the rest of it is not labelled: "
            "raise --max-frames, or --interval to spread them over it") in capsys.readouterr().err


def test_a_folder_of_images_skips_one_that_does_not_decode_and_refuses_another_size(tmp_path, capsys):
    """A corrupt file among the images ended the run with a traceback (cv2.imread's None); it is now skipped with a
    warning naming it, the others keeping their stamps. An image of another size than --camera says is refused."""
    folder, calibration = tmp_path / "images", tmp_path / "camera.yaml"
    folder.mkdir()
    write_camera_yaml(calibration, CAMERA)
    for k in range(4):
        cv2.imwrite(str(folder / f"{k:04d}.png"), textured(k))
    (folder / "0002.png").write_bytes(b"not a png")
    args = argparse.Namespace(camera=calibration, image_topic=None, fps=10.0)
    frames, camera = frames_of(folder, args)
    assert [stamp for stamp, _ in frames] == [0.0, 0.1, 0.3] and camera.width == 320
    assert f"warning: {folder / '0002.png'}: cannot decode image (9 bytes)" in capsys.readouterr().err
    cv2.imwrite(str(folder / "0004.png"), textured(4, (480, 640)))
    with pytest.raises(ValueError, match=f"{folder / '0004.png'}: 640x480, but --camera {calibration} is for 320x240 "
                                         "images: give the calibration of the camera that took them"):
        list(frames_of(folder, args)[0])
    write_camera_yaml(calibration, Camera(CAMERA.K))  # no image size: the first image's is every image's
    with pytest.raises(ValueError, match=f"{folder / '0004.png'}: 640x480, but the folder's first image is 320x240: "
                                         "one camera's images are one size"):
        list(frames_of(folder, args)[0])


def test_an_option_for_another_kind_of_recording_is_said_to_be_ignored(tmp_path, capsys):
    """--fps (a folder of images' stamps) given for a bag or a sequence folder, and --image-topic given for a folder,
    did nothing without a word: the user meant something by them."""
    bag = tmp_path / "run.mcap"
    assert make_bag(data_dir("kitti-07"), bag, frames=range(60, 62)) == 2
    for source, option, warned in ((bag, "fps", True), (data_dir("kitti-07"), "fps", True),
                                   (data_dir("kitti-07"), "image_topic", True), (bag, "image_topic", False)):
        given = {"fps": None, "image_topic": None, option: 30.0 if option == "fps" else "/camera/image_raw"}
        args = argparse.Namespace(camera=None, **given)
        frames, _ = frames_of(source, args)
        assert len(list(frames)) >= 2
        flag = "--" + option.replace("_", "-")
        what = "stamps a folder of images" if option == "fps" else "names a bag's topic"
        assert (f"warning: {flag} {what}; {source} is not one: {flag} is ignored" in capsys.readouterr().err) == warned


def test_a_range_or_a_truth_that_does_not_fit_the_recording_is_refused_before_the_reconstruction(tmp_path):
    """`label kitti-07:0-3000` (160 frames) ended in an IndexError traceback; a --truth folder of other frames was
    found out after the reconstruction's minutes. Both are said before it, and leave no output."""
    r = nmnet("label", f"{data_dir('kitti-07')}:0-3000", str(tmp_path / "a"))
    assert r.returncode == 2 and "frames 0-3000 are not all in the folder; it has frames 0-159" in r.stderr, r.stderr
    r = nmnet("label", f"{SAMPLE_BAG}:0-10", str(tmp_path / "a"))  # it said to replay it, eval and train taking folders
    assert r.returncode == 2 and "a bag is read whole, it takes no frame range" in r.stderr, r.stderr
    bag = tmp_path / "run.mcap"
    assert make_bag(data_dir("kitti-07"), bag, frames=range(60, 72)) == 12
    r = nmnet("label", str(bag), str(tmp_path / "b"), "--truth", str(data_dir("strecha-entry-p10")))
    assert r.returncode == 2 and "reconstructing" not in r.stderr, r.stderr
    assert f"--truth {data_dir('strecha-entry-p10')}: none of its frames has a keyframe's stamp" in r.stderr
    r = nmnet("label", str(bag), str(tmp_path / "c"), "--min-flow", "300")  # it named only --interval
    assert r.returncode == 2 and "give a longer recording or a shorter --interval or a lower --min-flow" in r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]


def test_a_truth_without_poses_at_the_keyframes_is_said_before_any_check(tmp_path):
    """A --truth whose poses stop before the labelled frames (a tracker that lost the camera) has the keyframes'
    stamps but no pose there: nothing to check, said naming it (its message had never run)."""
    kitti = data_dir("kitti-07")
    images = [line.split() for line in (kitti / "images.txt").read_text().splitlines() if not line.startswith("#")]
    poses = [line for line in (kitti / "groundtruth.txt").read_text().splitlines() if not line.startswith("#")]

    def folder(name: str, frames: range, posed: range) -> Sequence:
        root = tmp_path / name
        root.mkdir()
        shutil.copy(kitti / "camera.yaml", root)
        (root / "images.txt").write_text("".join(f"{images[i][0]} {kitti / images[i][1]}\n" for i in frames))
        (root / "groundtruth.txt").write_text("".join(poses[i] + "\n" for i in posed))
        return Sequence.load(root)

    truth = folder("truth", range(10), range(2))  # poses for frames 0-1 only
    folder("labelled", range(4, 7), range(4, 7))
    with pytest.raises(ValueError, match="--truth T: it has no pose at any two consecutive keyframes the "
                                         "reconstruction posed: nothing to check the labels against"):
        truth_check(tmp_path / "labelled", truth, "T")


@pytest.mark.slow
def test_refined_intrinsics_are_the_ones_written_with_the_poses(tmp_path):
    """--refine-intrinsics let COLMAP fit the focal length, then wrote the calibration given beside poses made with
    the refined one: every epipolar label drawn from the folder used the wrong camera. A focal length 6 % off comes
    back within 0.5 % of the true one, in camera.yaml."""
    truth = Sequence.load(data_dir("strecha-fountain-p11")).camera
    off = Camera(truth.K * np.array([[1.06, 1, 1], [1, 1.06, 1], [1, 1, 1]]), truth.dist, truth.width, truth.height)
    write_camera_yaml(tmp_path / "off.yaml", off)
    r = nmnet("label", str(data_dir("strecha-fountain-p11")), str(tmp_path / "out"), "--interval", "0", "--camera",
              str(tmp_path / "off.yaml"), "--refine-intrinsics")
    assert r.returncode == 0, r.stderr
    K = Sequence.load(tmp_path / "out").camera.K
    assert abs(K[0, 0] / truth.K[0, 0] - 1) < 0.005 and abs(K[1, 1] / truth.K[1, 1] - 1) < 0.005, (K, truth.K)
    assert "refined" in json.loads((tmp_path / "out" / "reconstruction.json").read_text())["intrinsics"]


@pytest.mark.parametrize("model, dist, params, written_model, written", [
    ("plumb_bob", [], [700, 701, 320, 240], "plumb_bob", []),
    ("plumb_bob", [0.1, 0, 0, 0, 0], [700, 701, 320, 240, 0.11, 0.01, 0, 0], "plumb_bob", [0.11, 0.01, 0, 0, 0]),
    ("plumb_bob", [0.1, 0, 0, 0, 0.2], [700, 701, 320, 240, 0.1, 0, 0, 0, 0.2, 0.01, 0, 0], "rational_polynomial",
     [0.1, 0, 0, 0, 0.2, 0.01, 0, 0]),
    ("equidistant", [], [700, 701, 320, 240, 0.01, 0.02, 0, 0], "equidistant", [0.01, 0.02, 0, 0]),
])
def test_a_refined_calibration_keeps_its_lens_model(model, dist, params, written_model, written):
    """COLMAP's parameters (colmap_camera's order for the model it was given) back into a camera_info calibration."""
    from nmnet_ros.io.reconstruction import colmap_camera, refined_camera

    given = Camera(np.array([[690.0, 0, 319], [0, 690.0, 241], [0, 0, 1]]), np.array(dist, float), 640, 480, model)
    assert len(colmap_camera(given)[1]) == len(params)
    out = refined_camera(given, params)
    assert np.allclose(out.K, [[700, 0, 320], [0, 701, 240], [0, 0, 1]]) and (out.width, out.height) == (640, 480)
    assert out.model == written_model and np.allclose(out.dist, written), (out.model, out.dist)

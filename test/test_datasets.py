"""Sequence folder reader: real folders, pairs.txt, bad folders with clear errors."""

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from nmnet_ros.io.datasets import DatasetError, Sequence, has_baseline
from nmnet_ros.io.pairs import select_pairs

from .conftest import data_dir


def test_reads_real_sequence_and_relative_pose():
    seq = Sequence.load(data_dir("kitti-07"))
    assert len(seq) == 160 and seq.poses.shape == (160, 4, 4)
    assert seq.image(0).shape == (370, 1226)
    R, t = seq.relative_pose(0, 1)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert 0.05 < np.linalg.norm(t) < 2.0 and t[2] < 0  # driving forward: the scene comes closer
    assert seq.pairs((1, 2), range(0, 4)) == [(0, 1), (1, 2), (2, 3), (0, 2), (1, 3)]


def test_static_camera_pairs_are_excluded():
    seq = Sequence.load(data_dir("euroc-v101-cam0"))
    assert not has_baseline(seq, 0, 1)
    assert select_pairs(seq, (1, 5)) == []


def test_eval_and_neighbors_say_why_a_folder_gives_no_pairs(tmp_path, capsys):
    """nmnet eval said 'no pairs with ground truth and motion to evaluate' for a standing camera, a range too short
    for the gaps and a --stride past the range alike; it names which, as train does, before any features."""
    from nmnet_ros.core.detectors import make_detector
    from nmnet_ros.io.cache import FeatureCache
    from nmnet_ros.io.pairs import load_pairs

    cache = FeatureCache(make_detector("sift"), tmp_path)
    euroc, kitti = data_dir("euroc-v101-cam0"), data_dir("kitti-07")
    with pytest.raises(ValueError, match=f"^no pairs to evaluate: {euroc}: none of its 187 frame pairs \\(gaps 1,2\\) "
                                         "has a ground-truth pose on both frames, motion between them"):
        load_pairs([str(euroc)], (1, 2), cache)
    with pytest.raises(ValueError, match=f"{kitti}:3-4: its frames make no pairs \\(gaps 3\\)$"):
        load_pairs([f"{kitti}:3-4"], (3,), cache)
    with pytest.raises(ValueError, match=f"{kitti}:3-5: none of its pairs starts at a multiple of --stride 5"):
        load_pairs([f"{kitti}:3-5"], (1,), cache, stride=5)
    assert not any(tmp_path.iterdir())  # no features computed
    assert len(load_pairs([f"{kitti}:3-5"], (1,), cache, stride=2)) == 1  # (4, 5)
    from nmnet_ros.tools.cli import main  # nmnet neighbors printed an empty table, "0 pairs", exit 0

    assert main(["neighbors", str(euroc), "--gaps", "1", "--detector", "sift", "--cache", str(tmp_path)]) == 2
    assert f"nmnet neighbors: error: no pairs to evaluate: {euroc}: none of its 94 frame pairs" in capsys.readouterr().err


def test_ground_truth_stamped_in_nanoseconds_is_named_with_the_conversion(tmp_path):
    """A TUM file with ROS's nanosecond stamps (kitti-07's from 0: 1.04e8 apart) was read as seconds: every frame
    of a replay fell between its first two poses and was scored as standing still. Refused, with a command that
    converts it; the converted file reads as the original."""
    import shutil as sh
    import subprocess

    from nmnet_ros.io.trajectory import read_tum

    src = data_dir("kitti-07") / "groundtruth.txt"
    rows = [ln.split() for ln in src.read_text().splitlines() if ln and not ln.startswith("#")]
    ns = tmp_path / "gt_ns.txt"
    ns.write_text("# timestamp tx ty tz qx qy qz qw\n" + "".join(
        " ".join([str(round(float(r[0]) * 1e9)), *r[1:]]) + "\n" for r in rows))
    with pytest.raises(DatasetError, match=r"gt_ns.txt: poses a median of 1.04e\+08 s apart: the stamps look like "
                                           "nanoseconds") as said:
        read_tum(ns)
    command = str(said.value).split("e.g. ")[1].replace("in.txt", str(ns)).replace("out.txt", str(tmp_path / "s.txt"))
    if sh.which("awk"):
        subprocess.run(["sh", "-c", command], check=True)
        a, b = read_tum(tmp_path / "s.txt"), read_tum(src)
        assert np.allclose(a.stamps, b.stamps, atol=1e-9) and np.allclose(a.poses, b.poses)
    folder = tmp_path / "seq"  # a sequence folder's images.txt likewise (its frames found no pose)
    shutil.copytree(data_dir("strecha-fountain-p11"), folder)
    listing = [ln.split() for ln in (folder / "images.txt").read_text().splitlines() if ln and ln[0] != "#"]
    (folder / "images.txt").write_text("".join(f"{round(float(t) * 1e9)} {p}\n" for t, p in listing))
    with pytest.raises(DatasetError, match="images.txt: frames a median of 1e\\+09 s apart: the stamps look like nano"):
        Sequence.load(folder)


def test_a_frame_range_outside_the_folder_is_named(tmp_path):
    """'PATH:a-b' past the last frame (or with a > b) is an error naming the folder's frames, not an IndexError
    (eval, train; make-bag before it writes anything)."""
    from nmnet_ros.tools.make_bag import make_bag

    with pytest.raises(DatasetError, match="frames 157-999 are not all in the folder; it has frames 0-159"):
        make_bag(data_dir("kitti-07"), tmp_path / "b", "mcap", frames=range(157, 1000))
    assert not (tmp_path / "b").exists()
    seq = Sequence.load(data_dir("kitti-07"))
    with pytest.raises(DatasetError, match="frames 157-999 are not all in the folder; it has frames 0-159"):
        seq.pairs((1,), range(157, 1000))
    with pytest.raises(DatasetError, match="frames 5-3 are none"):
        seq.pairs((1,), range(5, 4))
    assert seq.pairs((1,), range(157, 160)) == [(157, 158), (158, 159)]


def test_a_frame_range_not_of_the_form_a_b_says_the_form(tmp_path):
    """'PATH:5' or 'PATH:-5-10' is an error saying the form, not Python's "not enough values to unpack" or "invalid
    literal for int()"; a folder whose own name ends in ':digits' is a folder."""
    from nmnet_ros.io.pairs import parse_seq_spec

    assert parse_seq_spec("d/kitti-07:0-119") == ("d/kitti-07", range(0, 120))
    assert parse_seq_spec("d/kitti-07") == ("d/kitti-07", None)
    for bad in ("5", "-5-10", "1-2-3"):
        with pytest.raises(ValueError, match=f"d/kitti-07:{bad}: a frame range is PATH:a-b, frames a to b"):
            parse_seq_spec(f"d/kitti-07:{bad}")
    odd = tmp_path / "run:7"
    odd.mkdir()
    assert parse_seq_spec(str(odd)) == (str(odd), None)
    for bad in ("10..20", "a-b", "10:20"):  # after a folder: a range mistyped (it was "not a directory")
        with pytest.raises(ValueError, match=f"{odd}:{bad}: a frame range is PATH:a-b"):
            parse_seq_spec(f"{odd}:{bad}")
    assert parse_seq_spec(f"{tmp_path}/no-such:x") == (f"{tmp_path}/no-such:x", None)  # left to the folder's check


def test_a_folder_given_with_a_trailing_slash_is_named_by_its_own_name():
    """'kitti-07/:120-159' (a shell's completion adds the slash) was named ':120-159' in eval's tables."""
    from nmnet_ros.io.pairs import spec_label

    assert spec_label("d/kitti-07/:120-159") == spec_label("d/kitti-07:120-159") == "kitti-07:120-159"
    assert spec_label("d/kitti-07/") == spec_label("d/kitti-07") == "kitti-07"


def test_pairs_txt_is_honoured(tmp_path):
    src = data_dir("strecha-entry-p10")
    dst = tmp_path / "entry"
    shutil.copytree(src, dst)
    (dst / "pairs.txt").write_text("# i j\n0 3\n2 5\n")
    seq = Sequence.load(dst)
    assert seq.pairs((1,)) == [(0, 3), (2, 5)]
    assert seq.pairs((1,), range(0, 4)) == [(0, 3)]  # 'PATH:0-3' keeps pairs.txt's pairs within those frames
    (dst / "pairs.txt").write_text("0 99\n")
    with pytest.raises(DatasetError, match="pairs.txt.*out of range"):
        Sequence.load(dst)


def test_image_paths_with_spaces_are_read_whole(tmp_path):
    """images.txt is 'timestamp path': a path with a space (a folder named 'cam 0', a camera's file names) was cut at
    the space and read as a missing image."""
    src = data_dir("strecha-entry-p10")
    for name in ("camera.yaml", "groundtruth.txt"):
        shutil.copy(src / name, tmp_path / name)
    shutil.copytree(src / "images", tmp_path / "cam 0")
    lines = [line.split() for line in (src / "images.txt").read_text().splitlines() if line and line[0] != "#"]
    (tmp_path / "images.txt").write_text("".join(f"{t}  cam 0/{Path(p).name} \n" for t, p in lines))
    seq = Sequence.load(tmp_path)
    assert [p.name for p in seq.paths] == [Path(p).name for _, p in lines]
    assert seq.paths[0].parent.name == "cam 0" and seq.image(0).shape == Sequence.load(src).image(0).shape


def test_ground_truth_with_other_stamps_than_the_images_gives_each_image_its_nearest_pose(tmp_path):
    """groundtruth.txt need not have a row per image (a faster tracker, extra poses): each image takes the pose
    nearest in time, whatever the rows' order."""
    src = data_dir("strecha-entry-p10")
    dst = tmp_path / "entry"
    shutil.copytree(src, dst)
    rows = [ln for ln in (src / "groundtruth.txt").read_text().splitlines() if not ln.startswith("#")]
    far = "100.0 " + " ".join(rows[0].split()[1:])
    (dst / "groundtruth.txt").write_text("\n".join([far, *reversed(rows)]) + "\n")
    np.testing.assert_array_equal(Sequence.load(dst).poses, Sequence.load(src).poses)


def test_frames_left_out_of_ground_truth_at_the_frames_stamps_have_no_pose_however_the_rest_are_spaced(tmp_path):
    """Ground truth at the images' own stamps (nmnet label's: a pose per registered keyframe) that leaves frames out:
    they have no pose. Keyframes chosen by image motion are spaced unevenly, and a frame left out between two close
    ones got a pose interpolated between them (as ground truth at its own rate is), which the reconstruction never
    gave it."""
    src = data_dir("kitti-07")
    dst = tmp_path / "labelled"
    dst.mkdir()
    shutil.copy(src / "camera.yaml", dst)
    images = [r.split() for r in (src / "images.txt").read_text().splitlines() if not r.startswith("#")][:31]
    (dst / "images.txt").write_text("".join(f"{stamp} {src / name}\n" for stamp, name in images))
    rows = [r for r in (src / "groundtruth.txt").read_text().splitlines() if not r.startswith("#")]
    posed = [0, 1, 2, 3, 5, 10, 15, 20, 25, 30]  # spaced 1 to 5 frames apart: frame 4 between two 1 apart
    (dst / "groundtruth.txt").write_text("".join(rows[i] + "\n" for i in posed))
    seq, kitti = Sequence.load(dst), Sequence.load(src)
    assert [i for i in range(31) if seq.has_pose(i)] == posed
    assert np.array_equal(seq.poses[posed], kitti.poses[posed])
    assert "21 of 31 frames have no pose (no line at their stamps; frames 4, 6, 7, 8, 9, ...)" in seq.uncovered_note()


def test_frames_read_one_at_a_time_get_the_poses_a_folder_gives_them():
    """A replay looks ground truth up frame by frame as it reads them (:class:`FrameTruth`): a pose per frame with
    frames left out gives those frames none, as a folder's do (it interpolated between unevenly spaced neighbours);
    ground truth at its own rate is interpolated as before. Poses outside the frames' span (a replay of part of a
    bag) do not count; a frame before any pose has been passed is looked up as :meth:`Trajectory.poses_at` does."""
    from nmnet_ros.io.trajectory import FrameTruth, Trajectory

    frames = np.round(np.arange(31) * 0.1 + 100.0, 6)
    T = np.tile(np.eye(4), (31, 1, 1))
    T[:, 0, 3] = np.arange(31)
    posed = [0, 1, 2, 3, 5, 10, 15, 20, 25, 30]
    per_frame = Trajectory(frames[posed], T[posed])
    assert not np.isnan(per_frame.poses_at(frames)).any()  # every frame interpolated: what a replay scored against
    for truth, window, expect in [(per_frame, slice(None), posed),
                                  (per_frame, slice(5, None), [5, 10, 15, 20, 25, 30]),  # poses before it: not frames'
                                  (Trajectory(frames[posed] + 0.013, T[posed]), slice(None), list(range(31)))]:
        stamps = frames[window]
        poses, is_per_frame = truth.at_frames(stamps)
        look = FrameTruth(truth)
        one_at_a_time = [look.at(t) for t in stamps]
        got = [n for n, p in zip(range(31)[window], one_at_a_time, strict=True) if p is not None]
        assert got == expect and is_per_frame == (truth is per_frame) == look.per_frame
        assert [n for n, p in zip(range(31)[window], poses, strict=True) if not np.isnan(p).any()] == expect
        for p, q in zip(poses, one_at_a_time, strict=True):
            assert q is None or np.array_equal(p, q)
    assert np.allclose(Trajectory(frames[posed] + 0.013, T[posed]).at_frames(frames[4:5])[0][0, 0, 3], 3.87)
    none, is_per_frame = per_frame.at_frames(np.zeros(0))  # no frames: no poses (not an IndexError)
    assert none.shape == (0, 4, 4) and not is_per_frame


def test_ground_truth_at_its_own_rate_is_interpolated_to_the_frames_stamps():
    """A 100 Hz motion-capture stream turning at 30 deg/s, frames 4.2 ms after its poses: each frame's pose is the
    true one (the nearest pose would be 0.126 deg off, four times the front end's median error on KITTI). A pose at
    the stamp itself is taken as is; in a gap of the stream only stamps within half a spacing of its ends have one,
    as before the first pose and after the last."""
    from nmnet_ros.core.geometry import rotation_error_deg
    from nmnet_ros.io.trajectory import Trajectory, between

    def true_pose(t: float) -> np.ndarray:
        a = np.radians(30.0) * t
        T = np.eye(4)
        T[:3, :3] = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        T[:3, 3] = [2.0 * t, np.sin(t), 0.1 * t * t]
        return T

    stamps = np.round(np.arange(0, 1.001, 0.01), 6)
    stamps = stamps[(stamps <= 0.41) | (stamps >= 0.6)]  # the tracker lost the body for 0.19 s
    gt = Trajectory(stamps, np.array([true_pose(t) for t in stamps]))
    frames = np.round(np.arange(0.0042, 1.0, 0.1), 6)
    poses = gt.poses_at(frames)
    for t, T in zip(frames, poses, strict=True):
        if 0.415 < t < 0.595:  # inside the gap, more than half a spacing from its ends
            assert np.isnan(T).all(), t
            continue
        assert rotation_error_deg(T[:3, :3], true_pose(t)[:3, :3]) < 1e-6 and np.abs(T[:3, 3] - true_pose(t)[:3, 3]).max() < 1e-4, t
        nearest = gt.poses[gt.nearest(t)[0]]
        assert rotation_error_deg(nearest[:3, :3], true_pose(t)[:3, :3]) == pytest.approx(0.126, abs=1e-3)
    assert np.isnan(poses[5]).all()  # 0.5042: in the gap
    assert np.array_equal(gt.at(0.3), gt.poses[30])  # a pose at the stamp: as is
    assert np.array_equal(gt.at(1.004), gt.poses[-1]) and gt.at(1.006) is None  # after the last: within half a spacing
    assert np.array_equal(gt.at(0.413), gt.poses[41]) and gt.at(0.416) is None  # at the gap's start: likewise
    half = between(gt.poses[10], gt.poses[11], 0.5)
    assert np.allclose(half, gt.at(0.105)) and np.allclose(between(gt.poses[10], gt.poses[11], 0.0), gt.poses[10])


def test_frames_the_ground_truth_does_not_cover_are_left_out_not_given_another_frames_pose(tmp_path, capsys, cache):
    """A groundtruth.txt without a pose at some image's stamp (a tracker that lost the camera): that frame has no
    pose, its pairs are not selected for eval/train, a bag made from the folder has no ground truth for it, and a
    file whose stamps match no image is refused, naming it."""
    from nmnet_ros.io.bags import BagReader
    from nmnet_ros.io.pairs import load_pairs
    from nmnet_ros.tools.make_bag import TOPICS, make_bag

    src = data_dir("strecha-entry-p10")
    dst = tmp_path / "entry"
    shutil.copytree(src, dst)
    rows = [ln for ln in (src / "groundtruth.txt").read_text().splitlines() if not ln.startswith("#")]
    (dst / "groundtruth.txt").write_text("\n".join(rows[:4] + rows[5:]) + "\n")  # frame 4's pose lost
    seq, full = Sequence.load(dst), Sequence.load(src)
    assert [seq.has_pose(i) for i in range(len(seq))] == [i != 4 for i in range(10)]
    assert "1 of 10 frames have no pose" in seq.uncovered_note() and full.uncovered_note() is None
    assert select_pairs(seq, (1, 2)) == [p for p in select_pairs(full, (1, 2)) if 4 not in p]
    assert len(select_pairs(seq, (1, 2))) < len(select_pairs(full, (1, 2)))
    with pytest.raises(DatasetError, match="no pose for frame 4"):
        seq.relative_pose(3, 4)
    assert make_bag(dst, tmp_path / "bag", "mcap", frames=range(3, 6)) == 3
    assert len(list(BagReader(tmp_path / "bag").messages({TOPICS["gt"]}))) == 2  # frames 3 and 5
    assert "1 of 10 frames have no pose" in (err := capsys.readouterr().err) and "written without a ground-truth" in err
    pairs = load_pairs([f"{dst}:3-5"], (1, 2), cache)  # nmnet eval says so, and evaluates (3, 5) only
    assert [(p.i, p.j) for p in pairs] == [(3, 5)] and "1 of 10 frames have no pose" in capsys.readouterr().err
    logs: list[str] = []  # nmnet train likewise, through its log
    pairs = load_pairs([f"{dst}:3-5"], (1, 2), cache, min_inliers=5, skip_empty=True, log=logs.append)
    assert [(p.i, p.j) for p in pairs] == [(3, 5)] and "1 of 10 frames have no pose" in logs[0], logs

    (dst / "groundtruth.txt").write_text("\n".join(f"{1000 + float(r.split()[0])} {r.split(maxsplit=1)[1]}" for r in rows))
    with pytest.raises(DatasetError, match="groundtruth.txt: no pose at any image's stamp.*must be those of images.txt"):
        Sequence.load(dst)


def test_empty_folder_names_missing_camera_yaml(tmp_path):
    with pytest.raises(DatasetError, match="camera.yaml: missing; a sequence folder needs camera.yaml"):
        Sequence.load(tmp_path)


def test_a_calibration_file_that_is_not_there_is_named_as_such(tmp_path):
    """``--camera`` (replay, label) naming no file said "missing; a sequence folder needs camera.yaml"."""
    from nmnet_ros.io.datasets import read_camera_yaml

    with pytest.raises(DatasetError, match=r"nope.yaml: no such file$"):
        read_camera_yaml(tmp_path / "nope.yaml")
    with pytest.raises(DatasetError, match=rf"{tmp_path}: not a file$"):
        read_camera_yaml(tmp_path)


def test_a_bag_given_to_eval_names_replay(tmp_path):
    """A bag (its file or its folder) given to eval or train said "not a directory" or "camera.yaml: missing"; it
    says it is a recording and names the tool that scores one."""
    from nmnet_ros.tools.options import SAMPLE_BAG

    said = r"this is a recording \(a bag\), which nmnet replay scores against its ground truth \(`nmnet replay BAG"
    bag = next(SAMPLE_BAG.glob("*.mcap"))
    with pytest.raises(DatasetError, match=f"{bag}: not a directory; {said}"):
        Sequence.load(bag)
    with pytest.raises(DatasetError, match=f"{SAMPLE_BAG / 'camera.yaml'}: missing; {said}"):
        Sequence.load(SAMPLE_BAG)
    with pytest.raises(DatasetError, match=r"x.txt: not a directory$"):
        Sequence.load(tmp_path / "x.txt")


def test_a_tum_rgbd_folder_reads_as_it_is_and_other_benchmarks_are_named(tmp_path):
    """TUM RGB-D's layout (rgb.txt, rgb/<stamp>.png, groundtruth.txt at its own rate, '#' headers) is the sequence
    format with rgb.txt for images.txt: it was refused for a missing images.txt. A homography benchmark's folder is
    named as such rather than as a sequence folder missing camera.yaml."""
    src = data_dir("kitti-07")
    rows = [r for r in (src / "images.txt").read_text().splitlines() if not r.startswith("#")][:6]
    (tmp_path / "rgb").mkdir()
    listing = ["# color images", "# file: 'rgbd_dataset_freiburg1_xyz.bag'", "# timestamp filename"]
    for row in rows:
        stamp, name = row.split()
        shutil.copy(src / name, tmp_path / "rgb" / f"{1305031102 + float(stamp):.6f}.png")
        listing.append(f"{1305031102 + float(stamp):.6f} rgb/{1305031102 + float(stamp):.6f}.png")
    (tmp_path / "rgb.txt").write_text("\n".join(listing) + "\n")
    gt = [r.split() for r in (src / "groundtruth.txt").read_text().splitlines() if not r.startswith("#")][:6]
    (tmp_path / "groundtruth.txt").write_text("# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n" + "".join(
        f"{1305031102 + float(r[0]):.4f} {' '.join(r[1:])}\n" for r in gt))
    with pytest.raises(DatasetError, match=r"camera.yaml: missing; rgb.txt: a TUM RGB-D sequence, read as it is"):
        Sequence.load(tmp_path)
    shutil.copy(src / "camera.yaml", tmp_path / "camera.yaml")
    seq, kitti = Sequence.load(tmp_path), Sequence.load(f"{src}")
    assert len(seq) == 6 and seq.paths[2].parent.name == "rgb" and np.array_equal(seq.image(2), kitti.image(2))
    assert np.allclose(seq.relative_pose(1, 4)[1], kitti.relative_pose(1, 4)[1], atol=1e-3)  # stamps of its own, interpolated

    (tmp_path / "images.txt").write_text("\n".join(listing[3:6]).replace("rgb/", "rgb/x"))  # images.txt comes first
    with pytest.raises(DatasetError, match=r"x1305031102.000000.png: cannot read image"):
        Sequence.load(tmp_path).image(0)
    boat = tmp_path / "boat"
    boat.mkdir()
    (boat / "H_1_to_2p").write_text("1 0 0\n0 1 0\n0 0 1\n")
    with pytest.raises(DatasetError, match="H_1_to_N files: a homography benchmark .* no camera poses"):
        Sequence.load(boat)
    parent = tmp_path / "runs"  # the folder of the sequences, given for them
    for name in ("b", "a"):
        (parent / name).mkdir(parents=True)
        shutil.copy(src / "camera.yaml", parent / name / "camera.yaml")
    with pytest.raises(DatasetError, match=f"missing; it holds sequence folders \\(a, b\\): give those, e.g. {parent}/a {parent}/b$"):
        Sequence.load(parent)


def test_a_tum_rgbd_folder_named_as_tum_names_it_takes_tums_published_calibration(tmp_path, capsys):
    """A TUM RGB-D download has no calibration file: its folder's name (rgbd_dataset_freiburgN_...) says which
    camera, whose calibration TUM publishes; it is used, with a note, and a camera.yaml in the folder replaces it."""
    src = Sequence.load(data_dir("kitti-07"))
    for n, fx in ((1, 517.3), (3, 535.4)):
        root = tmp_path / f"rgbd_dataset_freiburg{n}_xyz"
        (root / "rgb").mkdir(parents=True)
        for i in range(3):
            cv2.imwrite(str(root / "rgb" / f"{i}.png"), src.image(i)[:, 293:933][:480].repeat(2, axis=0)[:480])
        (root / "rgb.txt").write_text("# color images\n" + "".join(f"{1305031102 + i / 30:.6f} rgb/{i}.png\n" for i in range(3)))
        seq = Sequence.load(root)
        assert seq.camera.K[0, 0] == fx and (seq.camera.width, seq.camera.height) == (640, 480)
        assert seq.camera.dist.any() == (n == 1) and seq.image(2).shape == (480, 640)
        assert seq.notes() == [f"{root / 'camera.yaml'}: missing; TUM's published calibration of the freiburg{n} RGB "
                               f"camera is used (fx {fx}, fy {seq.camera.K[1, 1]}, cx {seq.camera.K[0, 2]}, cy "
                               f"{seq.camera.K[1, 2]}); a camera.yaml in the folder replaces it"]
    shutil.copy(data_dir("euroc-v101-cam0") / "camera.yaml", root / "camera.yaml")  # 752x480: the file is read
    with pytest.raises(DatasetError, match="camera.yaml describes 752x480 frames but 0.png is 640x480"):
        Sequence.load(root)
    from nmnet_ros.tools.cli import main

    (root / "camera.yaml").unlink()
    assert main(["eval", str(root), "--gaps", "1", "--methods", "ratio"]) == 2  # no groundtruth.txt: said after the note
    said = capsys.readouterr().err
    assert said.index("TUM's published calibration of the freiburg3 RGB camera is used") < said.index("groundtruth.txt: missing")


def test_a_euroc_asl_download_reads_as_it_is(tmp_path):
    """EuRoC's ASL layout (mav0/cam0/data.csv stamped in ns, sensor.yaml, the body's ground truth with qw first) reads
    as it is, the camera's poses those of the body composed with the camera's T_BS: it was only named, with its bag's
    replay. Built here from the shipped EuRoC excerpt, whose camera poses are the body's composed with T_BS."""
    from nmnet_ros.interface.posemsg import rot_to_quat

    src = Sequence.load(data_dir("euroc-v101-cam0"))
    mav = tmp_path / "V1_01_easy" / "mav0"
    cam0 = mav / "cam0"
    (cam0 / "data").mkdir(parents=True)
    (cam0 / "sensor.yaml").write_text(EUROC_SENSOR_YAML)
    T_BS = np.array(yaml.safe_load(EUROC_SENSOR_YAML)["T_BS"]["data"]).reshape(4, 4)
    listing, truth = ["#timestamp [ns],filename"], ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [],"
                                                    " q_RS_x [], q_RS_y [], q_RS_z [], v_RS_R_x [m s^-1]"]
    for i in range(0, 40, 2):  # every other frame: the ground truth (every frame) is sampled between the images
        shutil.copy(src.paths[i], cam0 / "data" / src.paths[i].name)
        listing.append(f"{src.paths[i].stem},{src.paths[i].name}")
    for i in range(40):
        T_WB = src.poses[i] @ np.linalg.inv(T_BS)
        x, y, z, w = rot_to_quat(T_WB[:3, :3])
        truth.append(f"{src.paths[i].stem},{','.join(f'{v:.9f}' for v in (*T_WB[:3, 3], w, x, y, z))},0.1")
    (cam0 / "data.csv").write_text("\r\n".join(listing) + "\r\n")
    (mav / "state_groundtruth_estimate0").mkdir()
    (mav / "state_groundtruth_estimate0" / "data.csv").write_text("\n".join(truth) + "\n")
    for folder in (mav.parent, mav, cam0):
        seq = Sequence.load(folder)
        assert len(seq) == 20 and np.allclose(seq.stamps, src.stamps[:40:2], atol=1e-6)
        assert np.array_equal(seq.camera.K, src.camera.K) and np.allclose(seq.camera.dist, src.camera.dist[:4])
        assert np.array_equal(seq.image(3), src.image(6))
        assert np.allclose(seq.poses, src.poses[:40:2], atol=1e-6)
    assert seq.calibration == cam0 / "sensor.yaml" and seq.truth_file == mav / "state_groundtruth_estimate0" / "data.csv"

    (cam0 / "sensor.yaml").write_text(EUROC_SENSOR_YAML.replace("0.0, 0.0, 0.0, 1.0]", "0.0, 0.0, 0.0]"))
    with pytest.raises(DatasetError, match=f"{cam0 / 'sensor.yaml'}: no T_BS .* 16 numbers"):
        Sequence.load(mav.parent)
    (cam0 / "sensor.yaml").write_text(EUROC_SENSOR_YAML.replace("[0.0148655429818,", "[0.5,"))
    with pytest.raises(DatasetError, match=f"{cam0 / 'sensor.yaml'}: T_BS is not a rigid transform"):
        Sequence.load(mav.parent)
    (cam0 / "sensor.yaml").write_text(EUROC_SENSOR_YAML)
    (mav / "state_groundtruth_estimate0" / "data.csv").write_text(truth[0] + "\n")
    with pytest.raises(DatasetError, match="state_groundtruth_estimate0/data.csv: no poses"):
        Sequence.load(mav.parent)
    (cam0 / "data.csv").write_text(listing[0] + "\n")
    with pytest.raises(DatasetError, match=f"{cam0 / 'data.csv'}: no frames listed"):
        Sequence.load(mav.parent)
    (cam0 / "data.csv").write_text("\n".join(listing) + "\n")
    (cam0 / "sensor.yaml").write_text(EUROC_SENSOR_YAML)
    (mav / "state_groundtruth_estimate0" / "data.csv").write_text(truth[0] + "\n" + truth[1].replace(",", ";") + "\n")
    with pytest.raises(DatasetError, match=r"state_groundtruth_estimate0/data.csv:2: expected 'timestamp \[ns\], p_RS_R"):
        Sequence.load(mav.parent)
    (mav / "state_groundtruth_estimate0" / "data.csv").unlink()  # no ground truth: frames without poses
    assert Sequence.load(mav.parent).poses is None
    with pytest.raises(DatasetError, match=f"{mav / 'state_groundtruth_estimate0' / 'data.csv'}: missing, so no"):
        Sequence.load(mav.parent).relative_pose(0, 1)
    (cam0 / "sensor.yaml").unlink()
    with pytest.raises(DatasetError, match="sensor.yaml"):
        Sequence.load(mav.parent)


def test_a_kitti_odometry_download_reads_as_it_is(tmp_path):
    """KITTI odometry's layout (sequences/NN: image_0/ or image_2/, calib.txt's projections, times.txt; poses/NN.txt
    beside sequences/, cam0's 3x4 poses) reads as it is; the colour camera's poses are cam0's moved by its baseline.
    It was refused for a missing camera.yaml. Built here from the shipped KITTI-07 excerpt."""
    src = Sequence.load(data_dir("kitti-07"))
    root = tmp_path / "dataset" / "sequences" / "07"
    (root / "image_0").mkdir(parents=True)
    for i in range(12):
        shutil.copy(src.paths[i], root / "image_0" / f"{i:06d}.png")
    P0 = np.hstack([src.camera.K, np.zeros((3, 1))])
    b = np.array([0.06, -0.001, 0.002])  # the colour camera's cam0 origin, in its coordinates (P2 = K [I | b])
    P2 = np.hstack([src.camera.K, (src.camera.K @ b)[:, None]])
    line = " ".join
    (root / "calib.txt").write_text("".join(f"{n}: {line(f'{v:.12e}' for v in P.ravel())}\n"
                                            for n, P in (("P0", P0), ("P1", P0), ("P2", P2), ("P3", P2), ("Tr", P0))))
    (root / "times.txt").write_text("".join(f"{t:.6e}\n" for t in src.stamps[:12]))
    seq = Sequence.load(root)
    assert len(seq) == 12 and seq.poses is None and np.allclose(seq.stamps, src.stamps[:12], atol=1e-6)
    assert np.allclose(seq.camera.K, src.camera.K) and not seq.camera.dist.any()
    assert np.array_equal(seq.image(5), src.image(5)) and seq.calibration == root / "calib.txt"
    assert (seq.camera.width, seq.camera.height) == (1226, 370)  # the first image's: every frame is checked against it
    cv2.imwrite(str(root / "image_0" / "000011.png"), src.image(11)[:, :1000])
    with pytest.raises(DatasetError, match="000011.png: 1000x370, but the folder's frames are 1226x370"):
        Sequence.load(root).image(11)
    shutil.copy(src.paths[11], root / "image_0" / "000011.png")
    (tmp_path / "dataset" / "poses").mkdir()
    poses = tmp_path / "dataset" / "poses" / "07.txt"
    poses.write_text("".join(line(f"{v:.12e}" for v in T[:3].ravel()) + "\n" for T in src.poses[:12]))
    seq = Sequence.load(root)
    assert np.allclose(seq.poses, src.poses[:12], atol=1e-9) and seq.truth_file == poses
    assert np.allclose(seq.relative_pose(2, 7)[0], src.relative_pose(2, 7)[0])

    (root / "image_0").rename(root / "image_2")  # the colour download: P2, poses moved by its baseline
    colour = Sequence.load(root)
    assert colour.paths[0].parent.name == "image_2" and np.allclose(colour.camera.K, src.camera.K)
    assert np.allclose(colour.poses[:, :3, 3], src.poses[:12, :3, 3] - src.poses[:12, :3, :3] @ b, atol=1e-9)

    poses.write_text(poses.read_text().split("\n", 1)[1])  # a line short: another sequence's file?
    with pytest.raises(DatasetError, match=f"{poses}: 11 poses for 12 frames of times.txt"):
        Sequence.load(root)
    (root / "times.txt").write_text("")
    with pytest.raises(DatasetError, match=f"{root / 'times.txt'}: no frames listed"):
        Sequence.load(root)
    (root / "calib.txt").write_text("P0: 1 0 0\n")
    with pytest.raises(DatasetError, match=f"{root / 'calib.txt'}: no 'P2:' line, the projection of image_2's camera"):
        Sequence.load(root)
    (root / "calib.txt").write_text("P2: 1 0 0\n")
    with pytest.raises(DatasetError, match="'P2:' must be 12 numbers"):
        Sequence.load(root)


def test_images_resized_from_the_calibration_get_k_scaled_and_another_size_is_refused(tmp_path, capsys):
    """A downscaled copy of a dataset (images half camera.yaml's size) was evaluated with the full-size K: poses
    and labels silently wrong (ratio+magsac AUC@5 0.0 on Strecha fountain). K is fitted to the images, with a
    note; a crop or a folder of mixed sizes is named."""
    from nmnet_ros.core.detectors import make_detector
    from nmnet_ros.io.cache import FeatureCache
    from nmnet_ros.io.pairs import make_pair

    src = data_dir("strecha-fountain-p11")
    for name in ("camera.yaml", "images.txt", "groundtruth.txt"):
        shutil.copy(src / name, tmp_path / name)
    full = Sequence.load(src)
    (tmp_path / "images").mkdir()
    for i in range(3):
        cv2.imwrite(str(tmp_path / "images" / full.paths[i].name), cv2.resize(full.image(i), (384, 256)))
    half = Sequence.load(tmp_path)
    assert half.size_note == (f"{tmp_path / 'camera.yaml'} describes 768x512 frames but 0000.jpg is 384x256: K scaled "
                              "by 0.5 to fit (a camera.yaml of these images silences this)")
    assert half.notes()[0] == half.size_note and (half.camera.width, half.camera.height) == (384, 256)
    assert np.isclose(half.camera.K[0, 0], full.camera.K[0, 0] / 2) and full.notes() == [] and full.size_note is None
    cache = FeatureCache(make_detector("sift"), tmp_path / "cache")
    inliers = [make_pair(seq, 0, 1, cache).labels.mean() for seq in (full, half)]
    assert inliers[1] > 0.7 * inliers[0] > 0.1, inliers  # with the full-size K: 0.03 of the half-size matches
    from nmnet_ros.tools.cli import main  # the tools say it: eval and train (their tests), neighbors here

    assert main(["neighbors", f"{tmp_path}:0-2", "--gaps", "1", "--stride", "1", "--detector", "sift", "--cache",
                 str(tmp_path / "cache")]) == 0
    assert f"warning: {half.size_note}" in capsys.readouterr().err
    out = tmp_path.with_name(tmp_path.name + "_out")  # beside the sequence folder: no tool writes into its input
    assert main(["make-bag", f"{tmp_path}:0-1", "--out", str(out / "bag")]) == 0  # make-bag too: it writes the fitted K
    assert f"warning: {half.size_note}" in capsys.readouterr().err

    cv2.imwrite(str(tmp_path / "images" / full.paths[2].name), full.image(2))  # one frame of another size
    with pytest.raises(DatasetError, match=r"0002.jpg: 768x512, but the folder's frames are 384x256 \(as its first "
                                           r"image\): every frame of a sequence folder must be one size"):
        Sequence.load(tmp_path).image(2)
    cv2.imwrite(str(tmp_path / "images" / full.paths[0].name), full.image(0)[:, :700])  # a crop: no K fits
    with pytest.raises(DatasetError, match=r"describes 768x512 frames but 0000.jpg is 700x512, which is not the "
                                           r"same image scaled"):
        Sequence.load(tmp_path)


def test_a_missing_truncated_or_empty_image_is_named_not_read_in_part(tmp_path, capsys):
    src = data_dir("strecha-fountain-p11")
    for name in ("camera.yaml", "images.txt", "groundtruth.txt"):
        shutil.copy(src / name, tmp_path / name)
    shutil.copytree(src / "images", tmp_path / "images")
    seq = Sequence.load(tmp_path)
    whole = seq.image(1)
    seq.paths[1].write_bytes(seq.paths[1].read_bytes()[:-2000])  # a copy cut short: cv2.imread gave its top part
    seq.paths[2].write_bytes(b"")
    seq.paths[3].unlink()
    assert whole.shape == (512, 768, 3) and seq.image(0).shape == whole.shape
    for i, said in ((1, "cannot decode image"), (2, r"cannot decode image \(0 bytes\)"), (3, "cannot read image: No such file")):
        with pytest.raises(DatasetError, match=f"{seq.paths[i].name}: {said}"):
            seq.image(i)
    # make-bag stopped at frame 1 and left a ROS 2 bag without metadata.yaml (unreadable, and in a rerun's way):
    # the frames it cannot read are skipped, named; with none readable, nothing is left behind
    from nmnet_ros.io.bags import BagError, BagReader
    from nmnet_ros.tools.make_bag import TOPICS, make_bag

    outs = tmp_path.with_name(tmp_path.name + "_out")  # beside the sequence folder: no tool writes into its input
    assert make_bag(tmp_path, outs / "bag", "mcap", frames=range(0, 5)) == 2  # frames 0 and 4
    said = capsys.readouterr().err
    assert [f"warning: frame {i}: skipped, {seq.paths[i]}: cannot" in said for i in range(5)] == [False, True, True, True, False]
    assert len(list(BagReader(outs / "bag").messages({TOPICS["image"]}))) == 2
    for fmt, out in (("mcap", outs / "none"), ("ros1", outs / "none.bag"), ("mcap", outs / "none.mcap")):
        with pytest.raises(BagError, match=f"{tmp_path}: none of the 3 frames could be read; no bag written"):
            make_bag(tmp_path, out, fmt, frames=range(1, 4))
        assert not out.exists()
    assert sorted(p.name for p in outs.iterdir()) == ["bag"]  # a single file's hidden writing folder went with it


def test_missing_images_txt_and_bad_yaml(tmp_path):
    shutil.copy(data_dir("kitti-07") / "camera.yaml", tmp_path / "camera.yaml")
    with pytest.raises(DatasetError, match="images.txt"):
        Sequence.load(tmp_path)
    (tmp_path / "camera.yaml").write_text("image_width: 10\ncamera_matrix: {data: [0,0,0,0,0,0,0,0,1]}\n")
    with pytest.raises(DatasetError, match="camera.yaml.*focal"):
        Sequence.load(tmp_path)
    (tmp_path / "camera.yaml").write_text("camera_matrix: {data: [500, 0, 320, 0, 500, 240, 0, 0, 1]}\n"
                                          "distortion_model: fov\ndistortion_coefficients: {data: [0.9]}\n")
    with pytest.raises(DatasetError, match="camera.yaml: distortion model 'fov' is not supported"):
        Sequence.load(tmp_path)
    with pytest.raises(DatasetError, match="not a directory"):
        Sequence.load(tmp_path / "nope")


EUROC_SENSOR_YAML = """\
# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""

CAMCHAIN = """\
cam0:
  camera_model: pinhole
  distortion_coeffs: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
  distortion_model: radtan
  intrinsics: [458.654, 457.296, 367.215, 248.375]
  resolution: [752, 480]
  rostopic: /cam0/image_raw
cam1:
  T_cn_cnm1: [[1, 0, 0, -0.11], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
  camera_model: pinhole
  distortion_coeffs: [0.01, -0.002, 0.0003, -0.0001]
  distortion_model: equidistant
  intrinsics: [380.8, 380.5, 510.2, 390.1]
  resolution: [1024, 768]
  rostopic: /cam1/image_raw
"""


def test_kalibr_camchain_and_euroc_sensor_yaml_read_as_the_camera_info_yaml(tmp_path):
    """EuRoC's sensor.yaml and a Kalibr camchain give the camera the ROS camera_info YAML of the same calibration
    gives (the shipped EuRoC folder's camera.yaml); of a camchain's cameras, the one on the image topic. Other camera
    models, distortions and malformed entries are named. Before, each was "malformed camera YAML ('camera_matrix')"."""
    from nmnet_ros.io.datasets import read_camera_yaml

    ros = read_camera_yaml(data_dir("euroc-v101-cam0") / "camera.yaml")
    (tmp_path / "sensor.yaml").write_text(EUROC_SENSOR_YAML)
    (tmp_path / "camchain.yaml").write_text(CAMCHAIN)
    pts = np.random.default_rng(0).uniform([0, 0], [752, 480], (50, 2))
    for cam in (read_camera_yaml(tmp_path / "sensor.yaml"), read_camera_yaml(tmp_path / "camchain.yaml", "/cam0/image_raw")):
        assert (cam.width, cam.height, cam.model) == (752, 480, "plumb_bob") and np.allclose(cam.K, ros.K)
        assert np.allclose(cam.normalize(pts), ros.normalize(pts), atol=1e-12)
    fisheye = read_camera_yaml(tmp_path / "camchain.yaml", "/cam1/image_raw")
    assert fisheye.model == "equidistant" and fisheye.width == 1024 and fisheye.K[0, 2] == 510.2
    assert fisheye.dist.tolist() == [0.01, -0.002, 0.0003, -0.0001]
    with pytest.raises(DatasetError, match=r"camchain.yaml: 2 cameras \(cam0 \(/cam0/image_raw\), cam1 \(/cam1/image_raw\)\) "
                                           r"and none's rostopic is the image topic /camera/image_raw"):
        read_camera_yaml(tmp_path / "camchain.yaml", "/camera/image_raw")
    one = tmp_path / "one.yaml"
    one.write_text(CAMCHAIN.split("cam1:")[0])  # a single camera is taken whatever the topic
    assert np.allclose(read_camera_yaml(one, "/camera/image_raw").K, ros.K)
    for edit, says in ((("pinhole", "omni"), "camera_model 'omni' is not supported: only pinhole"),
                       (("radial-tangential", "fov"), "distortion model 'fov' is not supported"),
                       (("367.215, 248.375]", "367.215]"), r"malformed camera YAML \(ValueError"),
                       (("intrinsics:", "intrinsic:"), "not a camera calibration; expected a ROS camera_info YAML")):
        bad = tmp_path / "bad.yaml"
        bad.write_text(EUROC_SENSOR_YAML.replace(*edit))
        with pytest.raises(DatasetError, match=f"bad.yaml: .*{says}"):
            read_camera_yaml(bad)


def test_a_calibration_that_is_not_yaml_is_named_on_one_line_with_where(tmp_path):
    """A camera YAML (or EuRoC sensor.yaml) PyYAML cannot parse printed its four-line message, naming "<unicode
    string>" and a caret; it is one line now, with the file, the line and the column."""
    from nmnet_ros.io.asl import body_to_camera
    from nmnet_ros.io.datasets import read_camera_yaml

    bad = tmp_path / "camera.yaml"
    bad.write_text("image_width: 752\n  image_height: 480\n")
    says = f"{bad}: not valid YAML (line 2, column 15: mapping values are not allowed here)"
    for read in (read_camera_yaml, body_to_camera):
        with pytest.raises(DatasetError) as e:
            read(bad)
        assert str(e.value) == says


ORB_SLAM_SETTINGS = """%YAML:1.0
Camera.type: "PinHole"
Camera.fx: 458.654
Camera.fy: 457.296
Camera.cx: 367.215
Camera.cy: 248.375
Camera.k1: -0.28340811
Camera.k2: 0.07395907
Camera.p1: 0.00019359
Camera.p2: 1.76187114e-05
Camera.width: 752
Camera.height: 480
Camera.fps: 20.0
"""


def test_opencv_yaml_calibrations_read_as_the_camera_info_yaml(tmp_path):
    """OpenCV's own YAML ('%YAML:1.0', which PyYAML cannot parse: "malformed camera YAML (ScannerError ...)") as its
    calibration writes it (cv2.FileStorage, camera_matrix / distortion_coefficients) and as ORB-SLAM2/3's settings
    give the camera the ROS camera_info YAML of the same calibration gives; ORB-SLAM3's fisheye too."""
    import cv2

    from nmnet_ros.io.datasets import read_camera_yaml

    ros = read_camera_yaml(data_dir("euroc-v101-cam0") / "camera.yaml")
    fs = cv2.FileStorage(str(tmp_path / "calib.yaml"), cv2.FILE_STORAGE_WRITE)
    for key, value in (("image_width", 752), ("image_height", 480), ("camera_matrix", ros.K),
                       ("distortion_coefficients", ros.dist.reshape(1, -1))):
        fs.write(key, value)
    fs.release()
    (tmp_path / "orb.yaml").write_text(ORB_SLAM_SETTINGS)
    pts = np.random.default_rng(0).uniform([0, 0], [752, 480], (50, 2))
    for name in ("calib.yaml", "orb.yaml"):
        cam = read_camera_yaml(tmp_path / name)
        assert (cam.width, cam.height, cam.model) == (752, 480, "plumb_bob") and np.allclose(cam.K, ros.K), name
        assert np.allclose(cam.normalize(pts), ros.normalize(pts), atol=1e-12), name
    fisheye = ORB_SLAM_SETTINGS.replace("PinHole", "KannalaBrandt8").replace("Camera.p1", "Camera.k3").replace(
        "Camera.p2", "Camera.k4").replace("Camera.", "Camera1.").replace("Camera1.type", "Camera.type").replace(
        "Camera1.width", "Camera.width").replace("Camera1.height", "Camera.height")  # ORB-SLAM3's names
    (tmp_path / "kb.yaml").write_text(fisheye)
    cam = read_camera_yaml(tmp_path / "kb.yaml")
    assert cam.model == "equidistant" and cam.dist.tolist() == [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
    (tmp_path / "k3.yaml").write_text(ORB_SLAM_SETTINGS + "Camera.k3: 0.001\n")  # ORB-SLAM's optional fifth
    assert read_camera_yaml(tmp_path / "k3.yaml").dist.tolist()[4:] == [0.001]
    for edit, says in ((("PinHole", "Fisheye"), "Camera.type 'Fisheye' is not supported"),
                       (("Camera.fy: 457.296\n", ""), "Camera.fy missing"),
                       (("Camera.", "Cam."), "an OpenCV YAML without a camera"),
                       (("Camera.fps: 20.0", ": ["), "malformed OpenCV YAML")):
        (tmp_path / "bad.yaml").write_text(ORB_SLAM_SETTINGS.replace(*edit))
        with pytest.raises(DatasetError, match=f"bad.yaml: {says}"):
            read_camera_yaml(tmp_path / "bad.yaml")


def test_a_malformed_line_is_named_with_its_file_and_line(tmp_path):
    """images.txt, pairs.txt and groundtruth.txt (also `nmnet replay --gt`) name the file, the line and its columns."""
    from nmnet_ros.io.trajectory import read_tum

    dst = tmp_path / "entry"
    shutil.copytree(data_dir("strecha-entry-p10"), dst)
    (dst / "pairs.txt").write_text("# i j\n0 3\nfoo bar\n")
    with pytest.raises(DatasetError, match=r"pairs.txt:3: expected 'i j', got 'foo bar'"):
        Sequence.load(dst)
    (dst / "pairs.txt").write_text("4\n")
    with pytest.raises(DatasetError, match=r"pairs.txt:1: expected 'i j', got '4'"):
        Sequence.load(dst)
    (dst / "pairs.txt").unlink()
    gt = (dst / "groundtruth.txt").read_text().splitlines()
    (dst / "groundtruth.txt").write_text("\n".join(gt[:2] + [" ".join(gt[2].split()[:7])] + gt[3:]) + "\n")
    with pytest.raises(DatasetError, match=r"groundtruth.txt:3: expected 'timestamp tx ty tz qx qy qz qw'"):
        Sequence.load(dst)
    with pytest.raises(DatasetError, match=r"nope.txt: missing; expected lines 'timestamp tx ty tz"):
        read_tum(tmp_path / "nope.txt")
    (tmp_path / "data.csv").write_text("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w []\n"
                                       "1403715273262142976,0.878612,2.142470,0.947262,0.060514,-0.828459,-0.058956,-0.553641\n")
    with pytest.raises(DatasetError, match=r"data.csv:2: expected 'timestamp tx ty tz qx qy qz qw', got .*separated by "
                                           r"commas.*`evo_traj euroc data.csv --save_as_tum`"):
        read_tum(tmp_path / "data.csv")  # EuRoC's ground truth, given as it comes
    (tmp_path / "07.txt").write_text("1.000000e+00 0.000000e+00 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 "
                                     "0.000000e+00 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00\n")
    with pytest.raises(DatasetError, match=r"07.txt:1: expected .*; 12 numbers: a KITTI poses file .*contrib/"
                                           r"kitti_poses_and_timestamps_to_trajectory.py POSES times.txt OUT .*; or give the KITTI "
                                           r"sequence folder \(sequences/NN\) itself"):
        read_tum(tmp_path / "07.txt")  # KITTI odometry's poses/07.txt, given as it comes
    (tmp_path / "empty.txt").write_text("# timestamp tx ty tz qx qy qz qw\n\n")
    with pytest.raises(DatasetError, match=r"empty.txt: no poses; expected lines 'timestamp tx ty tz"):
        read_tum(tmp_path / "empty.txt")
    # a lost track written as NaN, or as a zero quaternion (a RuntimeWarning, then the frame's pairs silently dropped)
    for n, cut, says in ((1, "nan", "a value that is not a finite number"), (4, "0 0 0 0", r"a zero quaternion \(qx qy qz qw all 0\)"),
                         (0, "inf", "a stamp that is not a finite number")):
        row = gt[2].split()
        row[n:n + len(cut.split())] = cut.split()
        (dst / "groundtruth.txt").write_text("\n".join(gt[:2] + [" ".join(row)] + gt[3:]) + "\n")
        with pytest.raises(DatasetError, match=rf"groundtruth.txt:3: {says} in 'timestamp tx ty tz qx qy qz qw'"):
            Sequence.load(dst)
        with pytest.raises(DatasetError, match=rf"groundtruth.txt:3: {says}"):
            read_tum(dst / "groundtruth.txt")
    (dst / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    rows = (dst / "images.txt").read_text().splitlines()
    (dst / "images.txt").write_text("\n".join(rows[:1] + ["t0 images/0001.jpg"] + rows[2:]) + "\n")
    with pytest.raises(DatasetError, match=r"images.txt:2: expected 'timestamp path', got 't0 images/0001.jpg'"):
        Sequence.load(dst)
    (dst / "images.txt").write_text("\n".join(rows[:1] + ["0.5"] + rows[2:]) + "\n")
    with pytest.raises(DatasetError, match=r"images.txt:2: expected 'timestamp path', got '0.5'"):
        Sequence.load(dst)


def test_a_pose_given_as_text_is_seven_numbers_with_a_rotation():
    """--gt-camera's 'x y z qx qy qz qw' (TUM's order): anything else is refused, saying what is expected."""
    from nmnet_ros.io.trajectory import parse_pose

    T = parse_pose("0.3, 0 0.5 -0.5 0.5 -0.5 0.5")
    np.testing.assert_allclose(T[:3, 3], [0.3, 0, 0.5])
    np.testing.assert_allclose(T[:3, :3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-12)
    for bad in ("0.3 0 0.5", "0 0 0 0 0 0 0", "0 0 0 nan 0 0 1", "a b c d e f g", "1 2 3 4 5 6 7 8"):
        with pytest.raises(ValueError, match="expected 'x y z qx qy qz qw', seven numbers with a non-zero quaternion"):
            parse_pose(bad)

"""Bags: make-bag round trips, replay outputs readable by rosbags and mcap, bad bags and interruptions."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import yaml

from nmnet_ros.io.bag_truth import bag_ground_truth, pick_ground_truth, pose_from_msg, tf_ground_truth
from nmnet_ros.io.bags import BagError, BagReader, choose_topics, image_frame, read_frames, typestore
from nmnet_ros.tools.make_bag import make_bag
from nmnet_ros.tools.options import SAMPLE_BAG

from .conftest import ROOT, data_dir, planar_views

FITTED = ("fitted_pose_sigma_rotation_deg", "fitted_pose_sigma_direction")  # the summary's pose sigmas fitted to its errors


def nmnet(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "nmnet_ros.tools.cli", *args], capture_output=True, text=True, cwd=ROOT, timeout=timeout)


def read_output(path: Path) -> dict[str, int]:
    """Message counts per topic, checked with both rosbags and mcap readers."""
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader

    with open(path, "rb") as fh:
        counts_mcap: dict[str, int] = {}
        for _, channel, _ in make_reader(fh).iter_messages():
            counts_mcap[channel.topic] = counts_mcap.get(channel.topic, 0) + 1
    counts: dict[str, int] = {}
    with AnyReader([path]) as r:
        for c, _, raw in r.messages():
            r.deserialize(raw, c.msgtype)
            counts[c.topic] = counts.get(c.topic, 0) + 1
    assert counts == counts_mcap
    return counts


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("bags")
    seq = data_dir("kitti-07")
    out = {}
    for fmt, name in (("mcap", "b_mcap"), ("sqlite3", "b_db3"), ("ros1", "b.bag")):
        out[fmt] = root / name
        assert make_bag(seq, out[fmt], fmt, compressed=fmt != "sqlite3", frames=range(50, 54)) == 4
    return out


def test_round_trip_all_formats_same_frames_and_results(bags, tmp_path):
    frames = {}
    for fmt, path in bags.items():
        it, chosen = read_frames(BagReader(path))
        frames[fmt] = list(it)
        assert chosen["camera_info"] == "/camera/camera_info" and pick_ground_truth(BagReader(path).topics, None)[0] == (
            "/ground_truth/pose")
    assert [len(v) for v in frames.values()] == [4, 4, 4]
    for a, b, c in zip(*frames.values(), strict=True):
        assert a.stamp == pytest.approx(b.stamp) == pytest.approx(c.stamp)
        np.testing.assert_array_equal(a.image, c.image)  # same JPEG bytes in .mcap and .bag
        assert np.abs(a.image.astype(int) - b.image.astype(int)).mean() < 3  # raw Image vs JPEG
        np.testing.assert_allclose(a.camera.K, b.camera.K)
    truths = [bag_ground_truth(BagReader(path)) for path in bags.values()]
    for truth in truths:
        np.testing.assert_allclose(truth.stamps, [f.stamp for f in frames["mcap"]])
        np.testing.assert_allclose(truth.poses, truths[0].poses)
    seq_gt = np.loadtxt(data_dir("kitti-07") / "groundtruth.txt")[50]
    np.testing.assert_allclose(truths[0].poses[0][:3, 3], seq_gt[1:4], atol=1e-9)
    results = {}
    for fmt in ("mcap", "ros1"):
        out = tmp_path / f"{fmt}.mcap"
        r = nmnet("replay", str(bags[fmt]), "--out", str(out), "--json", str(tmp_path / f"{fmt}.json"), "--no-progress")
        assert r.returncode == 0, r.stderr
        results[fmt] = json.loads((tmp_path / f"{fmt}.json").read_text())
        counts = read_output(out)
        assert counts["/nmnet_node/matches"] == counts["/nmnet_node/relative_pose"] == 4  # one each per frame
    for key in ("processed", "median_rot_deg", "median_trans_deg", "auc5"):
        assert results["mcap"][key] == pytest.approx(results["ros1"][key])
    assert results["mcap"]["median_rot_deg"] < 1.0


def test_a_compressed_bag_of_16_bit_frames_keeps_them(tmp_path):
    """make-bag --compressed wrote every frame as JPEG, which holds 8 bits: OpenCV clipped a 12-bit camera's frames
    to white without a word. 16-bit frames go in as PNG (as image_transport's compressed PNG) and read back the same."""
    import cv2

    src, folder = data_dir("strecha-fountain-p11"), tmp_path / "f16"
    (folder / "images").mkdir(parents=True)
    for name in ("camera.yaml", "groundtruth.txt"):
        shutil.copy(src / name, folder / name)
    rows = [ln.split() for ln in (src / "images.txt").read_text().splitlines() if ln and not ln.startswith("#")][:2]
    for _, image in rows:
        frame = cv2.imread(str(src / image), cv2.IMREAD_GRAYSCALE).astype(np.uint16) * 16  # 12 bits
        cv2.imwrite(str(folder / "images" / (Path(image).stem + ".png")), frame)
    (folder / "images.txt").write_text("".join(f"{t} images/{Path(image).stem}.png\n" for t, image in rows))
    frames = {}
    for kind, compressed in (("raw", False), ("png", True)):
        assert make_bag(folder, tmp_path / kind, "mcap", compressed=compressed) == 2
        frames[kind] = [f.image for f in read_frames(BagReader(tmp_path / kind))[0]]
    assert [f.dtype for f in frames["png"]] == [np.uint16] * 2 and 2048 < frames["png"][0].max() <= 4080  # JPEG: 255
    assert all(np.array_equal(a, b) for a, b in zip(frames["raw"], frames["png"], strict=True))


@pytest.mark.slow
def test_truncated_mcap_reports_and_uses_readable_part(tmp_path):
    src = next(SAMPLE_BAG.glob("*.mcap"))
    cut = tmp_path / "cut.mcap"
    data = src.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.3)])
    r = nmnet("replay", str(cut), "--out", str(tmp_path / "o.mcap"), "--json", str(tmp_path / "s.json"), "--no-progress",
              "--detector", "sift", "--selector", "ratio+magsac")
    assert r.returncode == 0, r.stderr
    assert "truncated" in r.stdout
    s = json.loads((tmp_path / "s.json").read_text())
    assert 3 <= s["processed"] < 40
    assert read_output(tmp_path / "o.mcap")["/nmnet_node/matches"] == s["processed"]


def test_a_damaged_bag_read_twice_is_reported_once(tmp_path):
    """The replay reads a bag once per pass (--baseline: twice) from one reader; each pass meets the same damage,
    which is said once."""
    src = next(SAMPLE_BAG.glob("*.mcap"))
    cut = tmp_path / "cut.mcap"
    data = src.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.3)])
    reader = BagReader(cut)
    counts = []
    for _ in range(2):
        counts.append(sum(1 for _ in reader.messages(set(reader.topics))))
        counts.append(reader.new_warnings())
    assert counts[0] == counts[2] > 0 and len(counts[1]) == 1 and "truncated" in counts[1][0] and counts[3] == [], counts


def test_an_intact_mcap_lists_its_topics_from_its_summary_and_a_cut_one_by_reading_it(tmp_path):
    """Opening a bag lists its topics from the .mcap's summary section at the file's end (a long recording is not
    read whole just for that: a file whose middle is garbage lists them all); a file cut short has no summary, and
    is read record by record for what it holds."""
    src = next(SAMPLE_BAG.glob("*.mcap"))
    data = bytearray(src.read_bytes())
    full = BagReader(src)
    assert "/camera/image_raw/compressed" in full.topics and full.damage is None
    middle = tmp_path / "middle.mcap"
    data[len(data) // 3: len(data) // 2] = bytes(len(data) // 2 - len(data) // 3)
    middle.write_bytes(data)
    listed = BagReader(middle)
    assert listed.topics == full.topics and listed.damage is None
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 3])
    streamed = BagReader(cut)
    assert streamed.topics == full.topics and streamed.damage is not None


def test_truncated_db3_reports_and_uses_readable_part(tmp_path):
    bag = tmp_path / "full"
    assert make_bag(data_dir("kitti-07"), bag, "sqlite3", compressed=True, frames=range(0, 30)) == 30
    data = next(bag.glob("*.db3")).read_bytes()
    cut = tmp_path / "cut.db3"
    cut.write_bytes(data[: int(len(data) * 0.5)])
    r = nmnet("replay", str(cut), "--out", str(tmp_path / "o.mcap"), "--json", str(tmp_path / "s.json"), "--no-progress",
              "--detector", "sift", "--selector", "ratio+magsac")
    assert r.returncode == 0, r.stderr
    assert "truncated" in r.stdout + r.stderr
    s = json.loads((tmp_path / "s.json").read_text())
    assert 3 <= s["processed"] < 30
    assert read_output(tmp_path / "o.mcap")["/nmnet_node/matches"] == s["processed"]


def split_bag(tmp_path: Path, fmt: str, names: list[str], metadata: bool = True) -> Path:
    """A ROS 2 bag directory as ``ros2 bag record --max-bag-size`` leaves it: one storage file per part, three frames
    each, listed in recording order in metadata.yaml (or, ``metadata=False``, without it)."""
    out, ext = tmp_path / f"split_{fmt}", "mcap" if fmt == "mcap" else "db3"
    out.mkdir(parents=True)
    for k, name in enumerate(names):
        part = tmp_path / f"part{k}_{fmt}"
        assert make_bag(data_dir("kitti-07"), part, fmt, frames=range(3 * k, 3 * k + 3)) == 3
        next(part.glob(f"*.{ext}")).rename(out / f"{name}.{ext}")
        if metadata and k == 0:
            meta = yaml.safe_load((part / "metadata.yaml").read_text())
    if metadata:
        meta["rosbag2_bagfile_information"]["relative_file_paths"] = [f"{n}.{ext}" for n in names]
        (out / "metadata.yaml").write_text(yaml.safe_dump(meta))
    return out


def recompressed(src: Path, out: Path, mode: str, storage: str) -> Path:
    """``src`` rewritten as ``ros2 bag record --compression-mode file|message --compression-format zstd`` writes it."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    w = Writer(out, version=9, storage_plugin=StoragePlugin[storage])
    w.set_compression(CompressionMode[mode], CompressionFormat.ZSTD)
    with AnyReader([src]) as r, w:
        conns = {c.topic: w.add_connection(c.topic, c.msgtype, typestore=typestore()) for c in r.connections}
        for c, t, raw in r.messages():
            w.write(conns[c.topic], t, raw)
    return out


def test_every_file_of_a_split_or_compressed_ros2_bag_is_read_in_recording_order(tmp_path):
    """A long recording split into several files is read whole (the .mcap reader used to take the first file only,
    dropping the rest without a word), in metadata.yaml's order or, without it, in rosbag2's numbering (_2 before
    _10), which is said; file- and message-compressed bags are read through rosbags."""
    stamps = np.loadtxt(data_dir("kitti-07") / "images.txt", usecols=0)[:9]

    def read(path: Path) -> tuple[list[float], list[str]]:
        reader = BagReader(path)
        it, _ = read_frames(reader)
        return [f.stamp for f in it], reader.new_warnings()

    names = ["run_0", "run_1", "run_2"]
    for fmt in ("mcap", "sqlite3"):
        got, warnings = read(split_bag(tmp_path / fmt, fmt, names))
        np.testing.assert_allclose(got, stamps, atol=1e-6, err_msg=fmt)
        assert warnings == [], warnings
    bare = split_bag(tmp_path / "bare", "mcap", ["run_2", "run_10", "run_11"], metadata=False)
    got, warnings = read(bare)
    np.testing.assert_allclose(got, stamps, atol=1e-6)
    assert warnings == [f"{bare}: no readable metadata.yaml; its 3 .mcap file(s) are read directly, in name order "
                        f"(`ros2 bag reindex {bare}` rewrites metadata.yaml)"]
    whole = split_bag(tmp_path / "whole", "mcap", names)
    for mode, storage in (("FILE", "MCAP"), ("MESSAGE", "MCAP"), ("FILE", "SQLITE3")):
        got, _ = read(recompressed(whole, tmp_path / f"{mode}_{storage}", mode, storage))
        np.testing.assert_allclose(got, stamps, atol=1e-6, err_msg=(mode, storage))
    db3 = split_bag(tmp_path / "bare_db3", "sqlite3", ["run_2", "run_10", "run_11"], metadata=False)
    got, warnings = read(db3)  # rosbags needs metadata.yaml: each .db3 is read directly, in rosbag2's numbering
    np.testing.assert_allclose(got, stamps, atol=1e-6)
    assert warnings == [f"{db3}: no readable metadata.yaml; its 3 .db3 file(s) are read directly, in name order "
                        f"(`ros2 bag reindex {db3}` rewrites metadata.yaml)"], warnings
    fake = next((tmp_path / "FILE_SQLITE3").glob("*.zstd"))
    fake.write_bytes(b"not zstd at all")
    with pytest.raises(BagError, match=r"\.db3\.zstd: not a zstd-compressed file \(it does not begin as one"):
        BagReader(tmp_path / "FILE_SQLITE3")
    zipped = tmp_path / "FILE_MCAP"
    (zipped / "metadata.yaml").unlink()
    with pytest.raises(BagError, match=r"\.mcap\.zstd files are compressed and metadata.yaml, which says how, is missing"):
        BagReader(zipped)
    listed = split_bag(tmp_path / "lost", "mcap", names)
    (listed / "run_1.mcap").unlink()
    got, warnings = read(listed)
    np.testing.assert_allclose(got, stamps[[0, 1, 2, 6, 7, 8]], atol=1e-6)
    assert warnings == [f"{listed / 'run_1.mcap'}: listed in {listed / 'metadata.yaml'} but missing; the bag's other "
                        "files are read"]
    r = nmnet("replay", str(split_bag(tmp_path / "cli", "mcap", names)), "--out", str(tmp_path / "o.mcap"), "--json",
              str(tmp_path / "s.json"), "--no-progress", "--detector", "sift", "--selector", "ratio+magsac")
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "s.json").read_text())["processed"] == 9


def test_a_folder_of_ros1_bag_parts_replays_as_one_recording(tmp_path):
    """``rosbag record --split`` leaves run_0.bag, run_1.bag, ...: their folder replays as one recording, merged in
    time and said so (a folder was refused as holding no .mcap or .db3 file, so each part replayed on its own)."""
    parts = tmp_path / "split"
    parts.mkdir()
    for k in range(3):
        assert make_bag(data_dir("kitti-07"), parts / f"run_{k}.bag", "ros1", frames=range(3 * k, 3 * k + 3)) == 3
    stamps = np.loadtxt(data_dir("kitti-07") / "images.txt", usecols=0)[:9]
    reader = BagReader(parts)
    np.testing.assert_allclose([f.stamp for f in read_frames(reader)[0]], stamps, atol=1e-6)
    assert reader.new_warnings() == [f"{parts}: its 3 ROS 1 bags are read as one recording, merged in time"]
    r, s = replay_json(parts, tmp_path, "--detector", "sift", "--selector", "ratio+magsac")
    assert r.returncode == 0 and s["processed"] == 9 and s["scored_pairs"] == 8, (r.stderr, s)


def test_a_replay_scores_no_frame_its_ground_truth_left_out(tmp_path):
    """A bag made from a folder whose ground truth is a pose per frame with frames left out (``nmnet label``'s
    unregistered keyframes): the replay scores only the pairs of frames with a pose of their own, as eval does for
    the folder; it gave every frame between two close poses one interpolated between them (30 pairs here)."""
    src, folder = data_dir("kitti-07"), tmp_path / "labelled"
    folder.mkdir()
    shutil.copy(src / "camera.yaml", folder)
    images = [r.split() for r in (src / "images.txt").read_text().splitlines() if not r.startswith("#")][:31]
    (folder / "images.txt").write_text("".join(f"{stamp} {src / name}\n" for stamp, name in images))
    rows = [r for r in (src / "groundtruth.txt").read_text().splitlines() if not r.startswith("#")]
    (folder / "groundtruth.txt").write_text("".join(rows[i] + "\n" for i in (0, 1, 2, 3, 5, 10, 15, 20, 25, 30)))
    assert make_bag(folder, tmp_path / "b.mcap", "mcap", compressed=False) == 31
    r, s = replay_json(tmp_path / "b.mcap", tmp_path, "--detector", "sift", "--selector", "ratio+magsac")
    assert r.returncode == 0 and s["processed"] == 31 and s["scored_pairs"] == 3, (r.stderr, s)
    said = ("the ground truth has no pose for 21 of 31 frames (its poses are the frames' own, and these have none; at "
            f"{float(images[4][0]):.3f}, ")
    assert f"warning: {said}" in r.stdout and any(w.startswith(said) for w in s["recording_warnings"]), r.stdout


def test_a_live_replays_score_does_not_depend_on_the_frames_the_node_dropped(tmp_path):
    """A live replay scores the pose messages the node recorded. Ground truth a pose per frame, some frames without
    one (unevenly spaced, as nmnet label's keyframes): given every frame played, the frames without a pose have none
    whichever frames the node dropped. Read as recorded, a dropped frame's pose lies between two recorded frames, as
    ground truth at its own rate does, and the rest were interpolated (10 pairs scored here instead of 2)."""
    from nmnet_ros.io.bags import BagReader
    from nmnet_ros.io.mcap_out import McapOutput
    from nmnet_ros.io.trajectory import read_tum
    from nmnet_ros.tools.live import recording_summary

    assert make_bag(data_dir("kitti-07"), tmp_path / "b.mcap", "mcap", compressed=False, frames=range(12)) == 12
    r, s = replay_json(tmp_path / "b.mcap", tmp_path, "--detector", "sift", "--selector", "ratio+magsac")
    assert r.returncode == 0 and s["processed"] == 12, r.stderr
    rows = [ln for ln in (data_dir("kitti-07") / "groundtruth.txt").read_text().splitlines() if not ln.startswith("#")]
    (tmp_path / "gt.txt").write_text("".join(rows[i] + "\n" for i in (0, 1, 2, 4, 6, 8, 10, 11)))
    truth = read_tum(tmp_path / "gt.txt")
    played = [m.log_time_ns for m in BagReader(tmp_path / "o.mcap").messages({"/nmnet_node/relative_pose"})]
    assert len(played) == 12
    dropped = McapOutput(tmp_path / "dropped.mcap")  # the node dropped frame 1: no message of it
    for m in BagReader(tmp_path / "o.mcap").messages({"/nmnet_node/relative_pose"}):
        if m.log_time_ns != played[1]:
            dropped.write(m.topic, m.msgtype, m.msg, m.log_time_ns)
    dropped.close()
    assert recording_summary(tmp_path / "o.mcap", truth, frames=played)[0]["scored_pairs"] == 3  # 0-1, 1-2, 10-11
    assert recording_summary(tmp_path / "o.mcap", truth)[0]["scored_pairs"] == 3  # nothing dropped: the same
    assert recording_summary(tmp_path / "dropped.mcap", truth, frames=played)[0]["scored_pairs"] == 2  # 0-2, 10-11


@pytest.mark.parametrize("fmt, out, sig", [("mcap", "bag", signal.SIGINT), ("ros1", "bag.bag", signal.SIGTERM),
                                           ("mcap", "bag.mcap", signal.SIGTERM)],
                         ids=["mcap-SIGINT", "ros1-SIGTERM", "mcap-file-SIGTERM"])
def test_an_interrupted_make_bag_leaves_a_readable_bag_of_the_frames_written(tmp_path, fmt, out, sig):
    """Ctrl-C (or SIGTERM) during make-bag: the bag is closed with the frames written so far, readable, exit 130. It
    removed the whole output (SIGTERM: left a ROS 2 bag without metadata.yaml, which nothing reads). A single .mcap
    is written in a hidden folder beside it and moved out whole, the folder then removed."""
    out = tmp_path / out
    written = {"bag": out / "bag.mcap", "bag.bag": out, "bag.mcap": tmp_path / "staging.mcap"}[out.name]
    with open(tmp_path / "log", "w") as log:
        proc = subprocess.Popen([sys.executable, "-m", "nmnet_ros.tools.cli", "make-bag", str(data_dir("kitti-07")), "--out", str(out),
                                 "--format", fmt], cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, text=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        t_end = time.monotonic() + 120
        while not (written.exists() and written.stat().st_size > 4e6) and time.monotonic() < t_end and proc.poll() is None:
            time.sleep(0.05)  # a few frames are in the file
            if out.suffix == ".mcap":  # the file being written, in its hidden folder
                written = next(tmp_path.glob(".bag.mcap.*/bag/bag.mcap"), written)
        assert proc.poll() is None, f"make-bag ended before it could be interrupted:\n{(tmp_path / 'log').read_text()}"
        proc.send_signal(sig)
        proc.wait(60)
    said = (tmp_path / "log").read_text()
    counts = [len(list(BagReader(out).messages({t}))) for t in ("/camera/image_raw", "/camera/camera_info",
                                                                  "/ground_truth/pose")]
    frames = counts[0]  # whole frames: the signal lands between two, never between an image and its pose
    assert counts == [frames] * 3, counts
    assert proc.returncode == 130 and "Traceback" not in said, said
    assert 0 < frames < 160 and f"interrupted: wrote {frames} of 160 frames to {out}, a readable bag" in said, said
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["log", out.name]), list(tmp_path.iterdir())


def test_a_folder_of_images_given_as_a_bag_says_how_to_replay_or_score_it(tmp_path):
    """A sequence folder (or a EuRoC / KITTI download) given to replay was "directory holds no .mcap, .db3 or .bag
    file": it says what the folder is and the two commands that take it."""
    with pytest.raises(BagError, match=r"holds no .mcap, .db3 or .bag file$"):
        BagReader(tmp_path)
    src = data_dir("kitti-07")
    kitti = tmp_path / "sequences" / "07"
    (kitti / "image_0").mkdir(parents=True)
    (kitti / "times.txt").write_text("0.0\n")
    (kitti / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    for folder in (src, kitti):
        with pytest.raises(BagError, match=f"{folder}: directory holds no .mcap, .db3 or .bag file; it is a folder of "
                                           f"images with their poses: `nmnet make-bag {folder} --out OUT.mcap` writes it as "
                                           f"a bag to replay, `nmnet eval {folder}` scores its pairs directly"):
            BagReader(folder)


def test_an_mcap_converted_from_a_ros1_bag_reads_as_the_bag(bags, tmp_path):
    """``mcap convert x.bag x.mcap`` keeps ROS 1 schemas (ros1msg, sensor_msgs/Image) and ROS 1 serialisation: the
    frames are those of the .bag (the reader found "no sensor_msgs/Image or CompressedImage topic", listing
    /camera/image_raw/compressed [sensor_msgs/CompressedImage]); live replay refuses it as it refuses a .bag."""
    from mcap.writer import Writer
    from rosbags.highlevel import AnyReader

    converted = tmp_path / "converted.mcap"
    with open(converted, "wb") as fh, AnyReader([bags["ros1"]]) as r:
        w = Writer(fh)
        w.start(profile="ros1", library="test")
        channels = {}
        for c in r.connections:
            schema = w.register_schema(name=c.msgtype.replace("/msg/", "/"), encoding="ros1msg", data=c.msgdef.data.encode())
            channels[c.id] = w.register_channel(topic=c.topic, message_encoding="ros1", schema_id=schema)
        for c, t, raw in r.messages():
            w.add_message(channels[c.id], log_time=t, data=raw, publish_time=t)
        w.finish()
    reader = BagReader(converted)
    assert reader.ros1 and reader.topics["/camera/image_raw/compressed"] == "sensor_msgs/msg/CompressedImage"
    got, want = (list(read_frames(BagReader(path))[0]) for path in (converted, bags["ros1"]))
    assert len(got) == len(want) == 4
    for a, b in zip(got, want, strict=True):
        assert a.stamp == b.stamp
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.camera.K, b.camera.K)
    got, want = (bag_ground_truth(BagReader(path), "/ground_truth/pose") for path in (converted, bags["ros1"]))
    np.testing.assert_array_equal(got.poses, want.poses)
    np.testing.assert_array_equal(got.stamps, want.stamps)
    r = nmnet("replay", str(converted), "--live", "--out", str(tmp_path / "live.mcap"))
    assert r.returncode == 2 and "replay ROS 1 bags (and .mcap files converted from them) offline" in r.stderr, r.stderr


def test_a_ros1_bag_is_refused_by_live_replay_before_the_output_file(bags, tmp_path):
    r = nmnet("replay", str(bags["ros1"]), "--live", "--out", str(tmp_path / "live.mcap"), "--no-progress")
    says = "live replay plays ROS 2 bags (.mcap/.db3); replay ROS 1 bags (and .mcap files converted from them) offline"
    assert r.returncode == 2 and says in r.stderr, r.stderr
    assert not (tmp_path / "live.mcap").exists()


def test_truncated_ros1_bag_is_a_clear_error(bags, tmp_path):
    cut = tmp_path / "cut.bag"
    data = bags["ros1"].read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError, match="cut.bag: cannot open bag.*rosbag reindex"):
        BagReader(cut)


@pytest.mark.slow
def test_bag_without_images_lists_its_topics(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = typestore()
    path = tmp_path / "noimg"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection("/imu/temperature", "sensor_msgs/msg/Temperature", typestore=ts)
        msg = ts.types["sensor_msgs/msg/Temperature"](header=ts.types["std_msgs/msg/Header"](
            stamp=ts.types["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="imu"), temperature=20.0, variance=0.0)
        w.write(c, 1, ts.serialize_cdr(msg, "sensor_msgs/msg/Temperature"))
    with pytest.raises(BagError, match="no sensor_msgs/Image.*/imu/temperature"):
        read_frames(BagReader(path))
    r = nmnet("replay", str(path), "--out", str(tmp_path / "o.mcap"))
    assert r.returncode == 2 and "/imu/temperature" in r.stderr
    from rosbags.typesys.msg import get_types_from_msg  # a camera recorded only through ffmpeg_image_transport

    video = "ffmpeg_image_transport_msgs/msg/FFMPEGPacket"
    ts.register(get_types_from_msg("std_msgs/Header header\nint32 width\nint32 height\nstring encoding\nuint64 pts\n"
                                   "uint8 flags\nbool is_bigendian\nuint8[] data", video))
    with Writer(tmp_path / "video", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        w.add_connection("/camera/image_raw/ffmpeg", video, typestore=ts)
    with pytest.raises(BagError, match=r"/camera/image_raw/ffmpeg is video \(image_transport's theora/ffmpeg/h264\), which "
                                       r"the replay does not decode: record the camera's raw or /compressed topic"):
        read_frames(BagReader(tmp_path / "video"))


@pytest.mark.slow
def test_unwritable_output_fails_before_processing(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    t = time.monotonic()
    r = nmnet("replay", str(SAMPLE_BAG), "--out", str(blocker / "out.mcap"))
    assert r.returncode == 2 and "cannot write output" in r.stderr and "frames" not in r.stdout
    assert time.monotonic() - t < 30


@pytest.mark.slow
def test_an_output_that_would_overwrite_an_input_or_a_recording_is_refused_before_processing(tmp_path):
    bag = tmp_path / "in.mcap"
    shutil.copy(next(SAMPLE_BAG.glob("*.mcap")), bag)
    gt = tmp_path / "gt.txt"
    gt.write_text("# a user's ground truth\n")
    other = tmp_path / "notes.txt"
    other.write_text("a user's file\n")
    kept = {p: p.read_bytes() for p in (bag, gt, other)}
    out = str(tmp_path / "o.mcap")
    for args, said in [(("--out", str(bag)), f"--out {bag} is an input of this command"),
                       (("--out", out, "--json", str(bag)), f"--json {bag} is an input of this command"),
                       (("--out", str(gt), "--gt", str(gt)), f"--out {gt} is an input of this command"),
                       (("--out", str(other)), "exists and was not written by nmnet"),
                       (("--out", out, "--json", out), "is also --out"),
                       (("--out", out, "--json", str(tmp_path / "o_errors.png")), "is also the errors plot"),
                       (("--out", out, "--plots", str(tmp_path / "p"), "--json", str(tmp_path / "p" / "matches.png")),
                        "is also the matches plot"),
                       (("--out", out, "--json", str(tmp_path)), "is a folder"),
                       (("--out", out, "--plots", str(other)), "is a file: give a folder")]:
        r = nmnet("replay", str(bag), *args, "--no-progress")
        assert r.returncode == 2 and said in r.stderr and "frames" not in r.stdout, (args, r.stderr)
    assert all(p.read_bytes() == data for p, data in kept.items())
    # an earlier output is overwritten, and the summary goes into a folder made for it, before the plots
    summary = tmp_path / "new" / "s.json"
    for _ in range(2):
        r = nmnet("replay", str(bag), "--out", out, "--json", str(summary), "--duration", "0.3", "--no-progress")
        assert r.returncode == 0, r.stderr
    assert json.loads(summary.read_text())["frames"] == 3 and read_output(Path(out))["/nmnet_node/relative_pose"] == 3


def _write_random_output(path: Path, messages: int) -> None:
    """An output of ``messages`` incompressible 200 kB messages: several 1 MB chunks."""
    from nmnet_ros.io.mcap_out import McapOutput

    rng = np.random.default_rng(0)
    out = McapOutput(path)
    T = out.ts.types
    try:
        for i in range(messages):
            header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=i, nanosec=0), frame_id="c")
            msg = T["sensor_msgs/msg/CompressedImage"](header=header, format="jpeg",
                                                       data=np.frombuffer(rng.bytes(200_000), np.uint8))
            out.write("/blob", "sensor_msgs/msg/CompressedImage", msg, i * 10**9)
    finally:
        out.close()


def test_an_output_cut_short_anywhere_is_ended_readable_or_removed(tmp_path):
    """A failed write (a full disk) left a file no reader opens ("File end magic is invalid"); end_cut_short keeps
    the complete records before the cut, readable by mcap and rosbags, or removes the file."""
    from nmnet_ros.io.mcap_out import end_cut_short

    whole = tmp_path / "whole.mcap"
    _write_random_output(whole, 20)
    data, kept = whole.read_bytes(), []
    for cut in (4, 40, *range(1_000, len(data), len(data) // 9)):
        part = tmp_path / f"cut{cut}.mcap"
        part.write_bytes(data[:cut])
        kept.append(end_cut_short(part))
        if kept[-1] is None:
            assert not part.exists()
            continue
        counts = read_output(part)  # mcap's reader and rosbags' agree (checked there)
        assert counts.get("/blob", 0) == kept[-1]
    assert kept[:2] == [None, 0]  # not even the header: no file; the header alone: a file without messages
    assert None not in kept[1:] and kept[1:] == sorted(kept[1:]) and 0 < kept[-1] < 20, kept


def with_file_size_limit(limit: int, call: str) -> subprocess.CompletedProcess:
    """Python ``call`` in a process whose files may not grow past ``limit`` bytes (RLIMIT_FSIZE): a write past it
    fails with a real OSError, as on a full disk. An OSError leaving ``call`` is its stderr, exit code 1."""
    code = ("import resource, signal, sys\n"
            "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
            f"resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))\n"
            "from pathlib import Path\n"
            "try:\n"
            f"    {call}\n"
            "except OSError as e:\n"
            "    sys.exit(str(e))\n")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)


@pytest.mark.parametrize(("messages", "limit", "given"), [(30, 2_500_000, "1[0-9]"), (3, 300_000, "3")],
                         ids=["writing", "finishing"])
def test_an_output_whose_disk_fills_keeps_what_was_written_readable(tmp_path, messages, limit, given):
    """Past the limit while writing (a 1 MB chunk leaves, 5 per chunk) or while finishing (all in the last chunk):
    the file keeps the complete chunks before it, readable, and the error says how many messages."""
    out = tmp_path / "o.mcap"
    r = with_file_size_limit(limit, f"__import__('test.test_bags').test_bags._write_random_output(Path({str(out)!r}), "
                                    f"{messages})")
    m = re.fullmatch(f"writing output {re.escape(str(out))} failed \\(File too large\\) with {given} messages given: "
                     "it keeps the first (\\d+), readable\n", r.stderr)
    assert r.returncode == 1 and m, r.stderr
    kept = int(m[1])
    assert (0 < kept < messages if messages > 5 else kept == 0) and read_output(out).get("/blob", 0) == kept


@pytest.mark.parametrize("name", ["run.mcap", "run", "run.bag"])
def test_a_make_bag_whose_disk_fills_names_its_output_and_leaves_none(tmp_path, name):
    """It said "[Errno 28] No space left on device", naming no file (the file-size limit fails a write as a full
    disk does)."""
    out = tmp_path / "bags" / name
    r = with_file_size_limit(1_000_000, f"__import__('nmnet_ros.tools.make_bag').tools.make_bag.make_bag("
                                        f"{str(data_dir('kitti-07'))!r}, {str(out)!r}, frames=range(0, 20))")
    assert r.returncode == 1 and r.stderr.strip() == f"writing {out} failed (File too large): nothing written", r.stderr
    assert list((tmp_path / "bags").iterdir()) == []  # no output, no hidden writing folder


def test_an_output_overwrites_only_an_earlier_output_or_an_empty_file(tmp_path):
    from nmnet_ros.io.mcap_out import McapOutput

    empty, ours, text = tmp_path / "empty.mcap", tmp_path / "ours.mcap", tmp_path / "notes.mcap"
    empty.write_bytes(b"")  # e.g. made by `touch` or a tool that reserves the name
    text.write_text("a user's file named .mcap\n")
    McapOutput(ours).close()
    for path in (empty, ours):
        McapOutput(path).close()
        assert read_output(path) == {}, path  # a valid, empty output
    with pytest.raises(FileExistsError, match="notes.mcap exists and was not written by nmnet"):
        McapOutput(text)
    assert text.read_text() == "a user's file named .mcap\n"


@pytest.mark.slow
def test_missing_bag_and_unknown_format(tmp_path):
    r = nmnet("replay", str(tmp_path / "nope.mcap"), "--out", str(tmp_path / "o.mcap"))
    assert r.returncode == 2 and "no such bag" in r.stderr
    odd = tmp_path / "x.txt"
    odd.write_text("hello")
    with pytest.raises(BagError, match="unknown bag type"):
        BagReader(odd)
    for ranged in (SAMPLE_BAG, SAMPLE_BAG / "kitti07_120-159.mcap"):  # a sequence folder's PATH:a-b given a bag
        with pytest.raises(BagError, match=f"{ranged}:0-10: a bag is read whole, it takes no frame range .* nmnet "
                                           "replay reads a part of it with --start and --duration"):
            BagReader(f"{ranged}:0-10")
    with pytest.raises(BagError, match=r"kitti07_120-159:abc: no such bag$"):  # not a range: no bag by that name
        BagReader(f"{SAMPLE_BAG}:abc")


def test_a_bag_whose_content_is_not_its_extensions_format_is_named(bags, tmp_path):
    """A renamed or wrongly saved file: the error says which format it is (and to rename it), or that it is none,
    instead of the reader's own ('utf-8' codec can't decode, file is not a database); no output file is made."""
    mcap_file = next(bags["mcap"].glob("*.mcap"))
    cases = {"mcap_named.bag": (mcap_file.read_bytes(), "an MCAP file with a .bag name; rename it to .mcap"),
             "bag_named.mcap": (bags["ros1"].read_bytes(), "a ROS 1 bag with a .mcap name; rename it to .bag"),
             "db3_named.mcap": (next(bags["sqlite3"].glob("*.db3")).read_bytes(),
                                "an SQLite rosbag2 file with a .mcap name; rename it to .db3"),
             "junk.mcap": (b"hello world", "not an MCAP file (it does not begin as one: b'hello world')"),
             "empty.db3": (b"", "empty file"),
             "cut.mcap": (mcap_file.read_bytes()[:200], "no sensor_msgs/Image or CompressedImage topic; the bag has: none; "
                          "reading stopped at EndOfFile after 0 topics: the file is damaged or cut short")}
    for name, (data, says) in cases.items():
        (tmp_path / name).write_bytes(data)
        r = nmnet("replay", str(tmp_path / name), "--out", str(tmp_path / "o.mcap"))
        assert r.returncode == 2 and f"{name}: {says}" in r.stderr, (name, r.stderr)
        assert not (tmp_path / "o.mcap").exists()
    with pytest.raises(BagError, match="a ROS 1 bag is one file .* name it b1.bag"):
        make_bag(data_dir("kitti-07"), tmp_path / "b1", "ros1", frames=range(2))
    # a ROS 1 bag into a folder not made yet: '[Errno 2] No such file' (the ROS 2 writers make theirs)
    assert make_bag(data_dir("kitti-07"), tmp_path / "new" / "b.bag", "ros1", frames=range(2)) == 2
    afile = tmp_path / "afile"
    afile.write_text("a user's file")
    for fmt, name in (("mcap", "b"), ("ros1", "b.bag")):  # through a file: '[Errno 20] Not a directory'
        with pytest.raises(ValueError, match=f"the output's folder {afile} is a file: give a folder for the bag"):
            make_bag(data_dir("kitti-07"), afile / name, fmt, frames=range(2))
    assert afile.read_text() == "a user's file"


def test_make_bag_writes_the_format_its_output_is_named_for(tmp_path):
    """`make-bag --out run.bag` wrote a ROS 2 folder of mcap named run.bag (and --out run.db3 one of mcap): the format
    was mcap whatever the name said. The name chooses it now, and a --format that contradicts it is refused before
    anything is written. --out run.mcap (or .db3) is that one file, as `ros2 bag play run.mcap` and Foxglove open it."""
    seq = data_dir("kitti-07")
    r = nmnet("make-bag", str(seq) + ":0-1", "--out", str(tmp_path / "cli.bag"))
    assert r.returncode == 0 and (tmp_path / "cli.bag").is_file(), r.stderr
    for name, kind in (("a.bag", "bag"), ("b.db3", "db3"), ("c.mcap", "mcap"), ("d", "mcap")):
        assert make_bag(seq, tmp_path / name, frames=range(2)) == 2
        reader = BagReader(tmp_path / name)
        # a storage file's name gets that one file (a folder named c.mcap held c.mcap.mcap); another, a bag folder
        assert reader.kind == kind and (tmp_path / name).is_file() == (name != "d"), name
        assert len(list(read_frames(reader)[0])) == 2, name
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bag", "b.db3", "c.mcap", "cli.bag", "d"]  # no staging left
    assert sorted(p.name for p in (tmp_path / "d").iterdir()) == ["d.mcap", "metadata.yaml"]
    for name, fmt, says in (("e.bag", "mcap", "its extension says ros1, --format says mcap; .* e.mcap"),
                            ("f.db3", "mcap", "its extension says sqlite3, --format says mcap"),
                            ("g.mcap", "sqlite3", "its extension says mcap, --format says sqlite3; .* g.db3"),
                            ("h.db3", "ros1", "a ROS 1 bag is one file .* name it h.bag")):
        with pytest.raises(BagError, match=says):
            make_bag(seq, tmp_path / name, fmt, frames=range(2))
        assert not (tmp_path / name).exists(), name


@pytest.mark.slow
def test_sigterm_mid_replay_leaves_valid_output(tmp_path):
    out = tmp_path / "o.mcap"
    # the kornia reference detector takes ~1 s per frame here: 40 frames leave a wide window to interrupt in
    proc = subprocess.Popen([sys.executable, "-m", "nmnet_ros.tools.cli", "replay", str(SAMPLE_BAG), "--out", str(out),
                             "--detector", "hessian-affine"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(15)
    assert proc.poll() is None, "replay finished before it could be interrupted"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "Traceback" not in err
    counts = read_output(out)
    assert 0 < counts.get("/nmnet_node/matches", 0) < 39


def test_demo_without_shared_data(tmp_path):
    """`nmnet demo` needs only the package: shipped weights and sample bag."""
    pkg = tmp_path / "pkg"
    shutil.copytree(ROOT / "nmnet_ros", pkg / "nmnet_ros", ignore=shutil.ignore_patterns("__pycache__"))
    r = subprocess.run([sys.executable, "-m", "nmnet_ros.tools.cli", "demo", "--out-dir", str(tmp_path / "demo")], cwd=pkg,
                       capture_output=True, text=True, timeout=1200)
    assert r.returncode == 0, r.stderr
    print(r.stdout)
    s = json.loads((tmp_path / "demo" / "summary.json").read_text())
    assert s["processed"] == 40 and s["median_rot_deg"] < 1.0
    for name in ("errors.png", "trajectory.png", "matches.png", "nmnet_output.mcap"):
        assert (tmp_path / "demo" / name).stat().st_size > 1000
    assert "SIFT+ratio+MAGSAC++" in r.stdout
    assert "1/2 live: playing" in r.stdout and json.loads((tmp_path / "demo" / "live_summary.json").read_text())["processed"] > 0
    assert "[WARN]" not in r.stderr, r.stderr  # the node warned no_frames while the player drained its results


def test_live_replay_agrees_with_offline(tmp_path):
    """The node as its own process, fed at recorded timing (slowed down), against the offline pass."""
    live = nmnet("replay", str(SAMPLE_BAG), "--out", str(tmp_path / "live.mcap"), "--json", str(tmp_path / "live.json"),
                 "--live", "--rate", "0.1")
    assert live.returncode == 0, live.stderr
    off = nmnet("replay", str(SAMPLE_BAG), "--out", str(tmp_path / "off.mcap"), "--json", str(tmp_path / "off.json"),
                "--no-progress")
    assert off.returncode == 0, off.stderr
    s_live, s_off = (json.loads((tmp_path / f"{m}.json").read_text()) for m in ("live", "off"))
    print("live", s_live, "\noffline", s_off)
    assert s_live["frames"] == s_off["frames"] == 40 and s_live["parameters"] == s_off["parameters"]
    assert s_live["processed"] + s_live["dropped"] == 40 and s_live["processed"] >= 5
    counts = read_output(tmp_path / "live.mcap")
    assert counts["/nmnet_node/matches"] == counts["/nmnet_node/relative_pose"] == s_live["processed"]
    assert s_live["median_rot_deg"] < 1.0 and abs(s_live["median_rot_deg"] - s_off["median_rot_deg"]) < 0.5
    # feature tracks, from the recorded ~/matches (live) and from the results (offline): the same when no frame dropped
    assert s_off["tracks"]["count"] > 1000 and 2.0 < s_off["tracks"]["mean_frames"] and s_off["tracks"]["longest"] >= 10
    if s_live["processed"] == 40:
        assert s_live["tracks"] == pytest.approx(s_off["tracks"], rel=0.05)
    else:
        assert s_live["tracks"]["count"] > 0


@contextmanager
def live_replay_playing(tmp_path: Path, seconds: float):
    """``nmnet replay --live`` of the sample bag at 1 frame a second (output ``live.mcap``, ``s.json``, log
    ``replay.log`` in tmp_path), yielded once the node is up and ``seconds`` of the bag have played; waited for on
    leaving. SIGINT reaches it as a terminal's Ctrl-C does: a shell's background job (CI) starts with it ignored."""
    log = tmp_path / "replay.log"
    with open(log, "w") as fh:
        proc = subprocess.Popen([sys.executable, "-m", "nmnet_ros.tools.cli", "replay", str(SAMPLE_BAG), "--out",
                                 str(tmp_path / "live.mcap"), "--json", str(tmp_path / "s.json"), "--live", "--rate", "0.1"],
                                cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT, text=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        t_end = time.monotonic() + 120
        while "camera_info received" not in log.read_text() and time.monotonic() < t_end and proc.poll() is None:
            time.sleep(0.2)  # the node is up and the bag plays
        time.sleep(seconds)
        assert proc.poll() is None, f"the replay ended before it could be interrupted:\n{log.read_text()}"
        yield proc
        proc.wait(60)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_an_interrupted_live_replay_sums_up_what_it_recorded(tmp_path, sig):
    """Ctrl-C (or SIGTERM) during a live replay: exit 130, a readable output file and the summary of the frames
    played so far, in --json too, marked interrupted. The player let rclpy install its signal handlers, which end
    the context instead of raising: a traceback (ExternalShutdownException) and no summary."""
    with live_replay_playing(tmp_path, 6) as proc:
        proc.send_signal(sig)
    text = (tmp_path / "replay.log").read_text()
    assert proc.returncode == 130 and "Traceback" not in text, text
    summary = json.loads((tmp_path / "s.json").read_text())
    assert summary["interrupted"] is True and 3 <= summary["frames"] < 40 and summary["processed"] >= 2, summary
    assert f"live: {summary['processed']}/{summary['frames']} frames processed" in text, text
    counts = read_output(tmp_path / "live.mcap")
    assert counts["/nmnet_node/matches"] == summary["processed"]  # a frame's pose follows its matches: in flight, one
    assert summary["processed"] - 1 <= counts.get("/nmnet_node/relative_pose", 0) <= summary["processed"]


def children_of(parent: int) -> list[int]:
    """The pids of ``parent``'s child processes (Linux /proc)."""
    children = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:  # the field after the command's closing parenthesis: state, then the parent's pid
            if int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1]) == parent:
                children.append(int(pid))
        except OSError:  # a process that ended meanwhile
            pass
    return children


def test_a_live_replay_whose_node_dies_before_it_subscribes_leaves_an_empty_readable_output(tmp_path):
    """The node ending while it starts (killed here, as the out-of-memory killer would): the replay names its exit
    code, plays nothing, exits 1 and closes its output empty and readable."""
    out = tmp_path / "live.mcap"
    proc = subprocess.Popen([sys.executable, "-m", "nmnet_ros.tools.cli", "replay", str(SAMPLE_BAG), "--out", str(out),
                             "--live"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    t_end = time.monotonic() + 120
    while not (children := children_of(proc.pid)) and proc.poll() is None and time.monotonic() < t_end:
        time.sleep(0.01)  # the node takes seconds to import torch and rclpy: killed long before it subscribes
    assert children, "the replay started no node"
    os.kill(children[0], signal.SIGKILL)
    text = proc.communicate(timeout=120)[0]
    assert proc.returncode == 1 and "error: nmnet_node exited with code -9 before it subscribed" in text, text
    assert "Traceback" not in text
    assert read_output(out) == {}


def test_a_live_replay_whose_node_dies_says_so_and_stops(tmp_path):
    """The node killed mid-replay (as the out-of-memory killer does): the replay stops playing, names the node's exit
    code, sums up what was recorded and exits 1. It went on playing into nothing and reported the rest of the bag
    as frames "not received", exit 0."""
    with live_replay_playing(tmp_path, 4) as proc:
        children = children_of(proc.pid)
        assert len(children) == 1, children
        os.kill(children[0], signal.SIGKILL)
    text = (tmp_path / "replay.log").read_text()
    summary = json.loads((tmp_path / "s.json").read_text())
    assert proc.returncode == 1 and "error: nmnet_node exited with code -9 after" in text, text
    assert summary["node_exit_code"] == -9 and 2 <= summary["frames"] < 20 and summary["processed"] >= 2, summary
    assert read_output(tmp_path / "live.mcap")["/nmnet_node/matches"] == summary["processed"]


def test_two_live_replays_on_one_domain_do_not_hear_each_other(tmp_path):
    """Two live replays at once on the same ROS_DOMAIN_ID (two runs that drew the same random domain, or a domain the
    user set): each records only its own node's results. They shared /live/image, /nmnet_node/matches and
    /diagnostics, so each node took the other's frames too (a CI run: 3 frames played, 6 processed, 9 received)."""
    from mcap.reader import make_reader

    from .rosharness import unique_domain

    env = {**os.environ, "ROS_DOMAIN_ID": str(unique_domain())}
    parts = {"first": ("0", "1.5"), "second": ("2", "1.5")}  # seconds after the first frame; KITTI frames 0.104 s apart
    frames = {"first": 15, "second": 14}  # frames 0-14 and 20-33
    procs = {name: subprocess.Popen([sys.executable, "-m", "nmnet_ros.tools.cli", "replay", str(SAMPLE_BAG), "--live",
                                     "--rate", "0.5", "--start", a, "--duration", d, "--out", str(tmp_path / f"{name}.mcap"),
                                     "--json", str(tmp_path / f"{name}.json")], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT, text=True)
             for name, (a, d) in parts.items()}
    logs = {name: p.communicate(timeout=300)[0] for name, p in procs.items()}
    stamps = {}
    for name, p in procs.items():
        assert p.returncode == 0, logs[name]
        s = json.loads((tmp_path / f"{name}.json").read_text())
        n = frames[name]
        assert s["frames"] == n and s["processed"] + s["dropped"] == n and s["received"] <= n, (name, s)
        with open(tmp_path / f"{name}.mcap", "rb") as f:
            stamps[name] = [m.log_time for _, _, m in make_reader(f).iter_messages(topics=["/nmnet_node/matches"])]
        assert len(stamps[name]) == s["processed"] >= 1, (name, s)  # how many keep up depends on the machine
    assert max(stamps["first"]) < min(stamps["second"])  # each holds its own part of the bag only


def test_live_replay_delivers_raw_frames_over_half_a_megabyte(tmp_path):
    """Raw 768x512 bgr8 frames (1.2 MB) reach the node: the player runs with the shipped large-frames profile.

    Without it, best effort over Fast DDS's default shared memory delivered 0-7 of 20 such frames (nmnet_ros/dds.py), and
    0 of these 6 in a hand run.
    """
    bag = tmp_path / "fountain_raw"
    assert make_bag(data_dir("strecha-fountain-p11"), bag, "mcap", compressed=False, frames=range(6)) == 6
    r = nmnet("replay", str(bag), "--out", str(tmp_path / "live.mcap"), "--json", str(tmp_path / "live.json"),
              "--live", "--rate", "0.5", "--no-progress")
    assert r.returncode == 0, r.stderr
    s = json.loads((tmp_path / "live.json").read_text())
    print(s)
    assert s["frames"] == 6 and s["processed"] == 6, s
    assert read_output(tmp_path / "live.mcap")["/nmnet_node/matches"] == 6


def test_a_standing_camera_is_scored_on_its_rotation(tmp_path):
    """Pairs whose ground truth did not move (standing, or turning on the spot) have no direction to score, so the
    pose AUC leaves them out; their rotation is scored on its own (EuRoC V1_01's first second: the MAV on the
    ground), offline and as --live scores its recording, and the summary says so. Before, they were not scored."""
    from nmnet_ros.tools.live import recording_summary

    bag = tmp_path / "euroc"
    assert make_bag(data_dir("euroc-v101-cam0"), bag, "mcap", frames=range(0, 21)) == 21
    r = nmnet("replay", str(bag), "--out", str(tmp_path / "o.mcap"), "--json", str(tmp_path / "o.json"), "--no-progress")
    assert r.returncode == 0, r.stderr
    s = json.loads((tmp_path / "o.json").read_text())
    assert s["scored_pairs"] == 0 and s["status"] == {"first_frame": 1, "no_motion": 20}, s
    assert s["still_pairs"] == 20 and s["median_still_rot_deg"] < 0.02, s  # measured 0.007; the identity's 0.02
    assert "without motion in the ground truth (20 pairs: standing, or turning on the spot): median rotation error" in r.stdout
    live = recording_summary(tmp_path / "o.mcap", bag_ground_truth(BagReader(bag), "/ground_truth/pose"))[0]
    assert live["still_pairs"] == 20 and live["median_still_rot_deg"] < 0.02, live  # every pair, as offline


def summary_json(summary: dict, tmp_path: Path) -> str:
    """What ``--json`` writes for ``summary``."""
    from nmnet_ros.io.outputs import write_json

    write_json(tmp_path / "s.json", summary)
    return (tmp_path / "s.json").read_text()


def test_a_summary_without_scored_pairs_is_strict_json(tmp_path):
    def refuse(name):
        raise AssertionError(f"{name} is not JSON")

    text = summary_json({"auc5": float("nan"), "nmnet": {"auc10": float("inf"), "per_frame": [1.5, float("nan")]},
                         "frames": 6}, tmp_path)
    doc = json.loads(text, parse_constant=refuse)
    assert doc.pop("written_by").startswith("nmnet_ros")
    assert doc == {"auc5": None, "nmnet": {"auc10": None, "per_frame": [1.5, None]}, "frames": 6}


def test_a_live_summary_says_why_frames_dropped_and_what_it_cannot_know_without_the_nodes_report(capsys, tmp_path):
    """The live replay's summary takes the reasons for dropped frames from the node's last /diagnostics; a node that
    never reported (it ended before its first 1 Hz report) leaves them unknown (null in JSON), not 0 or a crash."""
    from nmnet_ros.core.tracks import track_summary
    from nmnet_ros.tools.replay import live_summary
    from nmnet_ros.tools.scoring import PairScores

    stats = {"published": 10, "results": 7, "latency_ms": [40.0, 60.0], "diagnostics": {}}
    s = live_summary(stats, 2.0, PairScores().summary(), track_summary([]), {"k": 8})
    out = capsys.readouterr().out
    assert (s["processed"], s["dropped"], s["received"], s["dropped_busy"]) == (7, 3, None, None), s
    assert "live: 7/10 frames processed, 3 dropped, latency p50 50 ms" in out and "replaced" not in out, out
    assert json.loads(summary_json(s, tmp_path))["received"] is None and "tracks:" not in out  # no matches recorded, no line
    stats["diagnostics"] = {"frames_received": "9", "frames_dropped": "2", "warn_bad_image": "1", "rate_hz": "3.5"}
    s = live_summary(stats, 2.0, PairScores().summary(), track_summary([np.array([4, 5]), np.array([4])]), {"k": 8})
    out = capsys.readouterr().out
    assert (s["received"], s["dropped_busy"], s["warnings"]) == (9, 2, {"bad_image": 1}), s
    assert "3 dropped (2 replaced by a newer frame while the node was busy, 1 not received)" in out, out
    assert "the node's warnings (its /diagnostics): bad_image 1" in out, out
    assert "tracks: 2, seen in 2.5 frames on average" in out and json.loads(summary_json(s, tmp_path))["tracks"]["longest"] == 3


@pytest.mark.parametrize("model, dist, written", [
    ("equidistant", [0.05, -0.01, 0.003, -0.0005], [0.05, -0.01, 0.003, -0.0005]),  # fisheye: k1..k4 as given
    ("plumb_bob", [-0.28, 0.07, 0.0002, 0.00002], [-0.28, 0.07, 0.0002, 0.00002, 0.0]),  # k3 = 0, not a repeat of k1
])
@pytest.mark.parametrize("fmt", ["mcap", "ros1"])
def test_the_lens_model_travels_through_a_bag(tmp_path, fmt, model, dist, written):
    import yaml

    src = data_dir("kitti-07")
    seq_dir = tmp_path / "seq"
    (seq_dir / "images").mkdir(parents=True)
    names = sorted((src / "images").iterdir())[:2]
    for p in names:
        shutil.copy(p, seq_dir / "images" / p.name)
    (seq_dir / "images.txt").write_text("".join(f"{i * 0.1:.1f} images/{p.name}\n" for i, p in enumerate(names)))
    cam = yaml.safe_load((src / "camera.yaml").read_text())
    cam["distortion_model"], cam["distortion_coefficients"] = model, {"rows": 1, "cols": len(dist), "data": dist}
    (seq_dir / "camera.yaml").write_text(yaml.safe_dump(cam))
    bag = tmp_path / ("b.bag" if fmt == "ros1" else "b")
    assert make_bag(seq_dir, bag, fmt) == 2
    frames = list(read_frames(BagReader(bag))[0])
    assert [f.camera.model for f in frames] == [model, model]
    np.testing.assert_allclose(frames[0].camera.dist, written)


@contextmanager
def bag_copy(src: Path, dst: Path, leave_out: tuple[str, ...] = ()):
    """A ROS 2 bag ``src`` read beside the MCAP bag ``dst`` written, with ``src``'s topics but ``leave_out`` added:
    yields the rosbags reader, writer, the new connections by the old ones' ids, and the typestore."""
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer

    ts = typestore()
    with Reader(src) as r, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        yield r, w, {c.id: w.add_connection(c.topic, c.msgtype, typestore=ts) for c in r.connections
                     if c.topic not in leave_out}, ts


def rewrite_bag(src: Path, dst: Path, edit) -> None:
    """Copy a ROS 2 bag, passing every message through ``edit(topic, msg) -> msg`` (None: leave it out)."""
    with bag_copy(src, dst) as (r, w, conns, ts):
        for c, t, raw in r.messages():
            msg = edit(c.topic, ts.deserialize_cdr(raw, c.msgtype))
            if msg is not None:
                w.write(conns[c.id], t, ts.serialize_cdr(msg, c.msgtype))


@pytest.fixture(scope="module")
def raw_bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("rawbag") / "kitti"
    assert make_bag(data_dir("kitti-07"), path, "mcap", compressed=False, frames=range(60, 66)) == 6
    return path


def test_a_replay_keeps_no_frames_matches_and_sums_up_the_tracks_it_wrote(raw_bag, tmp_path):
    """A pass over a bag keeps a few hundred bytes a frame, not the frame's matches (58 KB at 2000 keypoints: an
    hour of a 30 Hz camera would take 6 GB), and its tracks are those of the ~/matches it wrote."""
    import pickle

    from nmnet_ros.core.pipeline import Frontend
    from nmnet_ros.core.tracks import track_summary
    from nmnet_ros.interface.imgconv import matches_of_cloud
    from nmnet_ros.io.mcap_out import McapOutput
    from nmnet_ros.tools.replay import process_bag

    out = McapOutput(tmp_path / "o.mcap")
    run, n, _ = process_bag(BagReader(raw_bag), out, Frontend(None, {}), progress=False, log=lambda _: None)
    out.close()
    written = [matches_of_cloud(m.msg.point_step, m.msg.fields, m.msg.data)["track_id"]
               for m in BagReader(tmp_path / "o.mcap").messages({"/nmnet_node/matches"})]
    s = run.summary(n)
    print(len(pickle.dumps(run)) / n, "bytes a frame", s["tracks"])
    assert n == 6 and s["processed"] == 6 and s["selected_per_frame"] > 100 and len(written) == 6
    assert s["tracks"] == track_summary(written) and s["tracks"]["longest"] >= 4
    assert len(pickle.dumps(run)) < 5000 * n


def as_16bit(encoding: str = "16UC1"):
    """A bag edit: each mono8 Image as 16-bit frames in ``encoding`` (the grey values x 16); other messages as they are."""
    from dataclasses import replace

    def edit(topic: str, msg):
        if not hasattr(msg, "encoding"):
            return msg
        grey = np.frombuffer(msg.data, np.uint8).astype(np.uint16) * 16
        return replace(msg, encoding=encoding, step=2 * msg.width, data=grey.view(np.uint8))
    return edit


def test_a_bags_16uc1_frames_on_a_topic_not_named_depth_are_named_as_maybe_depth(raw_bag, tmp_path):
    """16UC1 is what depth cameras publish: frames in it on a camera-like topic are read as 16-bit grey, and the
    replay says once that they may be depth and how to choose the camera's stream (as the node does). mono16 is not."""
    rewrite_bag(raw_bag, tmp_path / "d16", as_16bit())
    reader = BagReader(tmp_path / "d16")
    frames = list(read_frames(reader)[0])
    assert len(frames) == 6 and all(f.image is not None and f.image.dtype == np.uint16 for f in frames)
    said = [w for w in reader.warnings if "16UC1" in w]
    assert said == ["frames on /camera/image_raw are 16UC1, what depth cameras publish (a 16-bit grey camera says "
                    "mono16); if so: the front end detects features in camera frames, not in depth images: choose the "
                    "camera's colour, mono or infrared stream with --image-topic"], reader.warnings
    rewrite_bag(raw_bag, tmp_path / "m16", as_16bit("mono16"))  # a 16-bit grey camera: the same pixels, nothing said
    grey = BagReader(tmp_path / "m16")
    assert all(np.array_equal(g.image, f.image) for g, f in zip(read_frames(grey)[0], frames, strict=True))
    assert not [w for w in grey.warnings if "16UC1" in w], grey.warnings


def test_a_replay_says_the_recordings_warnings_before_its_first_frame_not_after_the_pass(raw_bag, tmp_path):
    """On an hour-long bag the topic it took, or frames that look like depth, must be said at once, not at the end.
    The warnings found at the end (ground truth missing for some frames) still come at the end, each once."""
    from nmnet_ros.core.pipeline import Frontend
    from nmnet_ros.tools.replay import process_bag

    rewrite_bag(raw_bag, tmp_path / "d16", as_16bit())
    fe = Frontend(None, {})
    processed, said = [], []
    real = fe.process
    fe.process = lambda *a: processed.append(1) or real(*a)  # the real front end, counted
    run, n, _ = process_bag(BagReader(tmp_path / "d16"), None, fe, progress=False,
                            log=lambda line: said.append((len(processed), line)))
    assert n == 6 and len(processed) == 6
    warned = [(k, line) for k, line in said if line.startswith("warning: ")]
    assert [k for k, line in warned if "are 16UC1" in line] == [0], said  # once, before the first frame was processed
    assert run.recording_warnings == [line.removeprefix("warning: ") for _, line in warned]


def test_a_bag_without_ground_truth_gets_the_match_picture_and_no_empty_plots(raw_bag, tmp_path):
    bag = tmp_path / "no_gt"
    rewrite_bag(raw_bag, bag, lambda topic, msg: None if topic == "/ground_truth/pose" else msg)
    r = nmnet("replay", str(bag), "--out", str(tmp_path / "o.mcap"), "--no-progress")
    assert r.returncode == 0 and "plot:" in r.stdout and "vs ground truth" not in r.stdout, r.stderr
    assert sorted(p.name for p in tmp_path.glob("*.png")) == ["o_matches.png"] and "legend" not in r.stderr
    one = tmp_path / "one_frame"  # ground truth, but a single frame: no pair, no path
    r = nmnet("replay", str(raw_bag), "--out", str(one / "o.mcap"), "--duration", "0", "--no-progress")
    assert r.returncode == 0 and "1/1 frames" in r.stdout and "plot:" not in r.stdout and not list(one.glob("*.png"))


def test_replays_of_several_bags_into_one_folder_keep_each_ones_plots(raw_bag, tmp_path):
    """Beside --out the plots are named after it: a second bag replayed into the folder (or a user's own errors.png
    there) was overwritten by the next replay's errors.png, trajectory.png and matches.png."""
    mine = tmp_path / "errors.png"
    mine.write_bytes(b"a user's plot")
    for name in ("a", "b"):
        r = nmnet("replay", str(raw_bag), "--out", str(tmp_path / f"{name}.mcap"), "--duration", "0.25", "--no-progress")
        assert r.returncode == 0, r.stderr
        assert f"plot: {tmp_path / f'{name}_errors.png'}" in r.stdout
    plots = {p.name: p.stat().st_size for p in tmp_path.glob("*.png")}
    assert set(plots) == {"errors.png"} | {f"{n}_{kind}.png" for n in "ab" for kind in ("errors", "trajectory", "matches")}
    assert mine.read_bytes() == b"a user's plot" and min(plots[p] for p in plots if p != "errors.png") > 1000
    r = nmnet("replay", str(raw_bag), "--out", str(tmp_path / "c.mcap"), "--plots", str(tmp_path / "p"), "--duration",
              "0.25", "--no-progress")  # a folder of its own keeps the plain names
    assert r.returncode == 0 and f"plot: {tmp_path / 'p' / 'matches.png'}" in r.stdout, r.stderr


def test_an_offline_replays_outputs_name_the_images_frame_as_the_nodes_do(raw_bag, tmp_path):
    """The node's outputs carry the image's header; an offline replay wrote "camera" whatever the images named."""
    bag = tmp_path / "front"

    def rename(topic, msg):
        if topic == "/camera/image_raw":
            msg.header.frame_id = "front_camera_optical_frame"
        return msg

    rewrite_bag(raw_bag, bag, rename)
    r = nmnet("replay", str(bag), "--out", str(tmp_path / "o.mcap"), "--duration", "0.25", "--no-progress")
    assert r.returncode == 0, r.stderr
    out = BagReader(tmp_path / "o.mcap")
    frames = {(m.topic, m.msg.header.frame_id) for m in out.messages(set(out.topics))}
    assert frames == {("/nmnet_node/matches", "front_camera_optical_frame"),
                      ("/nmnet_node/relative_pose", "front_camera_optical_frame")}


def test_a_refused_camera_info_is_named_then_counted_for_the_frames_it_stops(raw_bag, tmp_path):
    def fov(topic, msg):
        if topic.endswith("camera_info"):
            msg.distortion_model, msg.d = "fov", np.array([0.9])  # a lens model the replay cannot undistort
        return msg

    bag = tmp_path / "fov"
    rewrite_bag(raw_bag, bag, fov)
    r, s = replay_json(bag, tmp_path)
    out = r.stdout + r.stderr
    assert out.count("skipped, camera_info refused: distortion model 'fov' is not supported") == 3, out  # then counted
    assert "(give the calibration with --camera)" in out, out
    assert "no camera_info yet" not in out and "bad_camera_info: 6 frames in all" in out, out
    assert s["warnings"] == {"bad_camera_info": 6}, s


def restamp_images(src: Path, dst: Path, stamp) -> None:
    """Copy a ROS 2 bag with each image's header stamp replaced by ``stamp(n, old)`` (n counts the images from 1)."""
    n = [0]

    def edit(topic, msg):
        if msg.__class__.__name__.endswith("Image"):
            n[0] += 1
            msg.header.stamp = stamp(n[0], msg.header.stamp)
        return msg

    rewrite_bag(src, dst, edit)


def shifted_from(first: int, seconds: int):
    """A :func:`restamp_images` rule: images ``first`` and later moved by ``seconds``."""
    from rosbags.typesys.stores.ros2_humble import builtin_interfaces__msg__Time as Time

    return lambda n, t: Time(sec=t.sec + seconds, nanosec=t.nanosec) if n >= first else t


def replay_json(bag: Path, tmp_path: Path, *extra: str, name: str = "o") -> tuple[subprocess.CompletedProcess, dict | None]:
    """``nmnet replay BAG --out NAME.mcap --json NAME.json`` and its summary (None when none was written)."""
    r = nmnet("replay", str(bag), "--out", str(tmp_path / f"{name}.mcap"), "--json", str(tmp_path / f"{name}.json"),
              "--no-progress", *extra)
    summary = tmp_path / f"{name}.json"
    return r, json.loads(summary.read_text()) if summary.exists() else None


def test_a_driver_that_never_stamps_is_named_a_few_times_then_counted(raw_bag, tmp_path):
    """Every image stamped 0: the first frame is taken, each later one is a duplicate stamp; the replay says so
    for the first three and then counts, instead of a line per frame of the bag."""
    from rosbags.typesys.stores.ros2_humble import builtin_interfaces__msg__Time as Time

    restamp_images(raw_bag, tmp_path / "unstamped", lambda n, t: Time(sec=0, nanosec=0))
    r, s = replay_json(tmp_path / "unstamped", tmp_path)
    assert r.returncode == 0, r.stderr
    out = r.stdout + r.stderr
    assert out.count("does the camera driver stamp its frames?") == 3, out
    assert out.count("(further 'duplicate_stamp' frames are counted, not named)") == 1, out
    assert "duplicate_stamp: 5 frames in all" in out, out
    assert s["processed"] == 1 and s["warnings"] == {"duplicate_stamp": 5}, s
    assert out.count("If not, --stamp-source arrival stamps them on arrival") == 3, out
    keys = ("processed", "scored_pairs", "median_rot_deg", "median_trans_deg", "auc5")
    _, exact = replay_json(raw_bag, tmp_path, name="exact")
    for mode in ([], ["--live", "--rate", "0.5"]):  # arrival: when the bag recorded each frame; every frame, scored
        r, s = replay_json(tmp_path / "unstamped", tmp_path, "--stamp-source", "arrival", *mode, name="recorded")
        assert r.returncode == 0 and "duplicate_stamp" not in r.stdout + r.stderr, (mode, r.stdout, r.stderr)
        if mode:  # the node as its own process: every frame processed, the pairs --live scores, a good pose
            assert s["processed"] == 6 and s["scored_pairs"] == 5 and s["median_rot_deg"] < 0.5, s
        else:
            assert [s[k] for k in keys] == pytest.approx([exact[k] for k in keys]), (s, exact)


def test_replay_options_that_set_node_parameters_are_checked_as_the_node_checks_them(raw_bag, tmp_path):
    """--max-keypoints, --resize-width and --matches-within-px are refused outside the node's ranges, naming the
    option, before anything is written (a --max-keypoints of -5 used to run, keeping every keypoint but five, and
    recorded -5 as the setting); so is a --rate the player cannot keep (it used to play a negative one backwards).
    --matches-within-px records the matches near the pose, not only its inliers (with ratio_magsac, whose inliers are
    MAGSAC++'s at 0.15 px)."""
    for option, bad, why in (("--max-keypoints", "-5", "max_keypoints: -5 is out of range 100 .. 8000"),
                             ("--max-keypoints", "2.5", "'2.5' is not an integer"),
                             ("--resize-width", "-1", "resize_width: -1 is out of range 0 .. 20000"),
                             ("--matches-within-px", "-1", "matches_within_px: -1.0 is out of range 0.0 .. 100.0"),
                             ("--rate", "0", "'0': expected a speed factor > 0")):
        r = nmnet("replay", str(raw_bag), "--out", str(tmp_path / "none.mcap"), "--live", option, bad)
        assert r.returncode == 2 and f"argument {option}: {why}" in r.stderr, (option, r.stderr)
        assert not (tmp_path / "none.mcap").exists()
    r = nmnet("demo", "--rate", "-1", "--out-dir", str(tmp_path / "demo"))
    assert r.returncode == 2 and "argument --rate: '-1': expected a speed factor > 0" in r.stderr, r.stderr
    summaries = {}
    for px in ("0", "0.5"):
        r, summaries[px] = replay_json(raw_bag, tmp_path, "--matches-within-px", px, "--pose-estimator", "ratio_magsac",
                                       name=f"within{px}")
        assert r.returncode == 0, r.stderr
    print({px: s["selected_per_frame"] for px, s in summaries.items()})
    assert summaries["0.5"]["parameters"]["matches_within_px"] == 0.5
    assert summaries["0.5"]["selected_per_frame"] > 1.2 * summaries["0"]["selected_per_frame"]
    assert summaries["0.5"]["auc5"] == summaries["0"]["auc5"]  # the same poses


@pytest.mark.parametrize("name", ["oracle", "oracle-pool", "oracle+prosac"])
def test_the_oracle_selectors_are_refused_by_replay_as_they_need_ground_truth_labels(raw_bag, tmp_path, name):
    """On a bag's frames the oracles have no labels: the oracle selected nothing and reported every pose as 180
    degrees off."""
    r = nmnet("replay", str(raw_bag), "--out", str(tmp_path / "o.mcap"), "--selector", name)
    assert r.returncode == 2 and f"pose_estimator '{name}' needs each match's ground-truth label" in r.stderr, r.stderr
    assert not (tmp_path / "o.mcap").exists()


def test_start_and_duration_replay_a_part_of_the_bag(raw_bag, tmp_path):
    """--start/--duration (seconds after the first frame, by recording time, as ros2 bag play's --start-offset) replay
    that part only, offline and live, with the calibration recorded before it; a window after the bag's end is said,
    a negative or non-numeric value refused."""
    stamps = [f.stamp for f in read_frames(BagReader(raw_bag))[0]]
    assert len(stamps) == 6 and 0.1 < stamps[1] - stamps[0] < 0.105  # KITTI: frames 0.104 s apart, so 0.15 .. 0.45 s holds 3
    for mode in ([], ["--live", "--rate", "0.5"]):
        r, s = replay_json(raw_bag, tmp_path, "--start", "0.15", "--duration", "0.3", *mode, name="part")
        assert r.returncode == 0, r.stderr
        assert s["frames"] == 3 and s["processed"] == 3 and s["scored_pairs"] == 2, (mode, s)
        offline_or_live = read_output(tmp_path / "part.mcap")
        assert offline_or_live["/nmnet_node/relative_pose"] == 3, offline_or_live
    last = stamps[-1] - stamps[0]
    for mode in ([], ["--live"]):  # live said nothing: "0/0 frames"
        r, s = replay_json(raw_bag, tmp_path, "--start", "10", *mode, name="late")
        assert r.returncode == 0 and s["frames"] == 0, s
        assert ("warning: no frame in --start/--duration's 10 .. inf s (seconds after the bag's first frame): the bag "
                f"ends before, its last frame {last:.3f} s after its first") in r.stdout, (mode, r.stdout)
        # a window between two frames: it said "the bag ends before"
        r, s = replay_json(raw_bag, tmp_path, "--start", "0.11", "--duration", "0.05", *mode, name="between")
        assert r.returncode == 0 and s["frames"] == 0, s
        assert (f"0.11 .. 0.16 s (seconds after the bag's first frame): it falls between the frames at "
                f"{stamps[1] - stamps[0]:.3f} s and {stamps[2] - stamps[0]:.3f} s; give a longer --duration") in r.stdout, \
            (mode, r.stdout)
    for bad in ("-1", "soon", "nan"):
        r = nmnet("replay", str(raw_bag), "--out", str(tmp_path / "none.mcap"), "--start", bad)
        assert r.returncode == 2 and f"argument --start: {bad!r}: expected seconds, a number >= 0" in r.stderr, r.stderr


def test_replay_skips_frames_stamped_again_or_backwards_as_the_node_does(raw_bag, tmp_path):
    """A frame stamped as the one before (a driver republishing) or before it (within time_jump_s) is skipped
    and named, as the node skips it; the next frame in order is related to the last one taken."""
    stamps = []

    def restamp(n, t):
        stamps.append(t)
        return stamps[2] if n == 4 else stamps[1] if n == 5 else t  # the third frame's stamp again; 0.1 s before it

    restamp_images(raw_bag, tmp_path / "restamped", restamp)
    r, s = replay_json(tmp_path / "restamped", tmp_path)
    assert r.returncode == 0, r.stderr
    out = r.stdout + r.stderr
    assert out.count("(duplicate_stamp): skipped (as the node does)") == 1, out
    assert out.count("(out_of_order_stamp): skipped (as the node does)") == 1, out
    assert s["frames"] == 6 and s["processed"] == 4 and s["median_trans_deg"] < 2.0, s
    assert s["warnings"] == {"duplicate_stamp": 1, "out_of_order_stamp": 1}, s
    assert read_output(tmp_path / "o.mcap")["/nmnet_node/relative_pose"] == 4  # one per processed frame


def test_replay_restarts_the_chain_at_a_frame_stamped_far_back_as_the_node_does(raw_bag, tmp_path):
    """A frame more than time_jump_s before the one before (a bag recorded in a loop) is kept and starts a new
    chain: it gets no relative pose; the frame after it is related to it again."""
    from nmnet_ros.interface.posemsg import estimate_of_message

    restamp_images(raw_bag, tmp_path / "looped", shifted_from(5, -3))  # the last two frames, 3 s earlier
    r, s = replay_json(tmp_path / "looped", tmp_path)
    assert r.returncode == 0, r.stderr
    assert (r.stdout + r.stderr).count("restarting from this frame (as the node does)") == 1, r.stdout + r.stderr
    assert s["processed"] == 6 and s["median_trans_deg"] < 2.0, s
    status = []
    for m in BagReader(tmp_path / "o.mcap").messages({"/nmnet_node/relative_pose"}):
        o, t = m.msg.pose.pose.orientation, m.msg.pose.pose.position
        status.append(estimate_of_message(np.array([o.x, o.y, o.z, o.w]), np.array([t.x, t.y, t.z]), m.msg.pose.covariance)[0])
    # the first frame and the restart say "no estimate"; the frame after the restart relates again
    assert status == ["no_estimate", "ok", "ok", "ok", "no_estimate", "ok"], status


def test_replay_skips_frames_stamped_before_zero_and_still_writes_its_file(raw_bag, tmp_path):
    """A negative stamp (a bag restamped too far back) is no ROS time and cannot be logged in an .mcap: such
    frames are skipped and named, as the node skips them, and the replay ends with a readable file."""
    bag = tmp_path / "negative"
    restamp_images(raw_bag, bag, shifted_from(5, -10))  # the last two frames, 10 s earlier: before 0 on this sample
    r, s = replay_json(bag, tmp_path)
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    assert (r.stdout + r.stderr).count("is negative: skipped (ROS time starts at 0") == 2, r.stdout + r.stderr
    assert s["frames"] == 6 and s["processed"] == 4 and s["warnings"] == {"negative_stamp": 2}, s
    assert read_output(tmp_path / "o.mcap")["/nmnet_node/relative_pose"] == 4  # one per processed frame
    # live, the node skips them and its /diagnostics count reaches the summary: the 2 "dropped" are explained
    r, s = replay_json(bag, tmp_path, "--live", "--rate", "0.5", name="live")
    assert r.returncode == 0 and "the node's warnings (its /diagnostics): negative_stamp 2" in r.stdout, r.stdout + r.stderr
    assert s["processed"] == 4 and s["dropped"] == 2 and s["warnings"]["negative_stamp"] == 2, s
    assert s["received"] == 6 and s["dropped_busy"] == 0, s  # neither lost on the way nor replaced while busy
    assert read_output(tmp_path / "live.mcap")["/nmnet_node/relative_pose"] == 4


def test_a_replay_before_a_plane_says_so_and_records_a_covariance_reaching_the_planes_other_pose(tmp_path):
    """Views of a plane (a wall, flat ground) made into a bag: each pair's two poses are said (once per kind, then
    counted, as the node's warn_plane_ambiguous), and the recorded relative poses carry a direction sigma that
    reaches the other one (above 0.3, where a pair with depth gets 0.02-0.05)."""
    import cv2
    from rosbags.highlevel import AnyReader

    from nmnet_ros.interface.posemsg import rot_to_quat

    cam, views = planar_views(seed=5, frames=5)
    seq = tmp_path / "wall"
    (seq / "images").mkdir(parents=True)
    shutil.copy(data_dir("strecha-fountain-p11") / "camera.yaml", seq / "camera.yaml")
    rows, gt = [], []
    for k, (img, T) in enumerate(views):
        cv2.imwrite(str(seq / "images" / f"{k}.png"), img)
        rows.append(f"{0.1 * k:.1f} images/{k}.png")
        gt.append(" ".join(f"{v:.9f}" for v in (0.1 * k, *T[:3, 3], *rot_to_quat(T[:3, :3]))))
    (seq / "images.txt").write_text("\n".join(rows) + "\n")
    (seq / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    assert make_bag(seq, tmp_path / "bag", "mcap") == 5
    r, s = replay_json(tmp_path / "bag", tmp_path)
    assert r.returncode == 0, r.stderr
    assert "the matches lie on one plane (a wall, flat ground), which two poses fit as well" in r.stdout, r.stdout
    assert s["warnings"] == {"plane_ambiguous": 4} and s["status"] == {"first_frame": 1, "ok": 4}, s
    assert s["median_trans_deg"] < 2.0, s  # this sequence's first pair took the true one: it is kept
    with AnyReader([tmp_path / "o.mcap"]) as reader:
        sigmas = [np.sqrt(reader.deserialize(raw, c.msgtype).pose.covariance[0]) for c, _, raw in reader.messages()
                  if c.topic.endswith("relative_pose")]
    assert len(sigmas) == 5 and all(0.3 < d < 1.0 for d in sigmas[1:]), sigmas


def test_ground_truth_poses_that_are_not_numbers_are_a_gap_not_pairs_scored_against_nan(raw_bag, tmp_path):
    """A motion-capture stream that loses the body publishes NaN (or a zero quaternion). Those poses are left out,
    said once: a gap, not pairs taken for "without motion" with a NaN error. This stream is a pose per frame, so the
    frames at them have no pose and their pairs are not scored (as a folder's); one at its own rate would be
    interpolated across the gap."""
    n = {"/ground_truth/pose": 0, "/tf": 0}

    def lose_track(topic, msg):
        if topic in n:  # the same frames lost on the pose topic and on /tf (world -> camera_gt)
            n[topic] += 1
            pose = msg.pose if topic == "/ground_truth/pose" else msg.transforms[0].transform
            if n[topic] == 3:
                (pose.position if topic == "/ground_truth/pose" else pose.translation).x = float("nan")
            if n[topic] == 5:
                q = pose.orientation if topic == "/ground_truth/pose" else pose.rotation
                q.x = q.y = q.z = q.w = 0.0
        return msg

    rewrite_bag(raw_bag, tmp_path / "lost", lose_track)
    assert n == {"/ground_truth/pose": 6, "/tf": 6}
    for source, extra in (("/ground_truth/pose", []), ("--gt-tf world:camera_gt", ["--gt-tf", "world:camera_gt"])):
        r, s = replay_json(tmp_path / "lost", tmp_path, *extra)
        assert r.returncode == 0 and "RuntimeWarning" not in r.stderr, r.stderr
        assert (f"warning: {source}: 2 of 6 ground-truth poses are not finite numbers (NaN, or a zero quaternion: "
                "a lost track?): left out") in r.stdout, r.stdout
        assert s["scored_pairs"] == 1 and s["still_pairs"] == 0 and s["median_trans_deg"] < 2.0, s  # frames 60-61
        assert "the ground truth has no pose for 2 of 6 frames (its poses are the frames' own" in r.stdout, r.stdout

    def lose_all(topic, msg):
        if topic == "/ground_truth/pose":
            msg.pose.position.x = float("nan")
        elif topic == "/tf":
            msg.transforms[0].transform.translation.x = float("nan")
        return msg

    rewrite_bag(raw_bag, tmp_path / "none", lose_all)  # a track lost throughout: nothing to score against
    r, s = replay_json(tmp_path / "none", tmp_path, name="none")
    assert r.returncode == 0 and "/ground_truth/pose: 6 of 6 ground-truth poses are not finite" in r.stdout, r.stdout
    assert s["scored_pairs"] == 0 and s["processed"] == 6, s
    r = nmnet("replay", str(tmp_path / "none"), "--out", str(tmp_path / "tf.mcap"), "--gt-tf", "world:camera_gt")
    assert r.returncode == 2 and ("--gt-tf world:camera_gt: no transform from one to the other is a finite number"
                                  in r.stderr), r.stderr
    assert not (tmp_path / "tf.mcap").exists()


def test_frames_ground_truth_at_its_own_rate_does_not_reach_are_named(raw_bag, tmp_path):
    """A ``--gt`` stream at its own rate (20 Hz, 4 ms after the frames) that loses the camera for 0.3 s: the frames
    in the gap have no pose, and the replay says so and why, rather than scoring fewer pairs without a word."""
    from nmnet_ros.interface.posemsg import rot_to_quat
    from nmnet_ros.io.datasets import Sequence
    from nmnet_ros.io.trajectory import between

    seq = Sequence.load(data_dir("kitti-07"))
    lines = []
    for i in range(60, 66):
        for delay in (0.004, 0.054):
            t = seq.stamps[i] + delay
            if not seq.stamps[62] - 0.1 < t < seq.stamps[63] + 0.1:  # the tracker lost the camera around frame 63
                T = between(seq.poses[i], seq.poses[i + 1], delay / (seq.stamps[i + 1] - seq.stamps[i]))
                q = rot_to_quat(T[:3, :3])
                lines.append(f"{t:.6f} {T[0, 3]} {T[1, 3]} {T[2, 3]} {q[0]} {q[1]} {q[2]} {q[3]}\n")
    (tmp_path / "gt.txt").write_text("".join(lines))
    r, s = replay_json(raw_bag, tmp_path, "--gt", str(tmp_path / "gt.txt"), "--detector", "sift", "--selector",
                       "ratio+magsac")
    assert r.returncode == 0 and s["scored_pairs"] == 2, (r.stderr, s)  # 60-61, 64-65
    said = (f"the ground truth has no pose for 2 of 6 frames (none close enough to their stamps to take or interpolate; "
            f"at {seq.stamps[62]:.3f}, {seq.stamps[63]:.3f} s): the pairs with them are not scored")
    assert s["recording_warnings"] == [said] and f"warning: {said}" in r.stdout, (r.stdout, s)


def test_ground_truth_from_a_tum_file_scores_as_the_bags_own(raw_bag, tmp_path):
    """`--gt FILE` (TUM) and `--gt-tf world:camera_gt` (the bag's /tf) give the numbers the bag's own PoseStamped
    give, offline and in --live's scoring; a bad file, or a transform the bag lacks, stops the replay before the output
    file is made, naming the file and line or the transforms there are."""
    from nmnet_ros.io.trajectory import read_tum
    from nmnet_ros.tools.live import recording_summary

    tum = data_dir("kitti-07") / "groundtruth.txt"  # the poses the bag was made with, at the frames' stamps
    runs = {}
    for name, extra in (("bag", []), ("tum", ["--gt", str(tum)]), ("tf", ["--gt-tf", "world:camera_gt"])):
        r = nmnet("replay", str(raw_bag), "--out", str(tmp_path / f"{name}.mcap"), "--json", str(tmp_path / f"{name}.json"),
                  "--no-progress", *extra)
        assert r.returncode == 0, r.stderr
        runs[name] = json.loads((tmp_path / f"{name}.json").read_text())
    keys = ("median_rot_deg", "median_trans_deg", "auc5", "auc10", "auc20")
    assert runs["bag"]["auc5"] > 80 and [runs["tum"][k] for k in keys] == pytest.approx([runs["bag"][k] for k in keys]), runs
    assert [runs["tf"][k] for k in keys] == pytest.approx([runs["bag"][k] for k in keys]), runs  # make-bag's /tf: the same
    for value, says in (("world:robot", "--gt-tf world:robot: no transforms lead from world to robot; there are "
                                        "world:camera_gt (on /tf)"),
                        ("world", "--gt-tf world:camera: no transforms lead from world to camera"),  # the images' frame
                        ("world:", "--gt-tf: 'world:': expected PARENT or PARENT:CHILD, frame names"),
                        (":camera_gt", "--gt-tf: ':camera_gt': expected PARENT or PARENT:CHILD, frame names")):
        r = nmnet("replay", str(raw_bag), "--out", str(tmp_path / "none.mcap"), "--gt-tf", value, "--no-progress")
        assert r.returncode == 2 and says in r.stderr and not (tmp_path / "none.mcap").exists(), r.stderr
    own = bag_ground_truth(BagReader(raw_bag), "/ground_truth/pose")
    tf = tf_ground_truth(BagReader(raw_bag), "/tf", "world", "camera_gt")
    live_scoring = [recording_summary(tmp_path / "bag.mcap", gt)[0] for gt in (own, read_tum(tum), tf)]
    assert live_scoring[0]["scored_pairs"] == 5 and live_scoring[1] == pytest.approx(live_scoring[0])  # as --live scores
    assert runs["bag"][FITTED[0]] is not None  # fitted, so that the comparison below is not of two Nones
    assert [live_scoring[0][k] for k in FITTED] == pytest.approx([runs["bag"][k] for k in FITTED]), live_scoring[0]
    assert live_scoring[2] == pytest.approx(live_scoring[0])
    unscored = recording_summary(tmp_path / "bag.mcap", None)[0]  # no ground truth: nothing scored
    assert unscored["scored_pairs"] == 0 and unscored["median_rot_deg"] is None and np.isnan(unscored["auc5"])
    shifted = tmp_path / "shifted.txt"  # every pose a frame later: the errors change
    rows = [ln.split() for ln in tum.read_text().splitlines() if not ln.startswith("#")]
    shifted.write_text("".join(" ".join([a[0], *b[1:]]) + "\n" for a, b in zip(rows, rows[1:], strict=False)))
    assert recording_summary(tmp_path / "bag.mcap", read_tum(shifted))[0] != pytest.approx(live_scoring[0])
    gap = tmp_path / "gap.txt"  # no pose for frame 62: its two pairs are not scored (not against frame 61's pose)
    gap.write_text("".join(" ".join(r) + "\n" for r in rows[55:62] + rows[63:70]))
    assert recording_summary(tmp_path / "bag.mcap", read_tum(gap))[0]["scored_pairs"] == 3
    bad = tmp_path / "bad.txt"
    bad.write_text("0.0 1 2 3\n")
    r = nmnet("replay", str(raw_bag), "--out", str(tmp_path / "none.mcap"), "--gt", str(bad), "--no-progress")
    assert r.returncode == 2 and f"{bad}:1: expected 'timestamp tx ty tz qx qy qz qw'" in r.stderr, r.stderr
    assert not (tmp_path / "none.mcap").exists()


def test_ground_truth_at_its_own_rate_and_stamps_scores_every_frame(raw_bag, tmp_path, capsys):
    """A motion-capture stream in the bag is not stamped with the camera: here it runs at twice the camera's rate,
    4 and 54 ms after each frame, with the poses of those times (along the path between the frames' poses). Each
    frame's pose is interpolated between the two around it (within a millimetre of the frame's own; the nearest, 4 ms
    later, is 30 mm off at KITTI's speed), and the scores are close to the exact-stamp bag's, offline and as --live
    scores them (median errors 0.022 / 0.300 deg against 0.033 / 0.305: across a frame the path between the KITTI
    poses bends, which interpolation cannot know). Ground truth on another clock is named."""
    from nmnet_ros.interface.posemsg import rot_to_quat
    from nmnet_ros.io.datasets import Sequence
    from nmnet_ros.io.trajectory import between, read_tum
    from nmnet_ros.tools.live import recording_summary

    seq = Sequence.load(data_dir("kitti-07"))  # the raw bag's frames 60-65, and the pose after them
    mocap = tmp_path / "mocap"
    with bag_copy(raw_bag, mocap) as (r, w, conns, ts):
        Time = ts.types["builtin_interfaces/msg/Time"]
        for c, t, raw in r.messages():
            if c.topic != "/ground_truth/pose":
                w.write(conns[c.id], t, raw)
                continue
            i = int(np.argmin(np.abs(seq.stamps - t / 1e9)))
            for delay in (0.004, 0.054):
                msg = ts.deserialize_cdr(raw, c.msgtype)
                T = between(seq.poses[i], seq.poses[i + 1], delay / (seq.stamps[i + 1] - seq.stamps[i]))
                ns = t + round(delay * 1e9)
                msg.header.stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
                p, q = msg.pose.position, msg.pose.orientation
                (p.x, p.y, p.z), (q.x, q.y, q.z, q.w) = T[:3, 3], rot_to_quat(T[:3, :3])
                w.write(conns[c.id], ns, ts.serialize_cdr(msg, c.msgtype))
    runs = {}
    for name, bag in (("exact", raw_bag), ("mocap", mocap)):
        r, runs[name] = replay_json(bag, tmp_path, name=name)
        assert r.returncode == 0, r.stderr
    exact, mocap_run = runs["exact"], runs["mocap"]
    assert exact["scored_pairs"] == mocap_run["scored_pairs"] == 5, runs
    assert exact["recording_warnings"] == mocap_run["recording_warnings"] == [], runs  # every frame has a pose
    assert abs(mocap_run["median_trans_deg"] - exact["median_trans_deg"]) < 0.02, runs  # 0.005 measured
    assert abs(mocap_run["median_rot_deg"] - exact["median_rot_deg"]) < 0.02, runs  # 0.011 measured
    truth = bag_ground_truth(BagReader(mocap), "/ground_truth/pose")
    assert len(truth.stamps) == 12 and 0.04 < truth.spacing < 0.06
    at_frames = truth.poses_at(seq.stamps[60:66])
    assert np.abs(at_frames[1:, :3, 3] - seq.poses[61:66, :3, 3]).max() < 1e-3  # within a millimetre
    assert 0.02 < np.abs(at_frames[0, :3, 3] - seq.poses[60, :3, 3]).max() < 0.04  # before the stream: the nearest pose
    exact_truth = bag_ground_truth(BagReader(raw_bag), "/ground_truth/pose")
    live_like = recording_summary(tmp_path / "exact.mcap", truth)[0]  # as --live scores
    assert live_like["scored_pairs"] == 5
    assert abs(live_like["median_trans_deg"] - recording_summary(tmp_path / "exact.mcap", exact_truth)[0]["median_trans_deg"]) < 0.02
    capsys.readouterr()
    rows = [ln.split() for ln in (data_dir("kitti-07") / "groundtruth.txt").read_text().splitlines() if ln[0] != "#"]
    (tmp_path / "other_clock.txt").write_text("".join(f"{float(r[0]) + 1000} {' '.join(r[1:])}\n" for r in rows))
    says = "the ground truth has no pose at any frame's stamp (poses 1000.000 .. "
    r, other = replay_json(raw_bag, tmp_path, "--gt", str(tmp_path / "other_clock.txt"), name="other")
    assert r.returncode == 0 and says in r.stdout and other["scored_pairs"] == 0, (r.stdout, other)
    assert recording_summary(tmp_path / "exact.mcap", read_tum(tmp_path / "other_clock.txt"))[0]["scored_pairs"] == 0
    assert says in capsys.readouterr().err


def robot_tf_bag(src: Path, dst: Path, cam_in_body: np.ndarray) -> None:
    """``src`` with its world -> camera_gt transforms replaced by a robot's tree: motion capture's world -> base_link on
    /tf, base_link -> camera_link on /tf_static, camera_link -> camera_optical republished on /tf at every frame and
    stamped 0.1 s ahead (ROS 1's static_transform_publisher); ``cam_in_body`` is camera_optical in base_link, the
    frame the images name."""
    from nmnet_ros.interface.posemsg import rot_to_quat

    ts = typestore()
    T = ts.types
    mount = np.eye(4)
    mount[:3, 3] = [0.1, 0.0, 0.0]
    optical = np.linalg.inv(mount) @ cam_in_body

    def transform(stamp, parent: str, child: str, pose: np.ndarray):
        q = rot_to_quat(pose[:3, :3])
        return T["geometry_msgs/msg/TransformStamped"](
            header=T["std_msgs/msg/Header"](stamp=stamp, frame_id=parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](*pose[:3, 3]),
                                                       rotation=T["geometry_msgs/msg/Quaternion"](*q)))

    tf_type = "tf2_msgs/msg/TFMessage"
    with bag_copy(src, dst) as (r, w, conns, _):
        static = w.add_connection("/tf_static", tf_type, typestore=ts)
        for c, t, raw in r.messages():
            if c.msgtype == "sensor_msgs/msg/Image":
                msg = ts.deserialize_cdr(raw, c.msgtype)
                msg.header.frame_id = "camera_optical"
                raw = ts.serialize_cdr(msg, c.msgtype)
            if c.topic != "/tf":
                w.write(conns[c.id], t, raw)
                continue
            cam = ts.deserialize_cdr(raw, c.msgtype).transforms[0]
            body = transform(cam.header.stamp, "world", "base_link", pose_from_msg(cam) @ np.linalg.inv(cam_in_body))
            ahead = T["builtin_interfaces/msg/Time"](sec=cam.header.stamp.sec, nanosec=cam.header.stamp.nanosec)
            ahead.nanosec += 100_000_000
            ahead.sec, ahead.nanosec = ahead.sec + ahead.nanosec // 10**9, ahead.nanosec % 10**9
            fixed = transform(ahead, "camera_link", "camera_optical", optical)
            w.write(conns[c.id], t, ts.serialize_cdr(T[tf_type](transforms=[body, fixed]), tf_type))
        zero = T["builtin_interfaces/msg/Time"](sec=0, nanosec=0)
        w.write(static, 0, ts.serialize_cdr(T[tf_type](transforms=[transform(zero, "base_link", "camera_link", mount)]),
                                            tf_type))


def test_ground_truth_through_a_robots_tf_tree_scores_as_the_cameras_own_poses(raw_bag, tmp_path):
    """--gt-tf world:camera_optical on a robot's tree (moving world -> base_link, /tf_static base_link -> camera_link,
    a republished camera_link -> camera_optical stamped ahead) chains the three transforms, says so, and gives the
    scores of the camera's own poses; before, only one published edge was taken ("no such transform"). `--gt-tf world`
    takes the frame the images name; another frame of the tree is pointed out. Frames no chain joins are named with
    the transforms there are."""
    cam_in_body = np.eye(4)
    cam_in_body[:3, :3], cam_in_body[:3, 3] = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]]), [0.3, 0.0, 0.5]
    robot = tmp_path / "robot_tf"
    robot_tf_bag(raw_bag, robot, cam_in_body)
    own = tf_ground_truth(BagReader(raw_bag), "/tf", "world", "camera_gt")
    reader = BagReader(robot)
    chained = tf_ground_truth(reader, "/tf", "world", "camera_optical")
    assert np.allclose(chained.stamps, own.stamps) and np.allclose(chained.poses, own.poses)
    assert reader.warnings == ["--gt-tf world:camera_optical: chained world -> base_link -> camera_link -> camera_optical "
                               "(moving: world:base_link)"]
    up = tf_ground_truth(BagReader(robot), "/tf", "camera_optical", "world")  # asked the other way round: the inverse
    assert np.allclose(up.poses @ own.poses, np.eye(4))
    body = BagReader(robot)  # the robot's body, not the frame its images name: said, with the frame to give
    assert image_frame(body, "/camera/image_raw") == "camera_optical"
    tf_ground_truth(body, "/tf", "world", "base_link", camera_frame="camera_optical")
    assert ("--gt-tf world:base_link: the images are in frame camera_optical, which the transforms have; --gt-tf "
            "world:camera_optical scores the camera itself") in body.warnings[-1], body.warnings
    runs = {}
    for name, bag, frames in (("own", raw_bag, "world:camera_gt"), ("robot", robot, "world")):  # the images' frame
        r, runs[name] = replay_json(bag, tmp_path, "--gt-tf", frames, name=name)
        assert r.returncode == 0, r.stderr
        runs[name]["log"] = r.stdout
    keys = ("scored_pairs", "median_rot_deg", "median_trans_deg", "auc5", "auc10", "auc20")
    assert runs["own"]["scored_pairs"] == 5 and [runs["robot"][k] for k in keys] == pytest.approx(
        [runs["own"][k] for k in keys]), runs
    assert "warning: --gt-tf world:camera_optical: chained world -> base_link" in runs["robot"]["log"]
    assert "the images are in frame" not in runs["robot"]["log"]  # the camera's own frame: nothing to say
    r, _ = replay_json(robot, tmp_path, "--gt-tf", "world:base_link", name="body")
    assert r.returncode == 0 and "warning: --gt-tf world:base_link: the images are in frame camera_optical" in r.stdout
    with pytest.raises(BagError, match="--gt-tf base_link:camera_link: every transform from base_link to camera_link is "
                                       "on /tf_static: no motion to score against"):
        tf_ground_truth(BagReader(robot), "/tf", "base_link", "camera_link")
    def no_frame(topic, msg):
        if topic == "/camera/image_raw":
            msg.header.frame_id = ""
        return msg

    rewrite_bag(raw_bag, tmp_path / "no_frame", no_frame)  # a driver that names no frame: CHILD is asked for
    r = nmnet("replay", str(tmp_path / "no_frame"), "--out", str(tmp_path / "none.mcap"), "--gt-tf", "world", "--no-progress")
    assert r.returncode == 2 and ("--gt-tf world: the images on /camera/image_raw name no frame (an empty header.frame_id); "
                                  "give the camera's frame: --gt-tf world:CHILD") in r.stderr, r.stderr
    r = nmnet("replay", str(robot), "--out", str(tmp_path / "none.mcap"), "--gt-tf", "world:camera", "--no-progress")
    says = ("--gt-tf world:camera: no transforms lead from world to camera; there are base_link:camera_link, "
            "camera_link:camera_optical, world:base_link (on /tf and /tf_static)")
    assert r.returncode == 2 and says in r.stderr and not (tmp_path / "none.mcap").exists(), r.stderr


def test_ground_truth_from_ros1_tf_messages_of_before_tf2(tmp_path):
    """ROS 1 bags recorded before tf2 (TUM RGB-D's, with /world -> /kinect from motion capture) carry /tf as
    tf/tfMessage with slashed frame names; --gt-tf reads them as tf2_msgs/TFMessage. Before, the topic was refused
    ("carries tf/msg/tfMessage, not tf2_msgs/msg/TFMessage")."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys.msg import get_types_from_msg

    ts = typestore(ros1=True)
    ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf/msg/tfMessage"))
    T, bag = ts.types, tmp_path / "tum_like.bag"
    with Writer(bag) as w:
        conn = w.add_connection("/tf", "tf/msg/tfMessage", typestore=ts)
        for i in range(5):
            header = T["std_msgs/msg/Header"](seq=i, stamp=T["builtin_interfaces/msg/Time"](sec=10 + i, nanosec=0),
                                              frame_id="/world")
            move = T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](float(i), 0.0, 0.0),
                                                    rotation=T["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0))
            msg = T["tf/msg/tfMessage"](transforms=[T["geometry_msgs/msg/TransformStamped"](header=header,
                                                                                            child_frame_id="/kinect",
                                                                                            transform=move)])
            w.write(conn, (10 + i) * 10**9, ts.serialize_ros1(msg, "tf/msg/tfMessage"))
    truth = tf_ground_truth(BagReader(bag), "/tf", "world", "kinect")
    assert truth.stamps.tolist() == [10, 11, 12, 13, 14] and truth.poses[:, 0, 3].tolist() == [0, 1, 2, 3, 4]


def tum_rgbd_bag(src: Path, dst: Path, cam_in_body: np.ndarray) -> None:
    """The ROS 1 bag ``src`` laid out as TUM RGB-D's bags are: rgb8 frames on /camera/rgb/image_color with their
    camera_info, a 32FC1 depth image beside each, and the ground truth only as tf/tfMessage on /tf: motion capture's
    /world -> /kinect, then /kinect -> /openni_camera -> /openni_rgb_optical_frame republished with every message
    (``cam_in_body``: the optical frame in /kinect)."""
    from rosbags.rosbag1 import Reader, Writer
    from rosbags.typesys.msg import get_types_from_msg

    from nmnet_ros.interface.posemsg import rot_to_quat

    ts = typestore(ros1=True)
    ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf/msg/tfMessage"))
    T = ts.types
    mount = np.eye(4)
    mount[:3, 3] = [0.0, -0.02, 0.0]

    def transform(header, parent: str, child: str, pose: np.ndarray):
        head = T["std_msgs/msg/Header"](seq=header.seq, stamp=header.stamp, frame_id=parent)
        return T["geometry_msgs/msg/TransformStamped"](
            header=head, child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](*pose[:3, 3]),
                                                       rotation=T["geometry_msgs/msg/Quaternion"](*rot_to_quat(pose[:3, :3]))))

    image, tf_type = "sensor_msgs/msg/Image", "tf/msg/tfMessage"
    with Reader(src) as r, Writer(dst) as w:
        out = {topic: w.add_connection(topic, mtype, typestore=ts) for topic, mtype in (
            ("/camera/rgb/image_color", image), ("/camera/rgb/camera_info", "sensor_msgs/msg/CameraInfo"),
            ("/camera/depth/image", image), ("/tf", tf_type))}
        for c, t, raw in r.messages():
            msg = ts.deserialize_ros1(raw, c.msgtype)
            if c.msgtype == image:
                h, wd = msg.height, msg.width
                rgb = np.repeat(np.asarray(msg.data).reshape(h, wd, 1), 3, axis=2).ravel()
                w.write(out["/camera/rgb/image_color"], t, ts.serialize_ros1(
                    T[image](header=msg.header, height=h, width=wd, encoding="rgb8", is_bigendian=0, step=3 * wd, data=rgb), image))
                depth = np.ones((h, wd), np.float32).view(np.uint8).ravel()
                w.write(out["/camera/depth/image"], t, ts.serialize_ros1(
                    T[image](header=msg.header, height=h, width=wd, encoding="32FC1", is_bigendian=0, step=4 * wd, data=depth),
                    image))
            elif c.msgtype.endswith("CameraInfo"):
                w.write(out["/camera/rgb/camera_info"], t, raw)
            elif c.topic == "/tf":
                cam = msg.transforms[0]
                body = pose_from_msg(cam) @ np.linalg.inv(cam_in_body)
                tree = [transform(cam.header, "/world", "/kinect", body),
                        transform(cam.header, "/kinect", "/openni_camera", mount),
                        transform(cam.header, "/openni_camera", "/openni_rgb_optical_frame", np.linalg.inv(mount) @ cam_in_body)]
                w.write(out["/tf"], t, ts.serialize_ros1(T[tf_type](transforms=tree), tf_type))


def test_a_tum_rgbd_style_ros1_bag_replays_with_its_tf_ground_truth(tmp_path):
    """A ROS 1 bag as TUM RGB-D records them (colour and depth images, ground truth only on /tf as tf/tfMessage, the
    camera three transforms below the motion-capture frame): without --image-topic the colour frames are taken, and
    --gt-tf /world:/openni_rgb_optical_frame scores them as the bag's own camera poses do."""
    raw = tmp_path / "raw.bag"
    assert make_bag(data_dir("kitti-07"), raw, "ros1", frames=range(60, 66)) == 6
    cam_in_body = np.eye(4)
    cam_in_body[:3, :3], cam_in_body[:3, 3] = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]]), [0.1, 0.0, 0.05]
    tum_rgbd_bag(raw, tmp_path / "tum.bag", cam_in_body)
    keys = ("processed", "scored_pairs", "median_rot_deg", "median_trans_deg", "auc5", "auc10")
    # ratio_magsac: MAGSAC++ on a cut keeps its pose when grey rounding moves the frames by 1e-5, where the default's
    # PROSAC order can follow a score changed in its last digits to another pose, as good
    r, own = replay_json(raw, tmp_path, "--pose-estimator", "ratio_magsac", name="own")
    assert r.returncode == 0 and own["scored_pairs"] == 5, (r.stderr, own)
    r, tum = replay_json(tmp_path / "tum.bag", tmp_path, "--gt-tf", "/world:/openni_rgb_optical_frame",
                         "--pose-estimator", "ratio_magsac", name="tum")
    assert r.returncode == 0, r.stderr
    # the same poses (to 4e-15) and frames; rgb8's grey (float32 weights summing to 1 within 1e-7) moves errors by 1e-5
    assert [tum[k] for k in keys] == pytest.approx([own[k] for k in keys], rel=1e-4), (tum, own)
    assert "taken, not the depth images on /camera/depth/image" in r.stdout, r.stdout
    assert "chained world -> kinect -> openni_camera -> openni_rgb_optical_frame (moving: world:kinect)" in r.stdout


def test_an_rgbd_cameras_depth_images_are_not_taken_for_its_frames(tmp_path):
    """An RGB-D camera's bag (TUM RGB-D's, a RealSense's) holds depth images beside the frames: the frames are taken,
    and said so, with their own camera_info (the replay asked to choose). Two cameras still ask."""
    from nmnet_ros.interface.dds import is_depth
    from nmnet_ros.io.bags import pick_image

    image, info = "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo"
    for topic in ("/camera/depth/image", "/camera/aligned_depth_to_color/image_raw", "/cam/depth_registered/image_raw",
                  "/camera/depth/image_raw/compressedDepth"):
        assert is_depth(topic), topic
    for topic in ("/camera/rgb/image_color", "/depthai/rgb/image", "/cam/image_raw"):
        assert not is_depth(topic), topic
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = typestore()
    with Writer(tmp_path / "tum", version=9, storage_plugin=StoragePlugin.MCAP) as w:  # TUM RGB-D's topics, no messages
        for topic, mtype in (("/camera/rgb/image_color", image), ("/camera/rgb/camera_info", info),
                             ("/camera/depth/image", image), ("/camera/depth/camera_info", info),
                             ("/tf", "tf2_msgs/msg/TFMessage"), ("/imu", "sensor_msgs/msg/Imu")):
            w.add_connection(topic, mtype, typestore=ts)
    tum = BagReader(tmp_path / "tum")
    assert choose_topics(tum) == {"image": "/camera/rgb/image_color", "camera_info": "/camera/rgb/camera_info"}
    assert tum.warnings == ["image topic /camera/rgb/image_color taken, not the depth images on /camera/depth/image "
                            "(choose with --image-topic)"]
    realsense = {"/c/color/image_raw": image, "/c/color/image_raw/compressed": "sensor_msgs/msg/CompressedImage",
                 "/c/depth/image_rect_raw": image, "/c/aligned_depth_to_color/image_raw": image}
    assert pick_image(realsense, None) == ("/c/color/image_raw", "image topic /c/color/image_raw taken, not the same frames "
                                           "on /c/color/image_raw/compressed nor the depth images on "
                                           "/c/aligned_depth_to_color/image_raw, /c/depth/image_rect_raw (choose with "
                                           "--image-topic)")
    assert pick_image({"/c/depth/image_rect_raw": image}, None) == ("/c/depth/image_rect_raw", None)  # the only one
    with pytest.raises(BagError, match=r"several image topics \(/c/aligned_depth_to_color/image_raw, /c/color/image_raw, "
                                       r"/c/color/image_raw/compressed, /c/depth/image_rect_raw, /c/infra1/image_rect_raw\)"):
        pick_image({**realsense, "/c/infra1/image_rect_raw": image}, None)


def test_a_pose_topic_is_ground_truth_by_itself_only_when_its_name_says_so():
    """Motion-capture and simulator names are taken; a robot's other poses are not; two named ones ask for a choice,
    listing the whole bag."""
    from nmnet_ros.io.bag_truth import looks_like_ground_truth

    for topic in ("/ground_truth/pose", "/groundtruth", "/gt", "/robot/gt/odom", "/vicon/drone/drone", "/mocap/rb1/pose",
                  "/vrpn_mocap/robot/pose", "/optitrack/robot", "/leica/position"):
        assert looks_like_ground_truth(topic), topic
    for topic in ("/odom", "/goal_pose", "/amcl_pose", "/length/pose", "/target", "/camera/pose"):
        assert not looks_like_ground_truth(topic), topic
    pose, odom = "geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Odometry"
    assert pick_ground_truth({"/odom": odom, "/camera/image_raw": "sensor_msgs/msg/Image"}, None)[0] is None
    assert pick_ground_truth({"/odom": odom}, "/odom") == ("/odom", None)  # named: any pose topic
    with pytest.raises(BagError, match=r"several gt topics \(/ground_truth/odom, /ground_truth/pose\); choose one with "
                                       r"--gt-topic. Bag topics: /goal_pose \[geometry_msgs/msg/PoseStamped\], /ground"):
        pick_ground_truth({"/ground_truth/pose": pose, "/ground_truth/odom": odom, "/goal_pose": pose}, None)


def test_ground_truth_of_a_tracked_body_scores_the_camera_with_its_place_on_the_body(raw_bag, tmp_path):
    """A robot's bag: ground truth as nav_msgs/Odometry of base_link (x forward, z up) on /ground_truth/odom, beside
    wheel odometry on /odom and nav2's /goal_pose. The topic named as ground truth is taken, the others are named as
    not taken; --gt-camera (the camera's optical frame on the body) gives the scores of the camera's own poses, and
    without it the scores are those of the wrong frame."""
    from nmnet_ros.interface.posemsg import rot_to_quat

    ts = typestore()
    T, q = ts.types, rot_to_quat(np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]]))  # optical axes in base_link
    cam_in_body = np.eye(4)
    cam_in_body[:3, :3], cam_in_body[:3, 3] = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]]), [0.3, 0.0, 0.5]

    def odometry(header, pose: np.ndarray, child: str):
        rotation = rot_to_quat(pose[:3, :3])
        p = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](*pose[:3, 3]),
                                        orientation=T["geometry_msgs/msg/Quaternion"](*rotation))
        zero = T["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0)
        return T["nav_msgs/msg/Odometry"](header=header, child_frame_id=child,
                                          pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=p, covariance=np.zeros(36)),
                                          twist=T["geometry_msgs/msg/TwistWithCovariance"](
                                              twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
                                              covariance=np.zeros(36)))

    robot = tmp_path / "robot"
    with bag_copy(raw_bag, robot, leave_out=("/ground_truth/pose",)) as (r, w, conns, _):
        gt = w.add_connection("/ground_truth/odom", "nav_msgs/msg/Odometry", typestore=ts)
        wheels = w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
        goal = w.add_connection("/goal_pose", "geometry_msgs/msg/PoseStamped", typestore=ts)
        for c, t, raw in r.messages():
            if c.topic != "/ground_truth/pose":
                w.write(conns[c.id], t, raw)
                continue
            msg = ts.deserialize_cdr(raw, c.msgtype)
            body = pose_from_msg(msg) @ np.linalg.inv(cam_in_body)
            w.write(gt, t, ts.serialize_cdr(odometry(msg.header, body, "base_link"), "nav_msgs/msg/Odometry"))
            w.write(wheels, t, ts.serialize_cdr(odometry(msg.header, np.eye(4), "base_link"), "nav_msgs/msg/Odometry"))
            w.write(goal, t, ts.serialize_cdr(msg, c.msgtype))
    runs = {}
    place = " ".join(map(str, [0.3, 0.0, 0.5, *q]))
    for name, bag, extra in (("exact", raw_bag, []), ("body", robot, []), ("camera", robot, ["--gt-camera", place])):
        r, runs[name] = replay_json(bag, tmp_path, *extra, name=name)
        assert r.returncode == 0, r.stderr
        runs[name]["log"] = r.stdout
    keys = ("scored_pairs", "median_rot_deg", "median_trans_deg", "auc5", "auc10", "auc20")
    assert [runs["camera"][k] for k in keys] == pytest.approx([runs["exact"][k] for k in keys]), runs
    assert runs["body"]["scored_pairs"] == 5 and runs["body"]["median_trans_deg"] > 10 * runs["exact"]["median_trans_deg"]
    assert ("not taken as ground truth: /goal_pose [geometry_msgs/msg/PoseStamped], /odom [nav_msgs/msg/Odometry] (the name "
            "does not say so)") in runs["body"]["log"]
    r, _ = replay_json(robot, tmp_path, "--gt", str(data_dir("kitti-07") / "groundtruth.txt"), name="tum")
    assert r.returncode == 0 and "not taken as ground truth" not in r.stdout, r.stdout  # --gt decides: no topic is looked at
    r = nmnet("replay", str(robot), "--out", str(tmp_path / "none.mcap"), "--gt-camera", "0.3 0 0.5")
    assert r.returncode == 2 and "--gt-camera: '0.3 0 0.5': expected 'x y z qx qy qz qw'" in r.stderr, r.stderr
    r, live = replay_json(robot, tmp_path, "--live", "--rate", "0.3", "--gt-camera", place, name="live")  # as --live scores
    assert r.returncode == 0 and "not taken as ground truth: /goal_pose" in r.stdout, r.stdout + r.stderr
    assert live["scored_pairs"] >= 3 and live["median_trans_deg"] < 2 and live["median_rot_deg"] < 0.5, live


def two_camera_bag(src: Path, dst: Path) -> None:
    """``src`` with a second image topic, /camera2/image_raw, whose frames carry an encoding nobody can decode."""
    with bag_copy(src, dst) as (r, w, conns, ts):
        second = w.add_connection("/camera2/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        for c, t, raw in r.messages():
            w.write(conns[c.id], t, raw)
            if c.msgtype == "sensor_msgs/msg/Image":
                msg = ts.deserialize_cdr(raw, c.msgtype)
                msg.encoding = "bogus8"
                w.write(second, t, ts.serialize_cdr(msg, c.msgtype))


def test_the_image_topic_is_chosen_offline_and_live_and_a_bad_choice_stops_before_the_output(raw_bag, tmp_path):
    """A bag with two cameras: the replay asks which, --image-topic chooses (offline and, since this stop, --live: it
    was ignored there, so --live could not play such a bag); a topic the bag lacks, or one of another type, stops
    either mode before the output file is made, listing the bag's topics."""
    bag = tmp_path / "two_cameras"
    two_camera_bag(raw_bag, bag)
    image = next(t for t, m in BagReader(raw_bag).topics.items() if m == "sensor_msgs/msg/Image")
    for mode in ([], ["--live", "--rate", "0.5"]):
        out = tmp_path / "out.mcap"
        r = nmnet("replay", str(bag), "--out", str(out), "--no-progress", *mode)
        assert r.returncode == 2 and "several image topics (/camera/image_raw, /camera2/image_raw)" in r.stderr, (mode, r.stderr)
        for topic, error in (("/nope", "topic /nope not in the bag; it has: "),
                             ("/ground_truth/pose", "--image-topic /ground_truth/pose carries geometry_msgs/msg/PoseStamped")):
            r = nmnet("replay", str(bag), "--out", str(out), "--image-topic", topic, "--no-progress", *mode)
            assert r.returncode == 2 and error in r.stderr and "/camera2/image_raw [sensor_msgs/msg/Image]" in r.stderr, r.stderr
        assert not out.exists()
        r = nmnet("replay", str(bag), "--out", str(out), "--json", str(tmp_path / "s.json"), "--image-topic", image,
                  "--no-progress", *mode)
        assert r.returncode == 0, (mode, r.stderr)
        s = json.loads((tmp_path / "s.json").read_text())
        assert s["frames"] == 6 and s["processed"] == 6 and s["auc5"] > 80, (mode, s)
        out.unlink()


def camera_bag(src: Path, dst: Path, topics: dict[str, str]) -> None:
    """``src``'s frames and camera_info on each of ``topics`` (name -> Image, CompressedImage or CameraInfo), as a
    camera driver with image_transport (raw and /compressed) or a stereo pair records them."""
    import cv2
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer

    from nmnet_ros.interface.imgconv import image_to_array

    ts = typestore()
    with Reader(src) as r, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {t: w.add_connection(t, f"sensor_msgs/msg/{m}", typestore=ts) for t, m in topics.items()}
        for c, t, raw in r.messages():
            msg = ts.deserialize_cdr(raw, c.msgtype)
            kind = c.msgtype.rpartition("/")[2]
            for topic, m in topics.items():
                if m == kind:
                    w.write(conns[topic], t, raw)
                elif m == "CompressedImage" and kind == "Image":
                    img = image_to_array(msg.height, msg.width, msg.encoding, msg.step, msg.data)
                    jpeg = np.frombuffer(cv2.imencode(".jpg", img)[1].tobytes(), np.uint8)
                    out = ts.types["sensor_msgs/msg/CompressedImage"](header=msg.header, format="jpeg", data=jpeg)
                    w.write(conns[topic], t, ts.serialize_cdr(out, "sensor_msgs/msg/CompressedImage"))


def test_one_cameras_transports_and_a_stereo_pairs_camera_info_are_told_apart(raw_bag, tmp_path):
    """A driver with image_transport records each frame raw and on /compressed: the raw topic is taken, and said so
    (the replay asked to choose between the same frames). Of a stereo pair's two camera_info topics, the one beside
    the chosen image is taken, as image_transport pairs them (the replay asked for --info-topic too)."""
    mono = tmp_path / "mono"
    camera_bag(raw_bag, mono, {"/cam/image_raw": "Image", "/cam/image_raw/compressed": "CompressedImage",
                               "/cam/camera_info": "CameraInfo"})
    r, s = replay_json(mono, tmp_path)
    assert r.returncode == 0, r.stderr
    assert ("image topic /cam/image_raw taken, not the same frames on /cam/image_raw/compressed (choose with "
            "--image-topic)") in r.stdout and s["processed"] == 6, (r.stdout, s)
    stereo = tmp_path / "stereo"
    camera_bag(raw_bag, stereo, {"/left/image_raw": "Image", "/left/image_raw/compressed": "CompressedImage",
                                 "/left/camera_info": "CameraInfo", "/right/image_raw": "Image",
                                 "/right/camera_info": "CameraInfo"})
    reader = BagReader(stereo)
    with pytest.raises(BagError, match=r"several image topics \(/left/image_raw, /left/image_raw/compressed, /right/"):
        choose_topics(reader)
    for image, info in (("/right/image_raw", "/right/camera_info"), ("/left/image_raw/compressed", "/left/camera_info")):
        assert choose_topics(reader, image_topic=image)["camera_info"] == info
    assert choose_topics(reader, "/right/image_raw", "/left/camera_info")["camera_info"] == "/left/camera_info"
    from nmnet_ros.io.bags import camera_namespace

    assert [camera_namespace(t) for t in ("/left/image_raw/compressed", "/image_raw", "/a/b/image")] == ["/left", "", "/a/b"]
    r, s = replay_json(stereo, tmp_path, "--image-topic", "/right/image_raw", "--gt",
                       str(data_dir("kitti-07") / "groundtruth.txt"), name="right")
    assert r.returncode == 0 and s["processed"] == 6 and s["auc5"] > 80, (r.stderr, s)


def test_frames_resized_from_their_calibration_get_k_scaled(raw_bag, tmp_path):
    """A half-size stream with the full-size camera_info: K is scaled (and said so), and the poses stay right."""
    import cv2

    from nmnet_ros.interface.imgconv import array_to_image_fields, image_to_array

    def half(topic, msg):
        if msg.__class__.__name__.endswith("Image"):
            img = image_to_array(msg.height, msg.width, msg.encoding, msg.step, msg.data)
            f = array_to_image_fields(cv2.resize(img, (msg.width // 2, msg.height // 2), interpolation=cv2.INTER_AREA))
            f["data"] = np.frombuffer(f["data"], np.uint8)
            msg = type(msg)(header=msg.header, **f)
        return msg

    bag = tmp_path / "half"
    rewrite_bag(raw_bag, bag, half)
    r = nmnet("replay", str(bag), "--out", str(tmp_path / "o.mcap"), "--json", str(tmp_path / "s.json"), "--no-progress")
    assert r.returncode == 0, r.stderr
    assert "frames are 613x185 but camera_info describes 1226x370: K scaled by 0.5 to fit" in r.stdout + r.stderr
    s = json.loads((tmp_path / "s.json").read_text())
    # with the full-size K as is: translation 24 deg off, AUC@5 0 (measured); scaled: 0.3 deg, AUC@5 94
    assert s["processed"] == 6 and s["median_trans_deg"] < 2.0 and s["auc5"] > 80, s


def test_a_bag_without_camera_info_replays_with_a_calibration_file(raw_bag, tmp_path):
    bag = tmp_path / "nocal"
    rewrite_bag(raw_bag, bag, lambda topic, msg: None if topic.endswith("camera_info") else msg)
    r = nmnet("replay", str(bag), "--out", str(tmp_path / "a.mcap"), "--no-progress")
    assert "skipped, no camera_info yet (give the calibration with --camera)" in r.stdout + r.stderr
    yaml_file = data_dir("kitti-07") / "camera.yaml"
    for mode in ([], ["--live", "--rate", "0.5"]):
        name = "live" if mode else "offline"
        r = nmnet("replay", str(bag), "--camera", str(yaml_file), "--out", str(tmp_path / f"{name}.mcap"),
                  "--json", str(tmp_path / f"{name}.json"), "--no-progress", *mode)
        assert r.returncode == 0, r.stderr
        s = json.loads((tmp_path / f"{name}.json").read_text())
        assert s["processed"] == 6 and s["auc5"] > 80, (name, s)
    chain = tmp_path / "camchain.yaml"  # Kalibr's form of the same calibration; the camera on the bag's image topic
    chain.write_text("cam0: {camera_model: pinhole, intrinsics: [500.0, 500.0, 300.0, 200.0], distortion_model: radtan,\n"
                     "       distortion_coeffs: [0.1, 0.0, 0.0, 0.0], resolution: [1226, 370], rostopic: /other/image_raw}\n"
                     "cam1: {camera_model: pinhole, intrinsics: [707.0912, 707.0912, 601.8873, 183.1104],\n"
                     "       distortion_model: radtan, distortion_coeffs: [0.0, 0.0, 0.0, 0.0], resolution: [1226, 370],\n"
                     "       rostopic: /camera/image_raw}\n")
    r = nmnet("replay", str(bag), "--camera", str(chain), "--out", str(tmp_path / "chain.mcap"),
              "--json", str(tmp_path / "chain.json"), "--no-progress")
    assert r.returncode == 0, r.stderr
    keys = ("processed", "scored_pairs", "median_rot_deg", "median_trans_deg", "auc5")
    offline, chained = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("offline", "chain"))
    assert [chained[k] for k in keys] == pytest.approx([offline[k] for k in keys]), (chained, offline)
    bad = tmp_path / "camera.yaml"
    bad.write_text("camera_matrix: {data: [0, 0, 0, 0, 0, 0, 0, 0, 1]}\n")
    r = nmnet("replay", str(bag), "--camera", str(bad), "--out", str(tmp_path / "b.mcap"))
    assert r.returncode == 2 and f"{bad}: camera focal lengths must be positive" in r.stderr, r.stderr
    assert not (tmp_path / "b.mcap").exists()  # refused before the output file is made


def test_a_bag_of_rectified_frames_replays_with_the_projection_matrix(raw_bag, tmp_path):
    """--rectified: the camera is camera_info's P; its K and D (here a raw, distorted camera's) are not applied again."""
    def raw_calibration(topic, msg):
        if topic.endswith("camera_info"):
            msg.k = msg.k * np.array([0.9, 1, 0.9, 1, 0.9, 0.9, 1, 1, 1])  # fx, cx, fy, cy of another (raw) camera
            msg.d = np.array([-0.3, 0.1, 0.0, 0.0, 0.0])
        return msg

    bag = tmp_path / "rect"
    rewrite_bag(raw_bag, bag, raw_calibration)
    res = {}
    for flag in ([], ["--rectified"]):
        r = nmnet("replay", str(bag), "--out", str(tmp_path / f"o{len(flag)}.mcap"), "--json", str(tmp_path / "s.json"),
                  "--no-progress", *flag)
        assert r.returncode == 0, r.stderr
        res[bool(flag)] = json.loads((tmp_path / "s.json").read_text())
    print(res)
    assert res[True]["auc5"] > 80 > res[False]["auc5"]  # measured: 10 without the flag (translation 5 deg off)


def test_a_live_replay_plays_the_bags_transport_whatever_the_parameters_file_says(raw_bag, tmp_path):
    """A robot's parameters file with use_compressed: true (its camera sends JPEG) or qos: reliable made the live
    replay's node subscribe to a topic or QoS the player does not publish: 60 s of silence, then a traceback. The
    bag's transport wins; the file's other settings still apply, also from a namespaced camera's section (rcl gave
    those only to a node in that namespace, so the live node ran the defaults while the summary said the file's)."""
    params = tmp_path / "robot.yaml"
    params.write_text("/**:\n  ros__parameters:\n    use_compressed: true\n    qos: reliable\n"
                      "/robot/nmnet_node:\n  ros__parameters:\n    max_keypoints: 300\n    pose_estimator: classic\n")
    r, s = replay_json(raw_bag, tmp_path, "--live", "--params-file", str(params))
    assert r.returncode == 0, r.stderr
    assert s["processed"] >= 1 and s["parameters"]["max_keypoints"] == 300, s
    from rosbags.highlevel import AnyReader

    with AnyReader([tmp_path / "o.mcap"]) as reader:  # the node ran with the file's 300 keypoints
        widths = [reader.deserialize(raw, c.msgtype).width for c, _, raw in reader.messages() if c.topic.endswith("matches")]
    assert len(widths) == s["processed"] and 0 < max(widths) <= 300, widths


def test_a_ros_environment_without_a_way_to_talk_stops_a_live_replay_before_its_output(tmp_path):
    """ROS_DOMAIN_ID=abc (or 300) ended `nmnet replay --live` in rcl's traceback, after the output file was made;
    ROS_AUTOMATIC_DISCOVERY_RANGE=OFF in 60 s of silence, then "discovery failed, or the node is still starting",
    leaving an empty output; an RMW_IMPLEMENTATION the wheels lack in rcl's exit 102 on importing rclpy."""
    for name, value, says in [("ROS_DOMAIN_ID", domain, f"ROS_DOMAIN_ID='{domain}': a live replay runs on that domain, "
                               "and ROS takes a whole number") for domain in ("abc", "300", "-1")] + [
            ("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF", "ROS_AUTOMATIC_DISCOVERY_RANGE=OFF: a live replay's player and "
             "node are two processes that would never discover each other; unset it"),
            ("RMW_IMPLEMENTATION", "rmw_cyclonedds_cpp", "RMW_IMPLEMENTATION=rmw_cyclonedds_cpp: not installed; the ROS 2 "
             "wheels bring rmw_fastrtps_cpp only")]:
        r = subprocess.run([sys.executable, "-m", "nmnet_ros.tools.cli", "replay", str(SAMPLE_BAG), "--live", "--out",
                            str(tmp_path / "o.mcap")], capture_output=True, text=True, cwd=ROOT, timeout=120,
                           env={**{k: v for k, v in os.environ.items() if k != "AMENT_PREFIX_PATH"}, name: value})
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert says in r.stderr, r.stderr
        assert not (tmp_path / "o.mcap").exists()


def test_only_the_discovery_range_rcl_reads_as_off_is_refused(monkeypatch):
    """rcl takes ROS_AUTOMATIC_DISCOVERY_RANGE=OFF exactly; "off" or " OFF" it warns of and reads as LOCALHOST, where a
    live replay works: those are not refused."""
    from nmnet_ros.tools.live import check_ros_environment

    for value, refused in (("OFF", True), ("off", False), (" OFF", False), ("LOCALHOST", False), ("SUBNET", False)):
        monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", value)
        if refused:
            with pytest.raises(ValueError, match="ROS_AUTOMATIC_DISCOVERY_RANGE=OFF"):
                check_ros_environment()
        else:
            check_ros_environment()


def test_replay_runs_with_the_nodes_parameters_file(raw_bag, tmp_path):
    """--params-file: the settings the node runs (config/nmnet.yaml's form); an option given overrides the file;
    a name the node does not have is pointed out and ignored; a value the node would refuse stops the replay
    before anything is written, naming the file and the parameter."""
    params = tmp_path / "robot.yaml"
    params.write_text("/**:\n  ros__parameters:\n    max_keypoints: 300\n    max_keypoint: 9\n"
                      "nmnet_node:\n  ros__parameters:\n    min_matches: 100000\n")
    r = nmnet("replay", str(raw_bag), "--out", str(tmp_path / "a.mcap"), "--json", str(tmp_path / "a.json"),
              "--params-file", str(params), "--no-progress")
    assert r.returncode == 0, r.stderr
    assert f"warning: {params}: 'max_keypoint' is not an nmnet_node parameter: ignored" in r.stderr
    s = json.loads((tmp_path / "a.json").read_text())
    assert s["status"] == {"first_frame": 1, "too_few_matches": 5} and 0 < s["matches_per_frame"] <= 300, s
    assert s["parameters"]["max_keypoints"] == 300 and s["parameters"]["min_matches"] == 100000  # recorded in the summary
    params.write_text("/**:\n  ros__parameters:\n    max_keypoints: 300\n    pose_sigma_rotation_deg: 0.05\n")
    r = nmnet("replay", str(raw_bag), "--out", str(tmp_path / "b.mcap"), "--json", str(tmp_path / "b.json"),
              "--params-file", str(params), "--max-keypoints", "600", "--selector", "ratio+magsac", "--no-progress")
    assert r.returncode == 0, r.stderr
    s = json.loads((tmp_path / "b.json").read_text())
    assert 300 < s["matches_per_frame"] <= 600 and s["parameters"]["max_keypoints"] == 600
    assert s["parameters"]["pose_estimator"] == "classic"  # the node's name for --selector (former name) ratio+magsac
    from rosbags.highlevel import AnyReader

    from nmnet_ros.interface.posemsg import NO_ESTIMATE_VAR

    with AnyReader([tmp_path / "b.mcap"]) as reader:  # the recorded covariance has the file's rotation sigma
        covs = [reader.deserialize(raw, c.msgtype).pose.covariance.reshape(6, 6) for c, _, raw in reader.messages()
                if c.topic.endswith("relative_pose")]
    assert len(covs) == 6 and covs[0][0, 0] == NO_ESTIMATE_VAR  # the first frame: no estimate
    assert all(np.isclose(c[3, 3] / c[0, 0], np.radians(0.05) ** 2 / 0.05**2) for c in covs[1:])
    from nmnet_ros.tools.live import recording_summary  # the fitted sigmas, offline and from the file's covariances

    live = recording_summary(tmp_path / "b.mcap", bag_ground_truth(BagReader(raw_bag), "/ground_truth/pose"), (0.05, 0.05))[0]
    assert s[FITTED[0]] is not None and [live[k] for k in FITTED] == pytest.approx([s[k] for k in FITTED]), (live, s)
    assert (f"the published covariance would fit these errors with pose_sigma_rotation_deg {s[FITTED[0]]:.3g} and "
            f"pose_sigma_direction {s[FITTED[1]]:.3g}") in r.stdout, r.stdout  # said, as the JSON has it
    params.write_text("/**:\n  ros__parameters:\n    pose_threshold_px: 0.0\n")
    r = nmnet("replay", str(raw_bag), "--out", str(tmp_path / "c.mcap"), "--params-file", str(params))
    assert r.returncode == 2 and f"{params}: pose_threshold_px: 0.0 is out of range 0.05 .. 10.0" in r.stderr, r.stderr
    assert not (tmp_path / "c.mcap").exists()
    missing = tmp_path / "mine.pt"  # --weights reaches the network: a file that is not there is named
    for mode in ((), ("--live",)):  # refused before the output file is made (the live node would stop on it)
        r = nmnet("replay", str(raw_bag), "--out", str(tmp_path / "d.mcap"), "--weights", str(missing), "--no-progress",
                  *mode)
        assert r.returncode == 2 and f"{missing}: weights file not found" in r.stderr, (mode, r.stderr)
        assert not (tmp_path / "d.mcap").exists(), mode
    r = nmnet("replay", str(raw_bag), "--out", str(tmp_path / "e.mcap"), "--selector", "gms", "--live")  # not a node's
    said = "--pose-estimator gms: the node runs prosac, ratio_magsac, magsac, weighted8, classic"
    assert r.returncode == 2 and said in r.stderr, r.stderr
    assert not (tmp_path / "e.mcap").exists()

"""Feature tracks: ids follow a scene point through the selected matches, frame after frame."""

import numpy as np
import pytest

from nmnet_ros.core.tracks import NO_TRACK, continue_tracks, track_summary
from nmnet_ros.interface.imgconv import matches_of_cloud, matches_to_cloud_fields
from nmnet_ros.io.datasets import Sequence

from .conftest import data_dir


def test_a_match_passes_its_previous_keypoints_id_on_and_others_start_tracks():
    prev_ids = np.array([7, NO_TRACK, 9, NO_TRACK])
    idx = np.array([[0, 2], [1, 0], [2, 1]])  # keypoint 0 (track 7) -> 2, 1 (none) -> 0, 2 (track 9) -> 1
    cur, ids, nxt = continue_tracks(prev_ids, idx, np.ones(3), num_current=3, next_id=20)
    assert ids.tolist() == [7, 20, 9] and cur.tolist() == [20, 9, 7] and nxt == 21


def test_a_keypoint_two_matches_share_goes_to_the_better_one():
    """Nearest-neighbour selections can pair one keypoint twice: the better-scored match goes on with it, so ids stay
    unique within a message and the next frame follows one track per keypoint."""
    prev_ids = np.array([3, 4, 5])
    idx = np.array([[0, 1], [1, 1], [2, 0], [2, 2]])  # current 1 twice (tracks 3, 4); previous 2 (track 5) twice
    cur, ids, nxt = continue_tracks(prev_ids, idx, np.array([0.6, 0.9, 0.7, 0.8]), num_current=3, next_id=10)
    assert ids[1] == 4 and cur[1] == 4 and ids[0] not in (3, 4, 5)  # the 0.9 match won current keypoint 1
    assert ids[3] == 5 and cur[2] == 5  # the 0.8 match continues previous keypoint 2's track
    assert ids[2] not in (3, 4, 5) and cur[0] == ids[2]  # the 0.7 match starts a track at current keypoint 0
    assert len(set(ids.tolist())) == 4 and nxt == 12 and ids[0] not in cur  # the 0.6 match's id is used once
    assert continue_tracks(prev_ids, np.zeros((0, 2), int), np.zeros(0), 3, 5)[2] == 5  # nothing selected: no ids


def one_by_one(prev_ids: np.ndarray, idx: np.ndarray, scores: np.ndarray, num_current: int, next_id: int):
    """continue_tracks' rule written out as a loop over the matches, best first (the loop it was until stop 36)."""
    cur_ids, match_ids, used_prev = np.full(num_current, NO_TRACK, np.int64), np.empty(len(idx), np.int64), set()
    for m in np.argsort(-np.asarray(scores, np.float64), kind="stable"):
        i0, i1 = int(idx[m, 0]), int(idx[m, 1])
        if cur_ids[i1] != NO_TRACK:
            match_ids[m], next_id = next_id, next_id + 1
            continue
        if prev_ids[i0] == NO_TRACK or i0 in used_prev:
            match_ids[m], next_id = next_id, next_id + 1
        else:
            match_ids[m] = prev_ids[i0]
        used_prev.add(i0)
        cur_ids[i1] = match_ids[m]
    return cur_ids, match_ids, next_id


def test_the_array_form_gives_the_rule_match_by_match():
    """continue_tracks runs on whole arrays (0.06 ms for 600 matches instead of the loop's 0.39): on 2000 random
    frame pairs, with shared keypoints and tied scores, it gives what the rule gives one match at a time."""
    rng = np.random.default_rng(0)
    for trial in range(2000):
        n0, n1, m = rng.integers(1, 40), rng.integers(1, 40), rng.integers(0, 60)
        prev_ids = np.where(rng.random(n0) < 0.5, rng.integers(0, 1000, n0), NO_TRACK).astype(np.int64)
        idx = np.c_[rng.integers(0, n0, m), rng.integers(0, n1, m)]
        scores = rng.choice([0.2, 0.5, 0.9], m) if trial % 2 else rng.random(m)
        got, want = continue_tracks(prev_ids, idx, scores, n1, 2000), one_by_one(prev_ids, idx, scores, n1, 2000)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1]) and got[2] == want[2], trial


def test_the_matches_message_carries_the_ids_and_reads_back():
    k0, k1 = np.array([[1.5, 2.0], [3.0, 4.25]]), np.array([[5.0, 6.0], [7.0, 8.5]])
    f = matches_to_cloud_fields(k0, k1, np.array([0.9, 0.7]), np.array([12, 2**32 + 5]))
    assert [(n, o, d) for n, o, d in f["fields"]][-1] == ("track_id", 20, 6) and f["point_step"] == 24

    class Field:
        def __init__(self, name, offset, datatype):
            self.name, self.offset, self.datatype = name, offset, datatype

    back = matches_of_cloud(f["point_step"], [Field(*t) for t in f["fields"]], f["data"])
    assert back["u0"].tolist() == [1.5, 3.0] and back["v1"].tolist() == [6.0, 8.5]
    assert back["track_id"].tolist() == [12, 5]  # uint32: wraps
    assert np.allclose(back["score"], [0.9, 0.7])
    with pytest.raises(ValueError, match=r"not a ~/matches cloud: fields \['x'\]"):  # a float64 point cloud, say
        matches_of_cloud(24, [Field("x", 0, 8)], f["data"])


def test_tracks_follow_points_through_kitti_frames_and_restart_with_new_ids():
    """Six KITTI-07 frames through the front end: each pair's selected matches carry unique ids; a match whose
    previous keypoint was the current keypoint of a selected match the pair before carries that match's id (the
    keypoints are the same features, so their pixels are equal); most selected matches continue a track; tracks
    that continue are consistent with the ground-truth motion. After a reset no id comes back."""
    from nmnet_ros.core.geometry import essential_from_pose, sampson_distance
    from nmnet_ros.core.pipeline import Frontend

    seq = Sequence.load(data_dir("kitti-07"))
    fe = Frontend(seq.camera, {})
    before, seen, first_seen = None, set(), {}  # first_seen: track id -> (frame, pixel) where it starts
    for i in range(6):
        r = fe.process(seq.image(i), float(i))
        if i == 0:
            assert r.status == "first_frame"
            continue
        assert r.status == "ok"
        ids = r.track_ids[r.mask]
        assert len(np.unique(ids)) == len(ids) and (r.track_ids[~r.mask] == NO_TRACK).all()
        if before is not None:
            at = {tuple(k): t for k, t in zip(before[0], before[1], strict=True)}
            went_on = [(at[tuple(k)], t) for k, t in zip(r.k0[r.mask], ids, strict=True) if tuple(k) in at]
            print(f"frame {i}: {len(went_on)} of {len(ids)} selected matches continue a track")
            assert len(went_on) > 0.4 * len(ids) and all(a == b for a, b in went_on)
            assert r.tracks_continued == len(went_on)  # what /diagnostics reports
            assert not (set(ids.tolist()) - {a for a, _ in went_on}) & seen  # new tracks get new ids
        for k0, t in zip(r.k0[r.mask], ids, strict=True):
            first_seen.setdefault(int(t), (i - 1, k0))
        ends = [(first_seen[int(t)][1], k1) for k1, t in zip(r.k1[r.mask], ids, strict=True) if first_seen[int(t)][0] == i - 3]
        if ends:  # tracks over 3 frame steps: their ends satisfy the ground-truth epipolar geometry (pixels)
            E = essential_from_pose(*seq.relative_pose(i - 3, i))
            d = seq.camera.focal * sampson_distance(E, seq.camera.normalize(np.array([a for a, _ in ends])),
                                                    seq.camera.normalize(np.array([b for _, b in ends])))
            print(f"frame {i}: {len(ends)} tracks from frame {i - 3}, Sampson distance median {np.median(d):.2f} px")
            assert len(ends) > 50 and np.median(d) < 1.0
        before = (r.k1[r.mask], ids)
        seen |= set(ids.tolist())
    fe.reset()
    fe.process(seq.image(10), 10.0)
    r = fe.process(seq.image(11), 11.0)
    assert r.status == "ok" and not set(r.track_ids[r.mask].tolist()) & seen


def test_matches_within_px_publishes_the_pose_fits_candidates_near_the_pose_for_longer_tracks():
    """matches_within_px 0.5 with ratio_magsac: every match MAGSAC++ was given that lies within 0.5 px of the final
    pose is published, not only its inliers at pose_threshold_px (0.15 px): more matches and tracks seen in more
    frames, as consistent with the ground truth; the pose, and the count the covariance rests on (its inliers), are
    as with 0. With prosac (PoseLib's inliers within 1 px) and classic the same holds at 2 px and 0.5 px."""
    from nmnet_ros.core.geometry import essential_from_pose, sampson_distance
    from nmnet_ros.core.pipeline import Frontend

    seq = Sequence.load(data_dir("kitti-07"))
    runs = {}
    for px in (0.0, 0.5):
        fe, results = Frontend(seq.camera, {"pose_estimator": "ratio_magsac", "matches_within_px": px}), []
        for i in range(8):
            results.append(fe.process(seq.image(i), float(i)))
        runs[px] = results[1:]
    gt_px = []
    for i, (a, b) in enumerate(zip(runs[0.0], runs[0.5], strict=True), 1):
        assert a.status == b.status == "ok" and np.allclose(a.pose.R, b.pose.R) and np.allclose(a.pose.t, b.pose.t)
        assert a.pose_matches == b.pose_matches == a.num_selected and b.num_selected > 1.3 * a.num_selected
        assert np.mean(b.mask[a.mask]) > 0.99 and (b.scores[b.mask] > 0.5).all()  # the inliers stay, all NM-Net's
        E = essential_from_pose(*seq.relative_pose(i - 1, i))
        gt_px.append(seq.camera.focal * sampson_distance(E, seq.camera.normalize(b.k0[b.mask]),
                                                         seq.camera.normalize(b.k1[b.mask])))
    tracks = {px: track_summary(r.track_ids[r.mask] for r in rs) for px, rs in runs.items()}
    share = np.mean(np.concatenate(gt_px) < 1.0)
    print(f"published {sum(r.num_selected for r in runs[0.5])} against {sum(r.num_selected for r in runs[0.0])}; "
          f"{100 * share:.2f} % within 1 px of the ground truth; tracks {tracks}")
    assert share > 0.99 and tracks[0.5]["mean_frames"] > tracks[0.0]["mean_frames"] + 0.3
    classic = Frontend(seq.camera, {"pose_estimator": "classic", "matches_within_px": 0.5})  # no network: scores 1.0
    classic.process(seq.image(0), 0.0)
    r = classic.process(seq.image(1), 1.0)
    assert r.num_selected > r.pose_matches and (r.scores[r.mask] == 1.0).all() and (r.scores[~r.mask] == 0.0).all()
    inliers, near = (Frontend(seq.camera, {"pose_estimator": "prosac", "matches_within_px": px}) for px in (0.0, 2.0))
    a, b = ([fe.process(seq.image(i), float(i)) for i in (0, 1)][1] for fe in (inliers, near))
    assert a.status == b.status == "ok" and np.allclose(a.pose.R, b.pose.R) and np.allclose(a.pose.t, b.pose.t)
    assert a.pose_matches == b.pose_matches == a.num_selected < b.num_selected and b.mask[a.mask].all()


def test_a_streams_tracks_are_summed_up_by_length():
    """Track 1 in 3 messages (4 frames), track 2 in 1 (2 frames), track 3 in 5 (6 frames); no messages: zeros."""
    t = track_summary([np.array([1, 2, 3]), np.array([1, 3]), np.array([1, 3]), np.array([3]), np.array([3])])
    assert t == pytest.approx({"count": 3, "mean_frames": 4.0, "share_5_frames": 100 / 3, "longest": 6})
    assert track_summary([])["count"] == 0 and track_summary([np.zeros(0, np.int64)])["longest"] == 0


def test_a_long_streams_tracks_are_counted_as_they_come_as_a_full_count_would():
    """300 messages of tracks that go on, end and start at random: the running count (which holds only the last
    message's tracks) says what counting every id of every message says."""
    from nmnet_ros.core.tracks import TrackLengths

    rng, messages, live, next_id = np.random.default_rng(3), [], np.zeros(0, np.int64), 0
    for _ in range(300):
        kept = live[rng.random(len(live)) < 0.7]
        new = np.arange(next_id, next_id + rng.integers(0, 40))
        next_id += len(new)
        live = rng.permutation(np.concatenate([kept, new]))
        messages.append(live)
    seen: dict[int, int] = {}
    for ids in messages:
        for t in ids.tolist():
            seen[t] = seen.get(t, 0) + 1
    frames = np.array(list(seen.values())) + 1
    lengths = TrackLengths()
    for ids in messages:
        lengths.add(ids)
    assert lengths.summary() == pytest.approx({"count": len(frames), "mean_frames": frames.mean(),
                                               "share_5_frames": 100 * np.mean(frames >= 5), "longest": frames.max()})
    assert lengths.summary()["longest"] >= 10 and track_summary(messages) == lengths.summary()


def test_the_docs_back_end_snippet_collects_the_tracks_of_a_recording(tmp_path):
    """The docs' back-end code (docs/node.md), run as written on the ~/matches of a replay's output file: one entry per
    track, each with the frames it is seen in (its first message brings two), as the replay's summary counts them,
    every observation stamped (the first frame's message, empty, gives the stamp the next message relates to)."""
    import re

    from nmnet_ros.core.pipeline import Frontend
    from nmnet_ros.io.bags import BagReader
    from nmnet_ros.io.mcap_out import McapOutput

    from .conftest import ROOT

    block = re.search(r"### Reading the outputs in a back end.*?```python\n(.*?)```", (ROOT / "docs" / "node.md").read_text(),
                      re.S).group(1)
    seq = Sequence.load(data_dir("kitti-07"))
    fe, out, ids = Frontend(seq.camera, {}), McapOutput(tmp_path / "out.mcap"), []
    for i in range(8):  # as the node and the replay: a message for every frame, the first's empty
        r = fe.process(seq.image(i), float(i))
        out.write_result(r, 1.0 + i)
        ids.append(r.track_ids[r.mask])
    out.close()
    scope: dict = {}
    exec(block, scope)  # noqa: S102 - the docs' own code
    messages = [m.msg for m in BagReader(tmp_path / "out.mcap").messages({"/nmnet_node/matches"})]
    for msg in messages:
        scope["on_matches"](msg)
    seen = scope["observations"]
    expected = track_summary(ids)
    assert len(seen) == expected["count"] and max(len(v) for v in seen.values()) == expected["longest"]
    assert len(messages) == 8 and messages[0].width == 0
    for track in seen.values():  # one observation a frame, frame after frame, each stamped
        stamps = [s.sec + 1e-9 * s.nanosec for s, _, _ in track]
        assert stamps == [stamps[0] + k for k in range(len(track))] and stamps[0] >= 1.0

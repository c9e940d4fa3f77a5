"""Feature tracks: one id per scene point followed from frame to frame through the selected matches.

A VO/SLAM back end that optimises over several frames (a sliding window, bundle adjustment) needs to know that a
match of frame pair (t-1, t) and one of (t, t+1) observe the same point. Each frame's features are computed once, so
a keypoint of frame t is the current side of one pair and the previous side of the next: a selected match whose
previous keypoint carries an id passes it on to its current keypoint, any other selected match starts a new track.
Ids are handed out only to keypoints that are part of a selected match, in increasing order, so a camera at 30 Hz
starting ~200 tracks per frame takes days to run through the published uint32 (which then wraps).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

NO_TRACK = -1  # a keypoint that is in no selected match (yet)


def continue_tracks(prev_ids: np.ndarray, idx: np.ndarray, scores: np.ndarray, num_current: int,
                    next_id: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Track ids for one frame pair's selected matches.

    ``prev_ids``: the previous frame's id per keypoint (NO_TRACK where none); ``idx``: (M, 2) keypoint indices
    (previous, current) of the selected matches; ``scores``: their scores, which decide when two matches share a
    keypoint (the nearest-neighbour selections can pair one keypoint twice); ``num_current``: the current frame's
    keypoints; ``next_id``: the first unused id.

    Returns the current frame's ids per keypoint, one id per selected match (unique within the pair), and the next
    unused id. Of two matches sharing a current keypoint the better one goes on with it, the other gets an id used
    once; of two sharing a previous keypoint the better one continues its track, the other starts a new one.
    """
    order = np.argsort(-np.asarray(scores, np.float64), kind="stable")  # best first
    i0, i1 = np.asarray(idx, np.int64)[order].T.reshape(2, -1)
    keeps = _firsts(i1)  # the best match of each current keypoint goes on with it
    first_of_prev = np.flatnonzero(keeps)[_firsts(i0[keeps])]  # of those, the best of each previous keypoint
    starts = np.ones(len(order), bool)
    starts[first_of_prev] = prev_ids[i0[first_of_prev]] == NO_TRACK
    ids = prev_ids[i0].astype(np.int64)  # a copy
    ids[starts] = next_id + np.arange(int(starts.sum()))  # new ids in score order
    cur_ids = np.full(num_current, NO_TRACK, np.int64)
    cur_ids[i1[keeps]] = ids[keeps]
    match_ids = np.empty(len(order), np.int64)
    match_ids[order] = ids
    return cur_ids, match_ids, next_id + int(starts.sum())


def _firsts(a: np.ndarray) -> np.ndarray:
    """Whether each element is the first of its value in ``a``."""
    first = np.zeros(len(a), bool)
    first[np.unique(a, return_index=True)[1]] = True
    return first


class TrackLengths:
    """The lengths of the feature tracks of a stream of ``~/matches`` messages, counted as the messages come.

    A track goes on only from one message to the next (ids are never reused), so only the last message's tracks
    are held, and the finished ones are kept as a count per length: a replay of an hour-long bag holds a few
    hundred ids, not every track it ever saw.
    """

    def __init__(self) -> None:
        self._ids = np.zeros(0, np.int64)  # the last message's tracks
        self._seen = np.zeros(0, np.int64)  # in how many messages each of them is so far
        self._ended: dict[int, int] = {}  # messages a finished track is seen in -> how many tracks

    def add(self, ids: np.ndarray) -> None:
        """The next message's track ids (unique within a message, as the node's)."""
        ids = np.asarray(ids, np.int64)
        seen = np.ones(len(ids), np.int64)
        _, i_prev, i_cur = np.intersect1d(self._ids, ids, assume_unique=True, return_indices=True)
        seen[i_cur] += self._seen[i_prev]
        ended = np.ones(len(self._ids), bool)
        ended[i_prev] = False
        _count(self._ended, self._seen[ended])
        self._ids, self._seen = ids, seen

    def summary(self) -> dict:
        """``count``, ``mean_frames`` (the frames a track is seen in: its messages + 1), ``share_5_frames`` (percent
        of tracks seen in 5 frames or more) and ``longest``, the tracks still going counted as they stand; zeros for
        a stream without matches."""
        hist = _count(dict(self._ended), self._seen)
        count = sum(hist.values())
        if not count:
            return {"count": 0, "mean_frames": 0.0, "share_5_frames": 0.0, "longest": 0}
        return {"count": count, "mean_frames": sum((n + 1) * c for n, c in hist.items()) / count,
                "share_5_frames": 100 * sum(c for n, c in hist.items() if n + 1 >= 5) / count,
                "longest": max(hist) + 1}


def _count(hist: dict[int, int], seen: np.ndarray) -> dict[int, int]:
    """``hist`` (messages a track is seen in -> tracks) with the tracks of ``seen`` added."""
    for n, c in zip(*np.unique(seen, return_counts=True), strict=True):
        hist[int(n)] = hist.get(int(n), 0) + int(c)
    return hist


def track_summary(per_message: Iterable[np.ndarray]) -> dict:
    """:meth:`TrackLengths.summary` of a stream of ``~/matches`` messages, given each message's track ids."""
    lengths = TrackLengths()
    for ids in per_message:
        lengths.add(ids)
    return lengths.summary()

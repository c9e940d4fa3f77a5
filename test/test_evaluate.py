"""The paired bootstrap behind ``nmnet eval --reference``: differences with honest intervals."""

import numpy as np
import pytest

from nmnet_ros.core.geometry import pose_auc
from nmnet_ros.tools.evaluate import difference_lines, paired_auc_difference, per_sequence_table


def test_identical_methods_differ_by_nothing():
    e = np.random.default_rng(0).exponential(2.0, 100)
    assert paired_auc_difference(e, e.copy()) == (0.0, 0.0, 0.0)


def test_a_uniformly_better_method_has_an_interval_above_zero():
    ref = np.random.default_rng(1).exponential(2.0, 200)
    d, lo, hi = paired_auc_difference(ref / 2, ref)
    assert d == pytest.approx(100 * (pose_auc(ref / 2, (5.0,))[0] - pose_auc(ref, (5.0,))[0]))
    assert 0 < lo < d < hi


def test_a_difference_decided_by_one_pair_straddles_zero():
    ref = np.random.default_rng(2).exponential(1.0, 100)
    worse = ref.copy()
    worse[7] = 180.0  # one failure more, out of 100 pairs
    d, lo, hi = paired_auc_difference(worse, ref)
    assert d < 0 and lo < d and hi >= 0  # a third of the resamples miss that pair


def test_mismatched_pairs_are_refused():
    with pytest.raises(ValueError, match="same non-empty set of pairs"):
        paired_auc_difference(np.ones(5), np.ones(6))
    with pytest.raises(ValueError, match="same non-empty set of pairs"):
        paired_auc_difference(np.ones(0), np.ones(0))


def test_lines_name_every_other_method():
    e = {"a": np.ones(10), "ref": np.full(10, 2.0), "b": np.full(10, 3.0)}
    lines = difference_lines(e, "ref")
    assert lines[0].startswith("AUC@5 minus ref's, same 10 pairs")
    assert [ln.split(":")[0].strip() for ln in lines[1:]] == ["a", "b"]
    gain = 100 * (pose_auc(e["a"], (5.0,))[0] - pose_auc(e["ref"], (5.0,))[0])  # 1 deg against 2 deg everywhere
    assert gain > 15 and lines[1].split(":")[1].strip().startswith(f"{gain:+.1f} [{gain:+.1f}, {gain:+.1f}]")


def test_a_pairs_seeds_are_drawn_together():
    ref = np.random.default_rng(3).exponential(1.0, (50, 4))
    d, lo, hi = paired_auc_difference(ref.copy(), ref)
    assert (d, lo, hi) == (0.0, 0.0, 0.0)
    worse = ref.copy()
    worse[5, :] = 180.0  # one pair failed in every run: the interval still straddles zero (it is one pair)
    d, lo, hi = paired_auc_difference(worse, ref)
    assert d == pytest.approx(100 * (pose_auc(worse.ravel(), (5.0,))[0] - pose_auc(ref.ravel(), (5.0,))[0]))
    assert lo < d < 0 and hi >= 0
    with pytest.raises(ValueError, match="same non-empty set of pairs"):
        paired_auc_difference(ref, ref[:, :3])


def test_per_sequence_table_splits_the_pairs_by_sequence():
    rng = np.random.default_rng(4)
    ref = rng.exponential(1.0, 30)
    better = ref.copy()
    better[20:] /= 4  # better on the second sequence only
    groups = ["a:0-9"] * 20 + ["b"] * 10
    table = per_sequence_table({"ref": ref, "new": better}, groups, "ref").splitlines()
    assert table[0] == "| AUC@5 per sequence (pairs) | a:0-9 (20) | b (10) |"
    new = [c.strip() for c in table[3].strip("|").split("|")]
    assert new[0] == "new" and new[1].endswith("(+0.0 [+0.0, +0.0])")  # identical on the first sequence
    gain = 100 * (pose_auc(better[20:], (5.0,))[0] - pose_auc(ref[20:], (5.0,))[0])
    assert gain > 5 and new[2].startswith(f"{100 * pose_auc(better[20:], (5.0,))[0]:.1f} ({gain:+.1f} [")
    assert table[2] == f"| ref | {100 * pose_auc(ref[:20], (5.0,))[0]:.1f} | {100 * pose_auc(ref[20:], (5.0,))[0]:.1f} |"
    assert "(" not in per_sequence_table({"new": better}, groups, "ref").splitlines()[2]  # no reference: AUC only
    with pytest.raises(ValueError, match="29 sequence labels for 30 pairs"):
        per_sequence_table({"ref": ref}, groups[:-1])


def test_bins_give_each_methods_precision_and_recall_over_its_pairs_with_labels():
    """The hard pairs' selection quality (a selector's precision where few matches are inliers) was only in ad-hoc
    scripts; the bins carry each method's P/R/F over the runs on their pairs that have a labelled inlier."""
    from nmnet_ros.tools.evaluate import binned, group_table, mean_prf, prf_cell

    errors = {"a": np.ones((3, 2))}
    prfs = {"a": np.array([[[50, 100, 66.7]] * 2, [[100, 50, 66.7], [80, 50, 61.5]], [[np.nan] * 3] * 2])}
    rows = binned(errors, ["hard", "hard", "easy"], prfs=prfs)
    assert rows["hard"]["a"]["precision"] == pytest.approx((50 + 50 + 100 + 80) / 4)
    assert rows["hard"]["a"]["recall"] == pytest.approx(75)
    assert rows["easy"]["a"]["precision"] is None  # no labelled inlier there: undefined, not 0
    assert mean_prf(prfs["a"])["precision"] == rows["hard"]["a"]["precision"]
    assert group_table(rows, "P / R", prf_cell).splitlines()[2:] == ["| a | 70.0 / 75.0 | - |"]


def test_average_precision_rewards_an_order_that_puts_the_inliers_first():
    """The check a classifier for low-inlier pairs must pass (beat the ratio's order there) was a scratch script;
    the AP is the mean precision at each labelled inlier's rank, independent of any cut."""
    from nmnet_ros.core.metrics import average_precision

    labels = np.array([1, 0, 1, 0, 0], bool)
    assert average_precision(np.array([5, 4, 3, 2, 1.0]), labels) == pytest.approx(100 * (1 / 1 + 2 / 3) / 2)
    assert average_precision(np.array([5, 1, 4, 2, 3.0]), labels) == pytest.approx(100.0)  # inliers first
    assert average_precision(np.array([1, 5, 2, 4, 3.0]), labels) == pytest.approx(100 * (1 / 4 + 2 / 5) / 2)
    assert average_precision(np.zeros(5), labels) == pytest.approx(100 * (1 / 1 + 2 / 3) / 2)  # ties: given order
    assert np.isnan(average_precision(np.arange(3.0), np.zeros(3, bool)))  # no inlier: undefined, not 0
    with pytest.raises(ValueError, match="differ in shape"):
        average_precision(np.arange(3.0), labels)


def test_bins_give_each_ordered_methods_average_precision():
    from nmnet_ros.tools.evaluate import ap_cell, binned, group_table

    errors = {"net": np.ones(3), "fit": np.ones(3)}
    aps = {"net": np.array([40.0, 60.0, np.nan]), "fit": np.full(3, np.nan)}
    rows = binned(errors, ["hard", "hard", "easy"], aps=aps)
    assert rows["hard"]["net"]["ap"] == pytest.approx(50.0) and rows["easy"]["net"]["ap"] is None
    assert rows["hard"]["fit"]["ap"] is None  # a fit without an order has none
    assert group_table(rows, "AP", ap_cell, ["net"]).splitlines()[2:] == ["| net | 50.0 | - |"]

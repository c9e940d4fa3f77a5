"""`nmnet bench --pipeline` on three frames of the bundled sample bag: the JSON contract of issue 6 (numbers, not speed)."""

import pytest

from nmnet_ros.core.bf16 import native_bf16
from nmnet_ros.io.bags import BagReader, read_frames
from nmnet_ros.tools.bench import bench_pipeline
from nmnet_ros.tools.options import SAMPLE_BAG


@pytest.mark.slow
def test_pipeline_bench_reports_every_stage_and_the_baseline():
    it, _ = read_frames(BagReader(SAMPLE_BAG))
    frames = [f for _, f in zip(range(3), it, strict=False)]
    res = bench_pipeline([f.image for f in frames], frames[0].camera, sizes=(500,), reference=False)
    assert set(res) == {"640x480_N500", "native_N500"}
    for row in res.values():
        for stage in ("decode", "detect", "match", "neighbors", "nmnet", "pose", "total"):
            assert 0 < row[stage]["median"] <= row[stage]["p90"]
        assert ("match_float32" in row) == native_bf16()  # the float32 GEMM beside the screen, only where it screens
        if native_bf16():
            assert 0 < row["match_float32"]["median"] <= row["match_float32"]["p90"]
        assert row["end_to_end_hz"] > 0 and row["end_to_end_hz_match_stage2"] > 0
        if "end_to_end_hz_float32" in row:  # native bfloat16: float32 NM-Net and float32 matching beside it
            assert row["end_to_end_hz_float32"] > 0 and row["end_to_end_hz_match_float32"] > 0
        assert row["baseline_hz"] > 0 and row["sift_detect_ms"] > 0
        assert row["total"]["median"] >= row["detect"]["median"]


def test_bench_threads_option_sets_and_restores_the_thread_counts(capsys):
    """`nmnet bench --threads N` times the serial stages on N threads (1: one node stage's budget) and leaves
    the process as it was; a count below 1 is refused with the option named."""
    import cv2
    import torch

    from nmnet_ros.tools.bench import cpu_threads
    from nmnet_ros.tools.cli import main

    before = torch.get_num_threads(), cv2.getNumThreads()
    n = before[0] + 1  # differs from the counts before, so the restore is checked
    with cpu_threads(n):
        assert (torch.get_num_threads(), cv2.getNumThreads()) == (n, n)
    assert (torch.get_num_threads(), cv2.getNumThreads()) == before
    assert main(["bench", "--threads", "1", "--sizes", "200", "--repeat", "1"]) == 0
    assert "torch threads: 1" in capsys.readouterr().out
    assert (torch.get_num_threads(), cv2.getNumThreads()) == before
    with pytest.raises(SystemExit) as stop:
        main(["bench", "--threads", "0"])
    assert stop.value.code == 2 and "argument --threads: '0': expected a whole number >= 1" in capsys.readouterr().err


@pytest.mark.slow
def test_hd_bench_times_full_size_against_resize_width():
    """The high-resolution line: 1920x1080 frames at full size and downscaled by resize_width, detection and rate."""
    from nmnet_ros.tools.bench import bench_hd

    it, _ = read_frames(BagReader(SAMPLE_BAG))
    frames = [f for _, f in zip(range(3), it, strict=False)]
    hd = bench_hd([f.image for f in frames], frames[0].camera, n=500)
    assert hd["size"] == [1920, 1080] and hd["resize_width"] == 960
    assert hd["detect_ms_0"] > 0 and hd["detect_ms_960"] > 0  # numbers, not speed (the bench prints the ratio)
    assert hd["hz_0"] > 0 and hd["hz_960"] > 0

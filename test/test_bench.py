"""`nmnet bench --pipeline` on three frames of the bundled sample bag: the JSON contract of issue 6 (numbers, not speed)."""

from nmnet_ros.bags import BagReader, read_frames
from nmnet_ros.bench import bench_pipeline
from nmnet_ros.demo import SAMPLE_BAG


def test_pipeline_bench_reports_every_stage_and_the_baseline():
    it, _ = read_frames(BagReader(SAMPLE_BAG))
    frames = [f for _, f in zip(range(3), it, strict=False)]
    res = bench_pipeline([f.image for f in frames], frames[0].camera, sizes=(500,), reference=False)
    assert set(res) == {"640x480_N500", "native_N500"}
    for row in res.values():
        for stage in ("decode", "detect", "match", "neighbors", "nmnet", "pose", "total"):
            assert 0 < row[stage]["median"] <= row[stage]["p90"]
        assert row["end_to_end_hz"] > 0 and row["end_to_end_hz_match_stage2"] > 0
        assert row["baseline_hz"] > 0 and row["sift_detect_ms"] > 0
        assert row["total"]["median"] >= row["detect"]["median"]

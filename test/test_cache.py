"""The feature cache: each image file's features once, and again when the file changes."""

import os
import shutil

import numpy as np
import pytest

from nmnet_ros.core.detectors import make_detector
from nmnet_ros.io.cache import FeatureCache
from nmnet_ros.io.datasets import Sequence

from .conftest import data_dir


def test_a_changed_image_and_one_of_the_same_name_elsewhere_get_their_own_features(tmp_path):
    src = data_dir("strecha-fountain-p11")
    folder = tmp_path / "seq"
    (folder / "a").mkdir(parents=True)
    (folder / "b").mkdir()
    shutil.copy(src / "camera.yaml", folder / "camera.yaml")
    shutil.copy(src / "images" / "0000.jpg", folder / "a" / "0000.jpg")
    shutil.copy(src / "images" / "0001.jpg", folder / "b" / "0000.jpg")  # the same file name, another frame
    (folder / "images.txt").write_text("0.0 a/0000.jpg\n1.0 b/0000.jpg\n")
    detector = make_detector("sift")
    seq = Sequence.load(folder)

    def same(f, g) -> bool:
        return len(f) == len(g) and np.array_equal(f.keypoints, g.keypoints)

    first = [FeatureCache(detector, tmp_path / "cache")(seq, i) for i in (0, 1)]
    assert not same(*first) and all(same(f, detector(seq.image(i))) for i, f in enumerate(first))
    assert all(same(FeatureCache(detector, tmp_path / "cache")(seq, i), f) for i, f in enumerate(first))  # from disk
    # the first image replaced by another frame (as an edited or re-exported folder): detected again, not the old ones
    shutil.copy(src / "images" / "0002.jpg", seq.paths[0])
    os.utime(seq.paths[0], ns=(1, 10**18))
    again = FeatureCache(detector, tmp_path / "cache")(seq, 0)
    assert not same(again, first[0]) and same(again, detector(seq.image(0)))


def test_a_missing_image_is_named_by_the_cache_before_any_detection(tmp_path):
    from nmnet_ros.io.datasets import DatasetError

    folder = tmp_path / "seq"
    folder.mkdir()
    shutil.copy(data_dir("strecha-fountain-p11") / "camera.yaml", folder / "camera.yaml")
    (folder / "images.txt").write_text("0.0 gone.jpg\n")
    with pytest.raises(DatasetError, match=r"gone.jpg: cannot read image: No such file"):
        FeatureCache(make_detector("sift"), tmp_path / "cache")(Sequence.load(folder), 0)
    assert not (tmp_path / "cache").exists()


def test_a_cache_that_cannot_be_written_is_said_once_and_the_work_goes_on(tmp_path):
    """--cache naming a file (or NMNET_CACHE, or a read-only home) stopped eval and train with '[Errno 20] Not a
    directory' after the first frame's detection; the features are a cache: said once, computed without it."""
    from nmnet_ros.tools.cli import main

    (tmp_path / "afile").write_text("not a folder")
    seq = Sequence.load(data_dir("strecha-fountain-p11"))
    detector = make_detector("sift")
    cache = FeatureCache(detector, tmp_path / "afile")
    with pytest.warns(UserWarning, match=f"feature cache {tmp_path / 'afile'}: cannot write it .*give a writable folder"
                                         " with --cache or NMNET_CACHE") as said:
        f = [cache(seq, i) for i in (0, 1, 2)]
    assert len(said) == 1 and not cache.writable and np.array_equal(f[1].keypoints, detector(seq.image(1)).keypoints)
    assert (tmp_path / "afile").read_text() == "not a folder" and os.listdir(tmp_path) == ["afile"]
    with pytest.warns(UserWarning, match=f"feature cache {tmp_path / 'afile' / 'sub'}: cannot write it") as said:
        assert main(["eval", f"{seq.root}:0-2", "--gaps", "1", "--detector", "sift", "--methods", "ratio", "--cache",
                     str(tmp_path / "afile" / "sub"), "--json", str(tmp_path / "r.json")]) == 0
    assert len(said) == 1 and (tmp_path / "r.json").is_file()

"""Training smoke test: a few real steps on two pairs, checkpoint written, resumable, loadable."""

import argparse
import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from nmnet_ros.core.detectors import make_detector
from nmnet_ros.core.geometry import apply_homography, eight_point_rows, essential_from_pose, sym_epipolar_sq
from nmnet_ros.core.model import DEFAULT_CONFIG as MODEL_CONFIG
from nmnet_ros.core.model import load_model, weights_dir
from nmnet_ros.core.neighbors import mine_neighbors
from nmnet_ros.core.pipeline import DEFAULT_CONFIG as FRONTEND_DEFAULTS
from nmnet_ros.io.cache import FeatureCache
from nmnet_ros.io.pairs import load_pairs, shared_frames
from nmnet_ros.tools.options import evaluate as eval_args
from nmnet_ros.tools.options import neighbors as neighbors_args
from nmnet_ros.tools.options import train as train_args
from nmnet_ros.tools.train import (
    DEFAULT_CONFIG,
    MIN_THINNED_RATIO,
    balanced_bce,
    draw_augmentation,
    draw_sample,
    draw_turn,
    essential_loss,
    options_changed,
    pair_input,
    pair_weights,
    run_record,
    sample_correspondences,
    sample_essential,
    train,
    turn_camera,
)

from .conftest import data_dir


def test_balanced_bce_weights_positives():
    logits = torch.zeros(1, 4)
    labels = torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    # weight 3 on the one positive: mean of (3 + 1 + 1 + 1) * log 2 over 4
    assert balanced_bce(logits, labels).item() == np.float32(6 / 4 * np.log(2))


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on a machine without a GPU")
def test_cuda_without_a_gpu_is_a_clear_error(tmp_path):
    seq = str(data_dir("strecha-fountain-p11"))
    with pytest.raises(ValueError, match="no CUDA GPU.*--device cpu"):
        train([seq], [seq], tmp_path, {"device": "cuda"}, cache_dir=tmp_path / "cache")
    assert not any(tmp_path.iterdir())  # refused before any work


@pytest.mark.parametrize(("device", "said"), [("foo", "Expected one of cpu, cuda"), ("meta:x", "Invalid device string")])
def test_a_device_torch_cannot_use_is_a_clear_error(tmp_path, device, said):
    """--device with a name torch does not know ended in torch's traceback at the first tensor."""
    seq = str(data_dir("strecha-fountain-p11"))
    with pytest.raises(ValueError, match=f"^--device {device}: torch cannot use it \\({said}.*\\); use cpu or cuda"):
        train([seq], [seq], tmp_path, {"device": device}, cache_dir=tmp_path / "cache")
    assert not any(tmp_path.iterdir())  # refused before any work


@pytest.mark.parametrize("workers", [0, -2])
def test_workers_below_one_is_a_clear_error(tmp_path, workers):
    seq = str(data_dir("strecha-fountain-p11"))
    with pytest.raises(ValueError, match="--workers must be a whole number >= 1"):
        train([seq], [seq], tmp_path, {"workers": workers}, cache_dir=tmp_path / "cache")
    assert not any(tmp_path.iterdir())  # refused before any work


def test_train_few_steps_then_resume(tmp_path):
    seq = str(data_dir("strecha-fountain-p11"))
    cfg = {"epochs": 1, "steps_per_epoch": 2, "batch": 2, "num_corr": 128, "gaps": (1,), "max_val_pairs": 1,
           "workers": 2}  # the batch is mined in two threads
    spec_train, spec_val = [f"{seq}:0-1"], [f"{seq}:2-3"]  # one pair each
    said: list[str] = []
    s = train(spec_train, spec_val, tmp_path, cfg, resume=True, cache_dir=tmp_path / "cache", log=said.append)
    assert s["train_pairs"] == 1 and s["val_pairs"] == 1 and "does not exist yet, so this is a new run" in said[0]
    assert not any("warning" in line for line in said), said  # frames 0-1 and 2-3: validation apart from training
    for role, frames in (("train", "0-1"), ("val", "2-3")):  # the validation folder was "train: ..." too
        assert any(line.startswith(f"  {role}: strecha-fountain-p11:{frames}: 1 pairs, mean inlier ratio") and
                   "ready in" in line for line in said), said
    model = load_model(tmp_path / "best.pt")
    assert not model.training
    best = (tmp_path / "best.pt").read_bytes()
    with pytest.raises(ValueError, match=f"{tmp_path} holds a training run already .best.pt, last.pt.: add --resume"):
        train(spec_train, spec_val, tmp_path, cfg, cache_dir=tmp_path / "cache")  # run again, --resume forgotten
    assert (tmp_path / "best.pt").read_bytes() == best
    said.clear()
    s2 = train(spec_train, spec_val, tmp_path, {**cfg, "epochs": 2}, resume=True, cache_dir=tmp_path / "cache",
               log=said.append)
    hist = json.loads((tmp_path / "history.json").read_text())["epochs"]
    assert [h["epoch"] for h in hist] == [0, 1] and s2["best_val_f1_at_0.5"] >= s["best_val_f1_at_0.5"]
    assert not any("warning" in line for line in said), said  # more --epochs: what --resume is for
    assert any(line.startswith("resumed after epoch 1, best val F") for line in said), said  # it said epoch 0
    said.clear()  # other labels or validation frames: best.pt's F is then another measure, said
    train(spec_train, [f"{spec_val[0][:-4]}:2-4"], tmp_path, {**cfg, "epochs": 3, "label_threshold": 5e-5}, resume=True,
          cache_dir=tmp_path / "cache", log=said.append)
    assert [line for line in said if line.startswith("warning: resumed with other options")] == [
        f"warning: resumed with other options than the run was started with (label_threshold: 0.0001 -> 5e-05; val: "
        f"{spec_val} -> ['{spec_val[0][:-4]}:2-4']): best.pt is kept while validation F beats the run's best so far, "
        "which other --val, --label-threshold or --detector values make a different measure; start a new --out to "
        "compare them"], said
    assert 0 < s2["score_threshold"] < 1 and s2["val_f1"] >= s2["best_val_f1_at_0.5"] - 1e-9
    said.clear()  # a resume with no epoch left said only "resumed after epoch 2", then calibrated
    train(spec_train, [f"{spec_val[0][:-4]}:2-4"], tmp_path, {**cfg, "epochs": 3, "label_threshold": 5e-5}, resume=True,
          cache_dir=tmp_path / "cache", log=said.append)
    assert "--epochs 3: the run has done them all, so none is trained; give more to go on" in said, said
    assert len(json.loads((tmp_path / "history.json").read_text())["epochs"]) == 3


@pytest.mark.parametrize("tool, argv", [(train_args, ["--train", "a", "--val", "b", "--out", "c"]),
                                         (eval_args, ["seq"]), (neighbors_args, ["seq"])])
def test_tools_default_to_the_frames_the_front_end_runs(tool, argv):
    """Weights trained and scored with the defaults suit the node's defaults (kornia-trained
    weights cost 0.4 AUC@5 there); another detector is one flag away."""
    p = argparse.ArgumentParser()
    tool(p)
    assert p.parse_args(argv).detector == FRONTEND_DEFAULTS["detector"] == "hessian-affine-fast"
    assert p.parse_args(argv + ["--detector", "hessian-affine"]).detector == "hessian-affine"


def test_fine_tune_from_shipped_weights_on_the_fast_detector(tmp_path):
    seq = str(data_dir("strecha-fountain-p11"))
    cfg = {"epochs": 1, "steps_per_epoch": 1, "batch": 2, "num_corr": 128, "gaps": (1,), "max_val_pairs": 1,
           "lr": 0.0, "detector": "hessian-affine-fast", "init": str(weights_dir() / "nmnet.pt")}
    train([f"{seq}:0-1"], [f"{seq}:2-3"], tmp_path, cfg, cache_dir=tmp_path / "cache")
    shipped = dict(load_model().named_parameters())
    tuned = dict(load_model(tmp_path / "best.pt").named_parameters())
    assert all(torch.equal(shipped[k], tuned[k]) for k in shipped)  # lr 0: the parameters are the initial ones
    assert [p.name for p in (tmp_path / "cache").iterdir()] == [make_detector("hessian-affine-fast").cache_key]
    # resuming continues from last.pt: --init seeded the first start only (a missing file is not read again)
    train([f"{seq}:0-1"], [f"{seq}:2-3"], tmp_path, {**cfg, "epochs": 2, "init": str(tmp_path / "gone.pt")},
          resume=True, cache_dir=tmp_path / "cache")
    assert [h["epoch"] for h in json.loads((tmp_path / "history.json").read_text())["epochs"]] == [0, 1]


def test_stricter_label_threshold_keeps_a_subset_of_the_inliers(tmp_path):
    cache = FeatureCache(make_detector("hessian-affine-fast"), tmp_path)
    spec = [f"{data_dir('strecha-fountain-p11')}:0-2"]
    loose = load_pairs(spec, (1,), cache, min_inliers=5, log=lambda _: None)
    strict = load_pairs(spec, (1,), cache, min_inliers=5, log=lambda _: None, label_threshold=1e-5)
    for a, b in zip(loose, strict, strict=True):
        assert 0 < b.labels.sum() < a.labels.sum() and not (b.labels & ~a.labels).any()
    said: list[str] = []  # a pair with almost no inliers is dropped, and the count says so
    least = min(int(p.labels.sum()) for p in loose) + 1
    low = sum(int(p.labels.sum()) < least for p in loose)  # at least one
    kept = load_pairs(spec, (1,), cache, min_inliers=least, log=said.append, tool="train")
    assert len(kept) == len(loose) - low < len(loose) and all(p.labels.sum() >= least for p in kept)
    assert said[-1].startswith(f"train: strecha-fountain-p11:0-2: {len(kept)} pairs (of {len(loose)}; {low} with fewer "
                               f"than {least} inliers dropped), mean"), said


@pytest.mark.parametrize(("init", "match"), [("missing.pt", "--init .*missing.pt: weights file not found"),
                                             ("text.pt", "--init .*text.pt: cannot read weights: not a checkpoint written by `nmnet"),
                                             ("dict.pt", "--init .*dict.pt: not an NM-Net checkpoint"),
                                             ("nmnet-sp", "spatial neighbours; it does not fit this --variant")])
def test_init_that_does_not_fit_is_a_clear_error(tmp_path, init, match):
    seq = str(data_dir("strecha-fountain-p11"))
    path = weights_dir() / "nmnet-sp.pt" if init == "nmnet-sp" else tmp_path / init
    if init == "text.pt":
        path.write_text("not a checkpoint")
    elif init == "dict.pt":
        torch.save({"weights": torch.zeros(3)}, path)
    with pytest.raises(ValueError, match=match) as err:
        train([seq], [seq], tmp_path / "out", {"init": str(path)}, cache_dir=tmp_path / "cache")
    assert "weights_only" not in str(err.value)  # torch's advice to load it unsafely (any code in it would run)
    assert not (tmp_path / "out").exists()  # refused before any work


def test_a_file_among_the_folders_stops_the_run_before_any_features(tmp_path):
    """`nmnet train --train labelled/*` after a fleet's label run takes its report.json too: it was found out after
    the features of the folders before it (minutes each), and now before any."""
    seq = str(data_dir("strecha-fountain-p11"))
    report = tmp_path / "report.json"
    report.write_text("{}")
    with pytest.raises(ValueError, match=f"{report}: not a directory"):
        train([seq, str(report)], [seq], tmp_path / "out", cache_dir=tmp_path / "cache")
    assert not [p for p in (tmp_path / "cache").rglob("*") if p.is_file()]  # no feature computed
    assert not (tmp_path / "out").exists()


def test_a_run_stopped_with_ctrl_c_leaves_a_calibrated_best_pt(tmp_path):
    """Ctrl-C is how a long run is ended; its best.pt kept the uncalibrated cut 0.5, which the node and the tools
    then used without a word. Calibrated on the way out now (seconds), and the interrupt goes on to the CLI."""
    seq = str(data_dir("strecha-fountain-p11"))
    cfg = {"epochs": 3, "steps_per_epoch": 1, "batch": 2, "num_corr": 128, "gaps": (1,), "max_val_pairs": 1}
    said: list[str] = []

    def log(line: str, stop_at: str = "epoch 2/3") -> None:
        said.append(line)
        if line.startswith(stop_at):
            raise KeyboardInterrupt  # as Ctrl-C lands in that epoch
    with pytest.raises(KeyboardInterrupt):  # in the first epoch: no best.pt yet, nothing to calibrate
        train([f"{seq}:0-1"], [f"{seq}:2-3"], tmp_path / "first", cfg, cache_dir=tmp_path / "cache",
              log=lambda line: log(line, "epoch 1/3"))
    assert not (tmp_path / "first" / "best.pt").exists() and not any("calibrat" in line for line in said), said
    said.clear()
    with pytest.raises(KeyboardInterrupt):
        train([f"{seq}:0-1"], [f"{seq}:2-3"], tmp_path, cfg, cache_dir=tmp_path / "cache", log=log)
    ck = torch.load(tmp_path / "best.pt", map_location="cpu", weights_only=False)
    assert ck["epoch"] == 0 and 0 < ck["score_threshold"] < 1 and load_model(tmp_path / "best.pt").score_threshold == \
        ck["score_threshold"]
    assert said[-2].startswith("interrupted: calibrating best.pt") and said[-1].startswith("calibrated score threshold")
    assert not list(tmp_path.glob("*.tmp"))


def test_a_run_stopped_by_sigterm_is_calibrated_as_one_stopped_by_ctrl_c(tmp_path):
    """`timeout 300 nmnet train ...`, a job scheduler or `kill` end a run with SIGTERM, which killed it before the
    calibration: best.pt kept the uncalibrated cut 0.5. SIGTERM is taken as Ctrl-C: calibrated, exit 130."""
    import signal
    import subprocess
    import sys
    import time

    from .conftest import ROOT

    seq = str(data_dir("strecha-fountain-p11"))
    log = tmp_path / "log"
    with open(log, "w") as fh:
        proc = subprocess.Popen([sys.executable, "-m", "nmnet_ros.tools.cli", "train", "--train", f"{seq}:0-1", "--val", f"{seq}:2-3",
                                 "--out", str(tmp_path / "run"), "--epochs", "500", "--steps-per-epoch", "1", "--batch", "2",
                                 "--num-corr", "128", "--gaps", "1", "--max-val-pairs", "1", "--cache", str(tmp_path / "c")],
                                cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT, text=True)
        t_end = time.monotonic() + 300
        while "epoch 2/500" not in log.read_text() and time.monotonic() < t_end and proc.poll() is None:
            time.sleep(0.1)
        assert proc.poll() is None, log.read_text()
        proc.send_signal(signal.SIGTERM)
        proc.wait(120)
    said = log.read_text()
    assert proc.returncode == 130 and "interrupted: calibrating best.pt" in said and "Traceback" not in said, said
    assert 0 < torch.load(tmp_path / "run" / "best.pt", map_location="cpu", weights_only=False)["score_threshold"] < 1


def test_a_resume_compares_only_the_options_a_checkpoint_records():
    """last.pt written before it recorded the run's options resumes without the check (nothing to compare); a record
    says each changed option once, and not those a resume may change."""
    record = run_record({**DEFAULT_CONFIG, "gaps": (1, 2)}, ["a"], ["b"])
    assert options_changed({"epoch": 3, "best_f": 80.0}, record) == []
    changed = run_record({**DEFAULT_CONFIG, "gaps": (1,), "epochs": 99, "workers": 4}, ["a"], ["c"])
    assert options_changed(record, changed) == ["gaps: [1, 2] -> [1]", "val: ['b'] -> ['c']"]


def test_an_out_that_is_a_file_is_refused_before_any_features(tmp_path):
    """A file as --out failed with '[Errno 17] File exists' at the first checkpoint, after the features (minutes)."""
    seq = str(data_dir("strecha-fountain-p11"))
    afile = tmp_path / "afile"
    afile.write_text("a user's file")
    for out, said in ((afile, f"--out {afile} is a file: give a folder for the checkpoints"),
                      (afile / "run", f"--out {afile / 'run'}: {afile} is a file, not a folder")):
        with pytest.raises(ValueError, match=re.escape(said)):
            train([f"{seq}:0-1"], [f"{seq}:2-3"], out, {"gaps": (1,)}, cache_dir=tmp_path / "cache")
    assert not (tmp_path / "cache").exists() and afile.read_text() == "a user's file"


def test_validation_on_training_frames_is_warned_before_any_features():
    """--val overlapping --train (a folder given to both, ranges that meet) makes validation F, which picks best.pt,
    measure memory; it was not said. Said before the features are computed (minutes)."""
    kitti, herz = str(data_dir("kitti-07")), str(data_dir("strecha-herz-jesus-p25"))
    assert shared_frames([f"{kitti}:0-119", herz], [f"{kitti}:120-159", f"{herz}/"]) == ["strecha-herz-jesus-p25, every frame"]
    assert shared_frames([f"{kitti}:0-119"], [f"{kitti}:100-159", kitti]) == ["kitti-07 frames 100-119", "kitti-07 frames 0-119"]
    assert shared_frames([f"{kitti}:0-119"], [f"{kitti}:120-159", herz]) == []
    said: list[str] = []
    with pytest.raises(ValueError, match="weights file not found"):  # stops before features: the warning came first
        train([herz], [f"{herz}:20-24"], Path("unused"), {"init": "missing.pt"}, log=said.append)
    assert said == ["warning: --val takes --train's frames (strecha-herz-jesus-p25 frames 20-24): validation F, which "
                    "picks best.pt and the score threshold, then rewards memorising them; validate on other frames or "
                    "scenes (--train SEQ:0-119 --val SEQ:120-159)"]


@pytest.mark.parametrize(("key", "value", "match"), [("label_threshold", 0.0, "--label-threshold must be in"),
                                                     ("label_threshold", -1e-4, "--label-threshold must be in"),
                                                     ("label_threshold", 2.0, "--label-threshold must be in"),
                                                     ("thin_inliers", -0.1, "--thin-inliers is a probability in"),
                                                     ("thin_inliers", 1.5, "--thin-inliers is a probability in"),
                                                     ("turn_deg", -5.0, "--turn-deg must be in"),
                                                     ("turn_deg", 90.0, "--turn-deg must be in"),
                                                     ("balance", -0.5, "--balance must be in"),
                                                     ("balance", 1.5, "--balance must be in"),
                                                     ("max_view_angle", 0.0, "--max-view-angle must be in"),
                                                     ("max_view_angle", 200.0, "--max-view-angle must be in"),
                                                     ("ess_loss", -0.1, "--ess-loss is a weight >= 0"),
                                                     ("num_corr", 7, "--num-corr must be at least k = 8"),
                                                     ("lr", -1e-3, "--lr is Adam's step size, a number >= 0"),
                                                     ("lr", float("nan"), "--lr is Adam's step size, a number >= 0")])
def test_option_out_of_range_is_a_clear_error(tmp_path, key, value, match):
    seq = str(data_dir("strecha-fountain-p11"))
    with pytest.raises(ValueError, match=match):
        train([seq], [seq], tmp_path, {key: value}, cache_dir=tmp_path / "cache")
    assert not any(tmp_path.iterdir())  # refused before any work


def test_max_view_angle_admits_wider_training_pairs(tmp_path, cache):
    """train had no --max-view-angle: pairs more than 40 degrees apart (Herz-Jesus 0-8: 49) could not be trained on."""
    from nmnet_ros.tools.train import DEFAULT_CONFIG, _labelled_pairs

    spec = f"{data_dir('strecha-herz-jesus-p25')}:0-8"
    notes = []
    assert _labelled_pairs([spec], cache, {**DEFAULT_CONFIG, "gaps": (8,)}, notes.append) == []
    assert any("none of its" in n and "40" in n for n in notes), notes  # said why
    wide = _labelled_pairs([spec], cache, {**DEFAULT_CONFIG, "gaps": (8,), "max_view_angle": 60.0}, notes.append)
    assert [(p.i, p.j) for p in wide] == [(0, 8)]
    parser = argparse.ArgumentParser()
    train_args(parser)
    args = parser.parse_args(["--train", spec, "--val", spec, "--out", str(tmp_path), "--max-view-angle", "60"])
    assert args.max_view_angle == 60.0


def _fountain_pair(tmp_path):
    cache = FeatureCache(make_detector("hessian-affine-fast"), tmp_path)
    return load_pairs([f"{data_dir('strecha-fountain-p11')}:0-1"], (1,), cache, min_inliers=5, log=lambda _: None)[0]


def _plane_map(mirror: bool, roll: float) -> np.ndarray:
    """3x3 map of homogeneous normalised points: mirror in x, then roll (what the augmentation means)."""
    c, s = np.cos(roll), np.sin(roll)
    H = np.eye(3)
    H[:2, :2] = np.array([[c, -s], [s, c]]) @ np.diag([-1.0 if mirror else 1.0, 1.0])
    return H


def test_augmentation_keeps_the_labels(tmp_path):
    pair = _fountain_pair(tmp_path)
    E = essential_from_pose(pair.R, pair.t)
    x0, x1 = pair.normalized()
    d = sym_epipolar_sq(E, x0, x1)
    rng = np.random.default_rng(3)
    drawn = [draw_augmentation(rng) for _ in range(8)]
    assert {a[0] for a in drawn} == {False, True} and {a[1] for a in drawn} == {False, True}  # both kinds occur
    for aug in drawn:
        swap, mirror, roll0, roll1 = aug
        assert max(abs(roll0), abs(roll1)) <= np.radians(10.0)
        x, _ = pair_input(pair, MODEL_CONFIG, augmentation=aug)
        xa0, xa1 = x[0, :, :2].double().numpy(), x[0, :, 2:].double().numpy()
        # the augmented points satisfy the correspondingly mapped geometry with the same distances
        Es = E.T if swap else E
        Ea = _plane_map(mirror, roll1) @ Es @ _plane_map(mirror, roll0).T
        da = sym_epipolar_sq(Ea, xa0, xa1)
        np.testing.assert_allclose(da, d, rtol=1e-3, atol=1e-9)
        assert not np.allclose(xa0, x0, atol=1e-4)  # the input did change


def test_augmentation_mines_neighbours_on_the_augmented_frames(tmp_path):
    pair = _fountain_pair(tmp_path)
    _, nb = pair_input(pair, MODEL_CONFIG)
    _, nb_id = pair_input(pair, MODEL_CONFIG, augmentation=(False, False, 0.0, 0.0))
    _, nb_swap = pair_input(pair, MODEL_CONFIG, augmentation=(True, False, 0.0, 0.0))
    assert torch.equal(nb, nb_id)
    swapped = mine_neighbors("compatibility", pair.k1, pair.a1, pair.k0, pair.a0, 8)
    assert np.array_equal(nb_swap[0].numpy(), swapped) and not torch.equal(nb_swap, nb)


def test_turn_is_a_rotation_of_the_second_camera(tmp_path):
    pair = _fountain_pair(tmp_path)
    k1, a1, x1, labels, inside = turn_camera(pair, np.eye(3))
    np.testing.assert_allclose(k1, pair.k1, atol=1e-9)
    np.testing.assert_allclose(a1, pair.a1, atol=1e-9)
    assert np.array_equal(labels, pair.labels) and inside.all()

    turn = draw_turn(np.random.default_rng(1), 20.0)
    angle = np.degrees(np.arccos((np.trace(turn) - 1) / 2))
    assert 0 < angle <= 20.0 and abs(turn[2, 2] - np.cos(np.radians(angle))) < 1e-9  # the axis lies in the image plane
    k1, a1, x1, labels, inside = turn_camera(pair, turn)
    x0, x1_orig = pair.normalized()
    # the turned rays are the original ones rotated, and the turned pose's epipolar residual is the original's
    u = np.c_[x1_orig, np.ones(len(x1_orig))] @ turn.T
    np.testing.assert_allclose(x1, u[:, :2] / u[:, 2:], atol=1e-12)
    E, E_turned = essential_from_pose(pair.R, pair.t), essential_from_pose(turn @ pair.R, turn @ pair.t)
    r = np.sum(np.c_[x1_orig, np.ones(len(x0))] * (np.c_[x0, np.ones(len(x0))] @ E.T), 1)
    r_turned = np.sum(np.c_[x1, np.ones(len(x0))] * (np.c_[x0, np.ones(len(x0))] @ E_turned.T), 1)
    np.testing.assert_allclose(r_turned * u[:, 2], r, atol=1e-9)
    assert np.array_equal(labels, sym_epipolar_sq(E_turned, x0, x1) < 1e-4)
    assert 0.9 < (labels == pair.labels).mean() < 1.0  # relabelled, not copied: a few distances cross the threshold
    # the affine frames follow the rotation homography's local linear map (finite differences)
    K = pair.seq.camera.K
    H = K @ turn @ np.linalg.inv(K)
    eps = 1e-3
    for axis in range(2):
        d = np.zeros(2)
        d[axis] = eps
        np.testing.assert_allclose((apply_homography(H, pair.k1 + d)[0] - apply_homography(H, pair.k1 - d)[0]) / (2 * eps),
                                   (a1 @ np.linalg.inv(pair.a1))[:, :, axis], atol=1e-5)
    # matches turned out of the image are flagged; those kept lie inside it
    w, h = pair.seq.camera.width, pair.seq.camera.height
    assert 0.2 < inside.mean() < 1.0
    assert (k1[inside] >= 0).all() and (k1[inside, 0] < w).all() and (k1[inside, 1] < h).all()
    assert not ((k1[~inside] >= 0).all(1) & (k1[~inside, 0] < w) & (k1[~inside, 1] < h)).any()


def test_essential_loss_measures_the_weighted_eight_point_against_the_samples_true_geometry(tmp_path):
    """sample_essential follows every augmentation and turn; the loss is ~0 for the true inliers' weights."""
    pair = _fountain_pair(tmp_path)
    c = {"turn_deg": 25.0, "augment": True, "thin_inliers": 0.0, "num_corr": 500, "min_inliers": 5,
         "label_threshold": 1e-4}
    rng = np.random.default_rng(2)
    kinds, posed = set(), 0
    for _ in range(6):
        sel, aug, turned, labels = draw_sample(rng, pair, c)
        kinds.add((turned is not None, aug[0]))
        x, _ = pair_input(pair, MODEL_CONFIG, sel, aug, turned)
        E = sample_essential(pair, aug, turned)
        assert abs(np.linalg.norm(E) - 1) < 1e-9
        d = sym_epipolar_sq(E, x[0, :, :2].double().numpy(), x[0, :, 2:4].double().numpy())
        # the sample's labels are its distances under E (the input is float32: a 10 % margin at the threshold)
        assert (d[labels] < 1.1e-4).all() and (d[~labels] > 0.9e-4).all() and labels.any() and not labels.all()
        E_gt = torch.from_numpy(E[None])
        truth = torch.from_numpy(np.where(labels, 5.0, -5.0)[None]).float()
        # the true inliers' eight-point is the true E (up to sign) where it is well posed: not when the two
        # smallest eigenvalues nearly meet (a turn can leave inliers on a near-critical surface)
        X = eight_point_rows(*(x[0, labels, i].double() for i in range(4)), xp=torch)
        ev = torch.linalg.eigvalsh(X.T @ X)
        if ev[1] > 5 * ev[0]:
            posed += 1
            assert essential_loss(truth, x, E_gt) < 1e-2
        assert essential_loss(torch.full_like(truth, 3.0), x, E_gt) > 0.5  # every match alike: outliers pull it away
        # the sign of E does not matter, and the loss reaches the logits
        assert abs(essential_loss(truth, x, -E_gt) - essential_loss(truth, x, E_gt)) < 1e-6
        logits = torch.zeros_like(truth).normal_(0.5, 1.0).requires_grad_()
        essential_loss(logits, x, E_gt).backward()
        assert torch.isfinite(logits.grad).all() and logits.grad.abs().sum() > 0
    # a sample the network rejects almost entirely (< 8 positive weights) has no eight-point: left out, gradients finite
    logits = torch.stack([torch.full_like(truth[0], -2.0), truth[0]]).requires_grad_()
    logits.data[0, :5] = 2.0
    both = torch.cat([x, x]), torch.cat([E_gt, E_gt])
    loss = essential_loss(logits, *both)
    assert abs(loss - essential_loss(truth, x, E_gt)) < 1e-6
    loss.backward()
    assert torch.isfinite(logits.grad).all()
    assert essential_loss(torch.full_like(logits, -2.0), *both) == 0
    assert {k[1] for k in kinds} == {False, True} and any(k[0] for k in kinds) and posed >= 4  # swapped or not, turned


def test_turn_on_a_distorted_camera_is_a_clear_error(tmp_path):
    euroc, fountain = str(data_dir("euroc-v101-cam0")), str(data_dir("strecha-fountain-p11"))
    with pytest.raises(ValueError, match="--turn-deg: .*euroc-v101-cam0/camera.yaml has lens distortion"):
        train([fountain, euroc], [fountain], tmp_path / "out", {"turn_deg": 10.0}, cache_dir=tmp_path / "cache")
    assert not any(tmp_path.iterdir())  # refused before any work


@pytest.mark.parametrize(("key", "on", "off"), [("augment", True, False), ("thin_inliers", 1.0, 0.0),
                                                ("turn_deg", 25.0, 0.0), ("ess_loss", 1.0, 0.0)])
def test_training_option_is_seeded_and_changes_the_training(tmp_path, key, on, off):
    seq = str(data_dir("strecha-fountain-p11"))
    cfg = {"epochs": 1, "steps_per_epoch": 2, "batch": 2, "num_corr": 128, "gaps": (1,), "max_val_pairs": 1}
    spec_train, spec_val, cache = [f"{seq}:0-1"], [f"{seq}:2-3"], tmp_path / "cache"

    def loss(out: str, value) -> float:
        train(spec_train, spec_val, tmp_path / out, {**cfg, key: value}, cache_dir=cache)
        return json.loads((tmp_path / out / "history.json").read_text())["epochs"][0]["loss"]

    a, b = loss("a", on), loss("b", on)
    assert a == b and a != loss("plain", off)
    assert load_model(tmp_path / "a" / "best.pt").config["neighbors"] == "compatibility"


def test_sampling_without_thinning_is_the_plain_uniform_draw():
    labels = np.random.default_rng(0).random(2000) < 0.36
    a, b = np.random.default_rng(5), np.random.default_rng(5)
    for _ in range(5):  # the same stream as before --thin-inliers existed: earlier runs reproduce
        assert np.array_equal(sample_correspondences(a, labels, 1000), b.choice(2000, size=1000, replace=False))
    assert a.random() == b.random()


def test_thinning_lowers_the_inlier_ratio_with_real_outliers():
    labels = np.random.default_rng(0).random(2000) < 0.36
    rng = np.random.default_rng(1)
    ratios = []
    for _ in range(200):
        sel = sample_correspondences(rng, labels, 1000, thin=1.0)
        assert sel.shape == (1000,) and len(np.unique(sel)) == 1000  # no duplicates: 2000 to draw from
        ratios.append(labels[sel].mean())
    ratios = np.array(ratios)
    assert ratios.min() >= MIN_THINNED_RATIO - 1e-3 and ratios.max() <= labels.mean() + 1e-3
    assert ratios.min() < 0.08 and ratios.max() > 0.3  # spread over the whole range, not one value
    # at probability 1/2 about half the samples keep the pair's own ratio (within sampling noise)
    half = [labels[sample_correspondences(rng, labels, 1000, thin=0.5)].mean() for _ in range(400)]
    share = np.mean(np.abs(np.array(half) - labels.mean()) < 0.03)
    assert 0.4 < share < 0.75  # uniform draws near the pair's ratio add a little to the unthinned half


def test_a_sample_never_repeats_a_match_of_a_pair_that_has_enough():
    """A repeated match would be its own twin: a neighbour with zero compatibility error that no real
    pair has (the old sampler repeated negatives of high-inlier pairs and filled small turned views)."""
    labels = np.random.default_rng(3).random(2000) < 0.7  # 600 negatives; a thinned sample of 1000 wants up to 950
    rng = np.random.default_rng(4)
    ratios = []
    for _ in range(200):
        sel = sample_correspondences(rng, labels, 1000, thin=1.0)
        assert sel.shape == (1000,) and len(np.unique(sel)) == 1000
        ratios.append(labels[sel].mean())
    assert min(ratios) == pytest.approx(0.4, abs=0.01)  # as low as the pair's 600 negatives allow
    assert max(ratios) <= labels.mean() + 0.05


def test_a_turn_that_leaves_fewer_matches_in_view_than_a_sample_takes_is_not_used(tmp_path):
    pair = _fountain_pair(tmp_path)
    c = {"turn_deg": 60.0, "num_corr": len(pair.labels) - 50, "thin_inliers": 0.5, "augment": False,
         "label_threshold": 1e-4, "min_inliers": 5}
    rng = np.random.default_rng(0)
    turned = 0
    for _ in range(40):
        sel, _, turn, labels = draw_sample(rng, pair, c)
        assert len(sel) == c["num_corr"] and len(np.unique(sel)) == len(sel)
        turned += turn is not None
    small = {**c, "num_corr": 300}  # small samples: most turns keep 300 matches in view
    used = sum(draw_sample(rng, pair, small)[2] is not None for _ in range(40))
    print(f"turns used: {turned} / 40 at {c['num_corr']} matches per sample, {used} / 40 at 300")
    assert turned < used


def test_thinning_leaves_pairs_already_below_the_floor_alone():
    labels = np.zeros(500, bool)
    labels[:10] = True  # 2 %
    a, b = np.random.default_rng(2), np.random.default_rng(2)
    assert np.array_equal(sample_correspondences(a, labels, 300, thin=1.0), b.choice(500, size=300, replace=False))


def test_balance_shares_the_samples_between_folders():
    assert pair_weights([29, 26, 1145], 0.0) is None  # off: the plain uniform draw over pairs
    for balance, expected in [(1.0, [1 / 3, 1 / 3, 1 / 3]), (0.5, np.sqrt([29, 26, 1145]) / np.sqrt([29, 26, 1145]).sum())]:
        w = pair_weights([29, 26, 1145], balance)
        assert w.shape == (1200,) and np.isclose(w.sum(), 1.0)
        shares = [w[:29].sum(), w[29:55].sum(), w[55:].sum()]
        assert np.allclose(shares, expected)
        assert np.allclose(w[:29], w[0]) and np.allclose(w[55:], w[55])  # uniform within a folder
    assert np.allclose(pair_weights([4, 0, 12], 1.0), np.r_[np.full(4, 1 / 8), np.full(12, 1 / 24)])  # empty folder skipped


def test_balance_is_seeded_and_changes_the_batches(tmp_path):
    fountain, entry = str(data_dir("strecha-fountain-p11")), str(data_dir("strecha-entry-p10"))
    cfg = {"epochs": 1, "steps_per_epoch": 2, "batch": 2, "num_corr": 128, "gaps": (1,), "max_val_pairs": 1}
    spec_train, spec_val, cache = [f"{fountain}:0-4", f"{entry}:0-1"], [f"{fountain}:5-6"], tmp_path / "cache"

    def loss(out: str, balance: float) -> float:
        train(spec_train, spec_val, tmp_path / out, {**cfg, "balance": balance}, cache_dir=cache)
        return json.loads((tmp_path / out / "history.json").read_text())["epochs"][0]["loss"]

    a, b = loss("a", 1.0), loss("b", 1.0)
    assert a == b and a != loss("plain", 0.0)


def test_a_folder_whose_pairs_all_lack_motion_says_why_it_gives_none(tmp_path):
    """EuRoC's excerpt (the MAV still on the ground) gave '0 pairs (of 0)' and then 'no training pairs', no reason."""
    said: list[str] = []
    euroc = str(data_dir("euroc-v101-cam0"))
    assert load_pairs([euroc], (1, 2), FeatureCache(make_detector("sift"), tmp_path), min_inliers=5, skip_empty=True,
                      log=said.append) == []
    assert said[0] == (f"warning: {euroc}: none of its 187 frame pairs (gaps 1,2) has a ground-truth pose on both "
                       "frames, motion between them (epipolar labels need a baseline) and views within 40 degrees")
    assert not any(tmp_path.iterdir())  # no features computed for it


@pytest.mark.parametrize("balance", [0.0, 1.0])
def test_no_training_pairs_is_a_clear_error(tmp_path, balance):
    seq = str(data_dir("strecha-fountain-p11"))
    said: list[str] = []
    with pytest.raises(ValueError, match="no training pairs: check the sequence folders and frame ranges"):
        train([f"{seq}:0-0"], [f"{seq}:1-2"], tmp_path / "out", {"balance": balance, "gaps": (1,)},
              cache_dir=tmp_path / "cache", log=said.append)
    assert not (tmp_path / "out").exists()
    assert "loading validation pairs" not in said and not (tmp_path / "cache").exists(), said  # no features for --val


def test_no_validation_pairs_is_a_clear_error_before_training(tmp_path):
    """--val without pairs (EuRoC's standing excerpt) trained an epoch on 'val F nan', then failed with
    '[Errno 2] No such file or directory: best.pt'."""
    seq, euroc = str(data_dir("strecha-fountain-p11")), str(data_dir("euroc-v101-cam0"))
    said: list[str] = []
    with pytest.raises(ValueError, match=r"no validation pairs: check the --val folders and frame ranges"):
        train([f"{seq}:0-2"], [euroc], tmp_path / "out", {"gaps": (1,), "detector": "sift"}, cache_dir=tmp_path / "cache",
              log=said.append)
    assert not (tmp_path / "out").exists() and any("none of its 94 frame pairs" in line for line in said), said


def test_ratio_input_fine_tune_starts_as_the_checkpoint_and_is_kept(tmp_path):
    """--ratio-input from weights trained without it: a zero column, so the same logits at the start."""
    from nmnet_ros.core.selectors import build
    from nmnet_ros.io.pairs import to_correspondences
    from nmnet_ros.tools.train import _init_model

    pair = _fountain_pair(tmp_path)
    shipped = load_model()
    wide = _init_model(weights_dir() / "nmnet.pt", "compatibility", True)
    assert wide.config["ratio_input"] and wide.score_threshold == shipped.score_threshold
    x4, nb = pair_input(pair, shipped.config)
    x5, nb5 = pair_input(pair, wide.config)
    assert x5.shape[-1] == 5 and torch.equal(nb, nb5) and np.allclose(x5[0, :, 4].numpy(), pair.matches.ratio)
    with torch.inference_mode():
        torch.testing.assert_close(wide(x5, nb), shipped(x4, nb), atol=1e-5, rtol=0)
    seq = str(data_dir("strecha-fountain-p11"))
    cfg = {"epochs": 1, "steps_per_epoch": 1, "batch": 2, "num_corr": 128, "gaps": (1,), "max_val_pairs": 1,
           "init": str(weights_dir() / "nmnet.pt"), "ratio_input": True}
    train([f"{seq}:0-1"], [f"{seq}:2-3"], tmp_path / "run", cfg, cache_dir=tmp_path / "cache")
    assert load_model(tmp_path / "run" / "best.pt").config["ratio_input"]
    # the selectors (the front end's, eval's) feed such weights each match's own ratio: their scores are the network's
    # on pair_input's rows, and not those on another ratio (the ratio column is made to matter first)
    ck = torch.load(tmp_path / "run" / "best.pt", weights_only=False)
    ck["state_dict"]["embed.0.weight"][..., 4] = torch.linspace(-1.0, 1.0, ck["state_dict"]["embed.0.weight"].shape[0])[:, None, None]
    torch.save(ck, tmp_path / "ratio.pt")
    model = load_model(tmp_path / "ratio.pt")
    x5, nb = pair_input(pair, model.config)
    with torch.inference_mode():
        expected = torch.sigmoid(model(x5, nb))[0].numpy()
        x5[..., 4] = 1.0 - x5[..., 4]
        other = torch.sigmoid(model(x5, nb))[0].numpy()
    sel = build("nmnet", {"nmnet_precision": "float32"}, {"nmnet": str(tmp_path / "ratio.pt")})
    scores = sel(to_correspondences(pair)).scores
    np.testing.assert_allclose(scores, expected, atol=1e-4)
    assert np.abs(other - expected).max() > 0.1
    with pytest.raises(ValueError, match="trained with the ratio as an input; add --ratio-input"):
        train([seq], [seq], tmp_path / "out", {"init": str(tmp_path / "run" / "best.pt")}, cache_dir=tmp_path / "cache")
    with pytest.raises(ValueError, match="--resume: .*last.pt does not fit this run's network; resume with the options"):
        train([seq], [seq], tmp_path / "run", {**cfg, "ratio_input": False, "epochs": 2}, resume=True,
              cache_dir=tmp_path / "cache")

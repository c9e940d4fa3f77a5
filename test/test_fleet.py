"""``nmnet replay`` over many recordings on Ray: a real Ray head and worker on localhost, real bags, real kills."""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from nmnet_ros.tools import fleet

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "nmnet_ros" / "sample" / "kitti07_120-159"
BIN = Path(sys.executable).parent
TIMING = ("fps",)  # the only summary numbers that depend on the machine's load


def _copies(folder: Path, n: int) -> list[Path]:
    """``n`` copies of the sample bag, the last ``truncated`` (cut inside its messages)."""
    out = []
    for i in range(n):
        dst = folder / f"drive{i}"
        shutil.copytree(SAMPLE, dst)
        out.append(dst)
    cut = folder / "truncated"
    shutil.copytree(SAMPLE, cut)
    mcap = next(cut.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[: 3_000_000])
    return [*out, cut]


def _nmnet(*args: str, env: dict | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([str(BIN / "nmnet"), *args], capture_output=True, text=True, env=env, timeout=timeout)


def _comparable(summary: dict) -> dict:
    return {k: v for k, v in summary.items() if k not in TIMING and k != "written_by"}


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> list[Path]:
    return _copies(tmp_path_factory.mktemp("fleet"), 3)


@pytest.fixture(scope="module")
def serial(bags, tmp_path_factory) -> dict[str, dict]:
    """Each recording replayed alone, as a shell loop would: the results a fleet run must reproduce."""
    out = tmp_path_factory.mktemp("serial")
    results = {}
    for bag in bags:
        r = _nmnet("replay", str(bag), "--out", str(out / f"{bag.name}.mcap"), "--json", str(out / f"{bag.name}.json"),
                   "--no-progress")
        assert r.returncode == 0, r.stderr
        results[bag.name] = json.loads((out / f"{bag.name}.json").read_text())
    return results


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A Ray head (no CPUs of its own) and one worker node with one CPU, on localhost, token-authenticated as Ray's
    local clusters are: the address and the environment a client needs."""
    env = {**os.environ, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32), "RAY_USAGE_STATS_ENABLED": "0"}
    port = _free_port()
    ray = str(BIN / "ray")
    common = ("--node-ip-address", "127.0.0.1", "--disable-usage-stats")
    head = subprocess.run([ray, "start", "--head", "--port", str(port), "--num-cpus", "0", "--include-dashboard", "false",
                           *common],
                          capture_output=True, text=True, env=env, timeout=180)
    assert head.returncode == 0, head.stderr
    try:
        worker = subprocess.run([ray, "start", "--address", f"127.0.0.1:{port}", "--num-cpus", "1", *common],
                                capture_output=True, text=True, env=env, timeout=180)
        assert worker.returncode == 0, worker.stderr
        yield f"127.0.0.1:{port}", env
    finally:
        subprocess.run([ray, "stop", "--force"], capture_output=True, env=env, timeout=120)


def _worker_pids(task: str = "run_one") -> list[int]:
    """The Ray worker processes running ``task`` now (Ray names a busy worker's process ``ray::TASK``)."""
    pids = []
    for proc in Path("/proc").iterdir():
        try:
            if proc.name.isdigit() and (proc / "cmdline").read_bytes().startswith(f"ray::{task}".encode()):
                pids.append(int(proc.name))
        except OSError:
            continue
    return pids


@pytest.mark.slow
def test_a_cluster_replays_every_recording_as_a_serial_replay_does_and_reports_the_truncated_one(
        bags, serial, cluster, tmp_path):
    address, env = cluster
    run = tmp_path / "run"
    r = _nmnet("replay", *map(str, bags), "--out", str(run), "--ray-address", address, "--no-progress", env=env)
    assert r.returncode == 0, r.stdout + r.stderr
    for bag in bags:
        summary = json.loads((run / bag.name / "summary.json").read_text())
        assert _comparable(summary) == _comparable(serial[bag.name]), bag.name
        assert {p.name for p in (run / bag.name).iterdir()} >= {"nmnet.mcap", "summary.json", "replay.log", "errors.png"}
    report = json.loads((run / "report.json").read_text())
    rows = {row["name"]: row for row in report["recordings"]}
    assert [row["name"] for row in report["recordings"]] == [b.name for b in bags]  # the order given
    assert all(row["status"] == "ok" for row in rows.values())
    assert any("truncated" in w for w in rows["truncated"]["recording_warnings"])  # said, and in the table
    said = rows["truncated"]["recording_warnings"]  # once, though the bag is read twice (truth, frames)
    assert sum("truncated" in w for w in said) == 1, said
    assert [w for w in said if "truncated" not in w] == [  # the cut took the last frame's ground truth
        "the ground truth has no pose for 1 of 22 frames (its poses are the frames' own, and these have none; at "
        "14.665 s): the pairs with them are not scored"], said
    assert "truncated" in (run / "report.md").read_text().split("| truncated |")[1].splitlines()[0]
    assert rows["drive0"]["frames"] == 40 and rows["truncated"]["frames"] < 40
    for key in ("fitted_pose_sigma_rotation_deg", "fitted_pose_sigma_direction"):  # the bags carry ground truth
        assert rows["drive0"][key] == serial["drive0"][key] > 0, key
    assert report["totals"]["processed"] == sum(s["processed"] for s in serial.values())
    assert not list(run.glob(".partial-*"))

    again = _nmnet("replay", *map(str, bags), "--out", str(run), "--ray-address", "127.0.0.1:1", env=env)  # no Ray
    assert again.returncode == 0, again.stderr  # every recording complete: skipped, no cluster needed
    assert f"{len(bags)} of {len(bags)} recordings complete" in again.stdout
    assert all(row.get("skipped") for row in json.loads((run / "report.json").read_text())["recordings"])


@pytest.mark.slow
def test_a_worker_killed_mid_recording_is_retried_and_every_result_comes(bags, serial, cluster, tmp_path):
    address, env = cluster
    run = tmp_path / "run"
    clean = bags[:3]
    proc = subprocess.Popen([str(BIN / "nmnet"), "replay", *map(str, clean), "--out", str(run), "--ray-address",
                             address, "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    killed = []
    deadline = time.monotonic() + 300
    while not killed and time.monotonic() < deadline and proc.poll() is None:
        if list(run.glob(".partial-*")) and _worker_pids():  # a recording is being written
            time.sleep(1.0)
            for pid in _worker_pids():
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
        time.sleep(0.2)
    out, _ = proc.communicate(timeout=600)
    assert killed, "no worker was seen running a recording"
    assert proc.returncode == 0, out
    for bag in clean:
        assert _comparable(json.loads((run / bag.name / "summary.json").read_text())) == _comparable(serial[bag.name])
    assert not list(run.glob(".partial-*"))  # the killed attempt's half-made folder is gone


@pytest.mark.slow
def test_the_local_runtime_reports_a_failed_recording_without_stopping_the_others(bags, tmp_path):
    """No address: Ray starts on this machine. A recording that cannot be read is a failed row; the others
    complete."""
    empty = tmp_path / "empty"
    empty.mkdir()
    run = tmp_path / "run"
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    r = _nmnet("replay", str(bags[0]), str(empty), "--out", str(run), "--no-progress", env=env)
    assert r.returncode == 1, r.stdout + r.stderr  # some failed
    rows = {row["name"]: row for row in json.loads((run / "report.json").read_text())["recordings"]}
    assert rows["drive0"]["status"] == "ok" and (run / "drive0" / "nmnet.mcap").is_file()
    assert rows["empty"]["status"] == "failed" and "holds no .mcap" in rows["empty"]["error"]
    assert "failed: empty" in r.stderr and (run / "empty.failed.log").is_file() and not (run / "empty").exists()



@pytest.mark.slow
def test_ctrl_c_keeps_the_finished_recordings_whole_and_reports_the_rest(bags, cluster, tmp_path):
    address, env = cluster  # one worker with one CPU: one recording at a time
    run2 = tmp_path / "run"
    proc = subprocess.Popen([str(BIN / "nmnet"), "replay", *map(str, bags), "--out", str(run2), "--no-progress",
                             "--ray-address", address],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # as at a terminal
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None and not any(
            (run2 / b.name / "summary.json").is_file() for b in bags):
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=300)
    report = json.loads((run2 / "report.json").read_text())
    finished = [row["name"] for row in report["recordings"] if row["status"] == "ok"]
    assert finished, out
    for name in finished:  # whole: what a complete replay writes
        assert json.loads((run2 / name / "summary.json").read_text())["frames"] > 0
    assert proc.returncode == 130, out  # one at a time: the last of four recordings has not started yet
    assert any(row["status"] == "interrupted" for row in report["recordings"])
    assert not list(run2.glob(".partial-*"))


def test_recordings_come_from_paths_globs_and_a_manifest_each_once(tmp_path):
    for name in ("a.mcap", "b.mcap", "c.db3"):
        (tmp_path / name).write_bytes(b"")
    manifest = tmp_path / "list.txt"
    manifest.write_text("# the fleet\nb.mcap\n\n*.db3\n")
    got = fleet.recordings([str(tmp_path / "*.mcap")], manifest)
    assert [p.name for p in got] == ["a.mcap", "b.mcap", "c.db3"]  # b.mcap once, at its first place
    with pytest.raises(ValueError, match="matches no recording"):
        fleet.recordings([str(tmp_path / "*.bag")], None)
    (tmp_path / "none.txt").write_text("# nothing\n")
    with pytest.raises(ValueError, match="lists no recording"):
        fleet.recordings([], tmp_path / "none.txt")


def test_recordings_of_the_same_name_get_folders_of_their_own():
    assert fleet.names_of([Path("x/run.mcap"), Path("y/run.mcap"), Path("z/run"), Path("w/other.bag")]) == [
        "run", "run-2", "run-3", "other"]


@pytest.mark.parametrize(("extra", "message"), [
    (["--json", "s.json"], "--json: not with several recordings"),
    (["--gt", "gt.txt"], "--gt: not with several recordings (each recording's ground truth must be in its bag"),
    (["--live"], "--live: not with several recordings (a live replay plays at recorded timing and needs the cores"),
])
def test_options_a_fleet_run_cannot_honour_are_refused_before_any_work(tmp_path, extra, message):
    r = _nmnet("replay", str(SAMPLE), str(SAMPLE / "metadata.yaml"), "--out", str(tmp_path / "run"), *extra)
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert not (tmp_path / "run").exists()


def test_a_fleet_out_is_a_folder_and_never_an_input(tmp_path):
    r = _nmnet("replay", str(SAMPLE), str(tmp_path), "--out", str(tmp_path / "run.mcap"))
    assert r.returncode == 2 and "with several recordings the output is the run's folder" in r.stderr
    r = _nmnet("replay", str(SAMPLE), str(tmp_path), "--out", str(tmp_path))
    assert r.returncode == 2 and "the output" in r.stderr and "an input" in r.stderr, r.stderr


def test_the_report_totals_the_finished_recordings_and_names_the_failed(tmp_path):
    """The totals, the table and the plot: a value a recording lacks is '-' in the table and no bar in the plot (not
    a bar at 0, which reads as an AUC@5 of 0 or a perfect sigma); the failed are named in red."""
    from nmnet_ros.tools.replay import FLEET

    rows = [{"name": "a", "status": "ok", "frames": 40, "processed": 40, "dropped": 0, "scored_pairs": 39,
             "auc5": 80.0, "fps": 4.0, "fitted_pose_sigma_rotation_deg": 0.05, "fitted_pose_sigma_direction": 0.02},
            {"name": "b", "status": "ok", "frames": 20, "processed": 18, "dropped": 2, "scored_pairs": 0,
             "auc5": None, "fps": 6.0, "fitted_pose_sigma_rotation_deg": None, "fitted_pose_sigma_direction": None},
            {"name": "c", "status": "failed", "error": "BagError: unreadable"},
            {"name": "d", "status": "interrupted"}]
    t = fleet.totals(FLEET, rows)
    assert t == {"recordings": 4, "ok": 2, "failed": 1, "interrupted": 1, "frames": 60, "processed": 58, "dropped": 2,
                 "scored_pairs": 39, "auc5": 80.0, "fps": 5.0, "fitted_pose_sigma_rotation_deg": 0.05,
                 "fitted_pose_sigma_direction": 0.02}  # AUC@5 and the fitted sigmas over the scored recording only
    table = fleet.report_table(FLEET, {"recordings": rows, "totals": t})
    assert "| 39 | 80.0 | 0.05 | 0.02 | 4.0 |" in table.splitlines()[2], table  # a's row
    assert "| 39 | 80.0 (mean by scored_pairs) | 0.05 (mean by scored_pairs) |" in table.splitlines()[-1], table
    assert "| c | failed |" in table and "BagError: unreadable" in table and "1 not run (interrupted)" in table
    fig = fleet._plot(FLEET, tmp_path / "report.png", rows)
    assert (tmp_path / "report.png").stat().st_size > 0
    shown = {ax.get_ylabel(): [bar.get_height() for bar in ax.patches] for ax in fig.axes}
    assert list(shown) == ["AUC@5", "fitted pose_sigma_rotation_deg", "fitted pose_sigma_direction", "frames/s"]
    assert shown["AUC@5"][0] == 80.0 and all(h != h for h in shown["AUC@5"][1:]), shown  # NaN: no bar
    sigma = shown["fitted pose_sigma_direction"]
    assert sigma[0] == 0.02 and all(h != h for h in sigma[1:]), shown
    assert shown["frames/s"][:2] == [4.0, 6.0]
    names = fig.axes[-1].get_xticklabels()
    assert [n.get_text() for n in names] == ["a", "b", "c", "d"]
    assert [n.get_color() for n in names] == ["tab:blue", "tab:blue", "tab:red", "tab:red"]


def test_the_fleets_auc_is_that_of_all_its_pairs_not_of_an_average_recording():
    """A short recording that went badly and an hour-long one that went well: the total AUC@5 is that of all their
    pairs scored together (a plain mean over the two recordings put it halfway)."""
    from nmnet_ros.core.geometry import pose_auc
    from nmnet_ros.tools.replay import FLEET

    rng = np.random.default_rng(0)
    errors = [rng.uniform(0, 20, 30), rng.exponential(0.8, 3000)]
    rows = [{"name": str(n), "status": "ok", "scored_pairs": len(e), "auc5": 100 * pose_auc(e)[0]}
            for n, e in enumerate(errors)]
    pooled = 100 * pose_auc(np.concatenate(errors))[0]
    plain = (rows[0]["auc5"] + rows[1]["auc5"]) / 2
    assert abs(pooled - plain) > 20 and fleet.totals(FLEET, rows)["auc5"] == pytest.approx(pooled, abs=0.1)


@pytest.mark.slow
def test_label_takes_many_recordings_too_and_names_the_one_it_refuses(tmp_path):
    """``nmnet label A B --out RUN``: a labelled sequence folder per recording, as ``nmnet label`` of each alone
    writes it, and a standing camera refused in its row while the others are labelled."""
    from nmnet_ros.io.datasets import Sequence

    from .conftest import data_dir

    kitti = data_dir("kitti-07")
    specs = [f"{kitti}:0-14", f"{data_dir('euroc-v101-cam0')}"]
    run = tmp_path / "labelled"
    r = _nmnet("label", *specs, "--out", str(run), "--interval", "0")
    assert r.returncode == 1, r.stdout + r.stderr  # one refused
    rows = {row["name"]: row for row in json.loads((run / "report.json").read_text())["recordings"]}
    assert rows["kitti-07:0-14"]["status"] == "ok" and rows["kitti-07:0-14"]["registered"] == 15
    assert len(Sequence.load(run / "kitti-07:0-14").paths) == 15 and (run / "kitti-07:0-14" / "label.log").is_file()
    assert rows["euroc-v101-cam0"]["status"] == "failed" and "barely moves" in rows["euroc-v101-cam0"]["error"]
    assert not (run / "euroc-v101-cam0").exists() and not [p for p in run.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize(("argv", "message"), [
    (["replay", "--out", "run"], "name a recording"),
    (["label", "run"], "name the labelled sequence folder to write: --out DIR"),
    (["label", "--out", "run"], "name a recording to label"),
    (["replay", "--manifest", "missing.txt", "--out", "run"], "--manifest missing.txt: cannot read it"),
    (["label", str(SAMPLE), str(SAMPLE / "metadata.yaml"), "run", "--truth", str(SAMPLE)],
     "--truth: not with several recordings (one --truth folder cannot check"),
    (["label", str(SAMPLE), str(SAMPLE / "metadata.yaml"), "run", "--json", "l.json"], "--json: not with several"),
])
def test_what_a_run_over_recordings_cannot_start_from_is_refused_by_name(tmp_path, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    r = _nmnet(*argv)
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert not (tmp_path / "run").exists()


def test_a_cluster_address_nobody_answers_at_stops_at_once_naming_it(tmp_path):
    """Ray itself kept trying to connect to such an address for many minutes, saying nothing."""
    empty = tmp_path / "other"
    empty.mkdir()
    r = _nmnet("replay", str(SAMPLE), str(empty), "--out", str(tmp_path / "run"), "--ray-address", "127.0.0.1:1",
               timeout=300)  # a hang fails here
    assert r.returncode == 2 and "--ray-address 127.0.0.1:1: no Ray cluster answers there" in r.stderr, r.stderr
    assert not (tmp_path / "run" / "report.json").exists()


@pytest.mark.slow
def test_eval_scores_several_folders_in_parallel_as_it_scores_them_in_one_process(tmp_path):
    """``nmnet eval A B --manifest M``: one Ray task per folder (local runtime), the same numbers as the pairs of all
    the folders scored in one process; a folder that cannot be read among them is named, the others are scored."""
    import numpy as np

    from nmnet_ros.core.detectors import make_detector
    from nmnet_ros.io.cache import FeatureCache
    from nmnet_ros.io.pairs import load_pairs
    from nmnet_ros.tools.evaluate import evaluate

    from .conftest import data_dir

    kitti = data_dir("kitti-07")
    specs = [f"{kitti}:120-125", f"{kitti}:130-135"]
    manifest = tmp_path / "folders.txt"
    manifest.write_text(f"# the second folder, and one that is not there\n{specs[1]}\nmissing-folder\n")
    methods = "nmnet,ratio+magsac,oracle"
    out = tmp_path / "eval.json"
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    r = _nmnet("eval", specs[0], "--manifest", str(manifest), "--gaps", "1,2", "--methods", methods, "--seeds", "2",
               "--cache", str(tmp_path / "cache"), "--json", str(out), env=env)
    assert r.returncode == 1, r.stdout + r.stderr  # one folder failed
    assert "failed: missing-folder" in r.stderr and "not a directory" in r.stderr
    assert "| AUC@5 per sequence (pairs) | kitti-07:120-125 (9) | kitti-07:130-135 (9) |" in r.stdout
    got = json.loads(out.read_text())
    assert list(got["failed"]) == ["missing-folder"]

    cache = FeatureCache(make_detector("hessian-affine-fast", {"max_keypoints": 2000}), tmp_path / "cache")
    pairs = [p for spec in specs for p in load_pairs([spec], (1, 2), cache)]
    alone = evaluate(pairs, methods.split(","), seeds=2)["metrics"]
    for name, metrics in alone.items():
        assert {k: v for k, v in got["methods"][name].items() if k != "sec_per_pair"} == pytest.approx(
            {k: v for k, v in metrics.items() if k != "sec_per_pair"}, abs=1e-9), name
    assert sum(b["pairs"] for b in got["bins"]["gap"].values()) == len(pairs) == 18
    assert 0 < got["methods"]["nmnet"]["ap"] <= 100 and got["methods"]["ratio+magsac"]["ap"] is None  # a fit: no order
    assert all(0 < b["nmnet"]["ap"] <= 100 for b in got["bins"]["inlier_ratio"].values())
    assert "| average precision (%) of the order by putative inlier ratio |" in r.stdout
    assert np.isfinite(got["auc5_vs_reference"]["oracle"]["auc5"])
    none = _nmnet("eval", str(tmp_path / "gone-a"), str(tmp_path / "gone-b"), "--methods", "ratio", env=env)
    assert none.returncode == 2 and "no pairs to evaluate in any of the folders" in none.stderr, none.stderr
    assert "failed: gone-a" in none.stderr and "failed: gone-b" in none.stderr  # each named, as it failed


@pytest.mark.slow
def test_train_computes_the_features_of_several_folders_in_parallel_before_it_loads_them(tmp_path, monkeypatch):
    """``nmnet train``'s preparation: the features the folders' pairs need, one Ray task per folder, into the cache
    the loaders read; the same features as computed in one process."""
    import numpy as np

    from nmnet_ros.core.detectors import make_detector
    from nmnet_ros.io.cache import FeatureCache
    from nmnet_ros.io.pairs import pair_frames
    from nmnet_ros.tools.train import DEFAULT_CONFIG, PARALLEL_FRAMES, prepare_features

    from .conftest import data_dir

    kitti = data_dir("kitti-07")
    specs = [f"{kitti}:0-19", f"{kitti}:20-39"]  # 40 frames: Ray's start pays
    c = {**DEFAULT_CONFIG, "gaps": (1, 2)}
    cache = FeatureCache(make_detector(c["detector"], {"max_keypoints": c["max_keypoints"]}), tmp_path / "cache")
    said: list[str] = []
    monkeypatch.delenv("RAY_ADDRESS", raising=False)  # a local runtime
    prepare_features(specs, cache, c, said.append)
    assert "features: 40 frames of 2 folders" in said[0] and said[1].startswith("features: 40 computed"), said
    assert PARALLEL_FRAMES <= 40
    for spec in specs:
        seq, frames = pair_frames(spec, c["gaps"])
        assert cache.fill(seq, frames) == 0  # every one there
    seq, _ = pair_frames(specs[1], c["gaps"])
    stored, computed = cache(seq, 25), cache.detector(seq.image(25))
    assert np.array_equal(stored.keypoints, computed.keypoints) and np.array_equal(stored.descriptors, computed.descriptors)
    said.clear()
    prepare_features(specs, cache, c, said.append)
    assert not said  # nothing left to compute: no Ray


@pytest.mark.slow
def test_eval_interrupted_writes_nothing_and_eval_needs_a_folder(cluster, tmp_path):
    """Ctrl-C during a parallel eval: exit 130, no half-merged JSON; no folder at all is refused."""
    from .conftest import data_dir

    address, env = cluster  # one worker with one CPU: one folder at a time
    kitti = data_dir("kitti-07")
    out = tmp_path / "eval.json"
    proc = subprocess.Popen([str(BIN / "nmnet"), "eval", *(f"{kitti}:{a}-{a + 5}" for a in (120, 130, 140, 150)),
                             "--gaps", "1", "--methods", "ratio+magsac", "--cache", str(tmp_path / "cache"),
                             "--json", str(out), "--ray-address", address],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # as at a terminal
    for line in proc.stderr:  # a folder's notes come when it is scored
        if "eval: kitti-07:" in line:
            break
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 130, err
    assert "interrupted" in err and not out.exists()
    r = _nmnet("eval", "--methods", "ratio")
    assert r.returncode == 2 and "name a sequence folder, or give --manifest FILE" in r.stderr


def test_a_bad_input_fails_its_task_in_the_words_of_the_command_alone():
    """A bad recording's row said "DatasetError: run/report.json: not a directory": the class name is the code's, not
    the user's; the message is what `nmnet eval run/report.json` says."""
    from nmnet_ros.io.datasets import DatasetError

    assert fleet.described(DatasetError("run/report.json: not a directory")) == "run/report.json: not a directory"
    assert fleet.described(OSError(28, "No space left on device", "out")) == "[Errno 28] No space left on device: 'out'"


@pytest.mark.slow
def test_a_task_that_raises_is_its_own_failure_said_in_one_line(monkeypatch):
    """map_tasks: an exception in one task (here ZeroDivisionError, not a bad-input error) is that task's Failed,
    named by its type and message; the other tasks' results come back."""
    import operator

    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    results, interrupted = fleet.map_tasks(operator.truediv, {"half": (1, 2), "zero": (1, 0)}, quiet=True)
    assert not interrupted and results["half"] == 0.5
    assert isinstance(results["zero"], fleet.Failed) and "ZeroDivisionError: division by zero" in results["zero"].error
    assert "ray::" not in results["zero"].error  # not the worker's traceback


@pytest.mark.slow
def test_ctrl_c_while_tasks_finish_returns_what_finished_and_keeps_the_driver(monkeypatch):
    """map_tasks: Ctrl-C arriving as a result comes in, with the other tasks finishing around it, ends the run with
    the results that came and interrupted=True, and Ray starts again in the same process. (It does not reproduce
    the race of ray-project/ray#54798, a cancel meeting a task's end, which map_tasks avoids by not cancelling.)"""
    import operator

    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    seen: list[str] = []

    def done(name: str, result: object) -> None:
        seen.append(name)
        if len(seen) == 2:
            raise KeyboardInterrupt  # as the SIGINT handler raises it in the driver

    calls = {f"t{i}": (i, 1) for i in range(40)}
    results, interrupted = fleet.map_tasks(operator.add, calls, quiet=True, done=done)
    assert interrupted and set(results) == set(seen) and len(seen) == 2
    assert all(results[name] == int(name[1:]) + 1 for name in seen)
    again, interrupted = fleet.map_tasks(operator.add, {"after": (1, 1)}, quiet=True)  # Ray starts again, in-process
    assert not interrupted and again == {"after": 2}

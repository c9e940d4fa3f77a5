"""``nmnet bench``: stage timings on this machine, printed with the command's own baselines.

Neighbour mining: the vectorised blocked-matmul miner against the paper's formula written as a
per-correspondence loop (numpy), both in this process, for N = 1000 and 2000.
Pipeline (``--pipeline``): per-stage median/p90 latency (decode, detect+describe, match,
neighbours, NM-Net, pose) on the sample bag's real frames at 640x480 and native size, for
N = 1000 and 2000 keypoints; the measured rate of the node's two-stage schedule; the kornia
detector and the reference network on the same input; and in the same run the OpenCV baseline
(SIFT 2000 + ratio + MAGSAC++) on the same frames, with the ratio.
"""

from __future__ import annotations

import argparse
import contextlib
import time
from collections.abc import Callable, Iterator
from functools import partial
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..core.neighbors import compatibility_neighbors, compatibility_neighbors_loop, spatial_neighbors
from ..io.outputs import output_file, write_json

if TYPE_CHECKING:  # the network and OpenCV load when a benchmark runs, not on import
    from ..core.geometry import Camera
    from ..core.pipeline import Frontend


def timeit(fn: Callable[[], object], repeat: int) -> list[float]:
    """Milliseconds of each of ``repeat`` calls after one warm-up call."""
    fn()
    out = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        out.append(1000 * (time.perf_counter() - t))
    return out


def synthetic_correspondences(n: int, seed: int = 0) -> tuple[np.ndarray, ...]:
    """Matched keypoints and frames with the statistics of a 640x480 pair (timing only)."""
    rng = np.random.default_rng(seed)
    k0 = rng.uniform([0, 0], [640, 480], (n, 2)).astype(np.float32)
    k1 = (k0 + rng.normal(0, 15, (n, 2))).astype(np.float32)
    a0 = (rng.normal(0, 3, (n, 2, 2)) + 8 * np.eye(2)).astype(np.float32)
    a1 = (a0 @ (np.eye(2) + rng.normal(0, 0.1, (n, 2, 2)))).astype(np.float32)
    return k0, a0, k1, a1


def bench_neighbors(sizes: tuple[int, ...] = (1000, 2000), repeat: int = 20) -> dict:
    """Median/p90 ms of the miners and the ratio to the loop baseline."""
    res = {}
    for n in sizes:
        corr = synthetic_correspondences(n)
        fast = timeit(partial(compatibility_neighbors, *corr), repeat)
        spatial = timeit(partial(spatial_neighbors, corr[0], corr[2]), repeat)
        loop = timeit(partial(compatibility_neighbors_loop, *corr), 2)
        res[n] = {"compatibility_ms": float(np.median(fast)), "compatibility_p90_ms": float(np.percentile(fast, 90)),
                  "spatial_ms": float(np.median(spatial)), "loop_ms": float(np.median(loop)),
                  "speedup_vs_loop": float(np.median(loop) / np.median(fast))}
    return res


def _stages(det, model, cam, imgs: list[np.ndarray], jpegs: list[bytes]) -> tuple[dict, list[float], list]:
    """Serial per-stage timings (ms) of one configuration over consecutive frames, and each frame's features."""
    import cv2

    from ..core.bf16 import native_bf16
    from ..core.matching import match_descriptors
    from ..core.neighbors import compatibility_neighbors
    from ..core.selectors import DEFAULT_CONFIG, SCORED_FITS, Correspondences, nmnet_scores
    from ..core.settings import DEFAULT_METHOD

    fit = SCORED_FITS[DEFAULT_METHOD]  # the default pose path after NM-Net

    h, w = imgs[0].shape[:2]
    screen = native_bf16()  # matching screens in bfloat16 here: time the float32 GEMM beside it
    st: dict[str, list[float]] = {k: [] for k in ("decode", "detect", "match", "neighbors", "nmnet", "pose", "total",
                                                  *(("match_float32",) if screen else ()))}
    feats, prev = [], None
    for img, jpg in zip(imgs, jpegs, strict=True):
        t = time.perf_counter()
        cv2.imdecode(np.frombuffer(jpg, np.uint8), cv2.IMREAD_UNCHANGED)
        t0 = time.perf_counter()
        f = det(img)
        t1 = time.perf_counter()
        feats.append(f)
        if prev is not None:
            m = match_descriptors(prev.descriptors, f.descriptors)
            t2 = time.perf_counter()
            k0, k1 = prev.keypoints[m.idx[:, 0]], f.keypoints[m.idx[:, 1]]
            a0, a1 = prev.frames[m.idx[:, 0]], f.frames[m.idx[:, 1]]
            nb = compatibility_neighbors(k0, a0, k1, a1)
            t3 = time.perf_counter()
            c = Correspondences(k0, k1, a0, a1, cam.normalize(k0), cam.normalize(k1), m.ratio, m.mutual, cam.focal, (w, h), (w, h))
            scored = nmnet_scores(model, c, DEFAULT_CONFIG, nb)
            t4 = time.perf_counter()
            fit(scored, c, DEFAULT_CONFIG)
            t5 = time.perf_counter()
            for k, v in zip(("decode", "detect", "match", "neighbors", "nmnet", "pose", "total"),
                            (t0 - t, t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t5 - t), strict=True):
                st[k].append(1000 * v)
            if screen:  # baseline: the same matching with the float32 GEMM
                t = time.perf_counter()
                match_descriptors(prev.descriptors, f.descriptors, {"gemm": "float32"})
                st["match_float32"].append(1000 * (time.perf_counter() - t))
        prev = f
    return st, feats


@contextlib.contextmanager
def cpu_threads(n: int) -> Iterator[None]:
    """torch's and OpenCV's thread counts set to ``n`` (numba's kernels follow torch's, see jit.py), restored after."""
    import cv2

    saved = torch.get_num_threads(), cv2.getNumThreads()
    torch.set_num_threads(n)
    cv2.setNumThreads(n)
    try:
        yield
    finally:
        torch.set_num_threads(saved[0])
        cv2.setNumThreads(saved[1])


def pipelined_hz(frontend: Frontend, imgs: list[np.ndarray], threads: int = 1) -> float:
    """Frames per second of the node's two-stage schedule: detection and matching of frame t+1 on a
    second thread while frame t is scored and posed, ``threads`` CPU threads per stage (nmnet_node's default)."""
    import queue
    import threading

    q: queue.Queue = queue.Queue(maxsize=1)

    def produce() -> None:
        for img in imgs:
            q.put(frontend.prepare(img))
        q.put(None)

    with cpu_threads(threads):
        frontend.reset()
        t = time.perf_counter()
        th = threading.Thread(target=produce)
        th.start()
        n, stamp = 0, 0.0
        while (item := q.get()) is not None:
            stamp += 0.1
            frontend.process_prepared(item, stamp)
            n += 1
        th.join()
        return n / (time.perf_counter() - t)


def bench_pipeline(frames: list[np.ndarray], camera: Camera, sizes: tuple[int, ...] = (1000, 2000), reference: bool = True) -> dict:
    """Per-stage latencies (ms) of the NM-Net front end, its pipelined rate, the kornia/reference-network
    costs and the OpenCV baseline (SIFT 2000 + ratio + MAGSAC++), all on the same frames."""
    import cv2

    from ..core.fast_hessaff import FastHessianAffine
    from ..core.features import HessianAffine, SiftSimilarity
    from ..core.matching import match_descriptors
    from ..core.model import load_model
    from ..core.model_fast import FastNMNet, resolve_precision
    from ..core.neighbors import compatibility_neighbors
    from ..core.pipeline import Frontend
    from ..core.selectors import Correspondences, build, nmnet_logits

    out: dict = {}
    ref_model = load_model()
    model = FastNMNet(ref_model, resolve_precision("auto"))  # what the node runs on this CPU
    model32 = FastNMNet(ref_model) if model.dtype != torch.float32 else None  # and the exact network beside it
    ratio_magsac = build("ratio+magsac")
    for label, shape in (("640x480", (640, 480)), ("native", None)):
        imgs = [cv2.resize(f, shape, interpolation=cv2.INTER_AREA) if shape else f for f in frames]
        jpegs = [cv2.imencode(".jpg", f, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes() for f in imgs]
        h, w = imgs[0].shape[:2]
        cam = camera.resized(w, h, (frames[0].shape[1], frames[0].shape[0]))
        for n in sizes:
            st, feats = _stages(FastHessianAffine({"max_keypoints": n}), model, cam, imgs, jpegs)
            row: dict = {k: {"median": float(np.median(v)), "p90": float(np.percentile(v, 90))} for k, v in st.items()}
            row["serial_hz"] = 1000.0 / row["total"]["median"]
            # the node's schedule, and as same-process baselines matching always beside NM-Net (before
            # match_stage auto), NM-Net in float32 (where auto picks bfloat16) and matching with the float32
            # GEMM (where auto screens in bfloat16); in the order A B C D D C B A, so that a drift of the
            # machine's speed cancels
            fe = {m: Frontend(cam, {"max_keypoints": n, "match_stage": m}) for m in ("auto", "second")}
            if model32 is not None:
                fe["float32"] = Frontend(cam, {"max_keypoints": n, "nmnet_precision": "float32"})
                fe["match_float32"] = Frontend(cam, {"max_keypoints": n, "match_gemm": "float32"})
            hz: dict[str, list[float]] = {m: [] for m in fe}
            for m in [*fe, *reversed(fe)]:
                hz[m].append(pipelined_hz(fe[m], imgs))
            row["end_to_end_hz"], row["end_to_end_hz_match_stage2"] = (float(np.mean(hz[m])) for m in ("auto", "second"))
            if model32 is not None:
                row["end_to_end_hz_float32"] = float(np.mean(hz["float32"]))
                row["end_to_end_hz_match_float32"] = float(np.mean(hz["match_float32"]))
            base, sift_ms = [], []
            sift = SiftSimilarity({"max_keypoints": 2000})
            prev = None
            for img in imgs:
                t = time.perf_counter()
                f = sift(img)
                sift_ms.append(1000 * (time.perf_counter() - t))
                if prev is not None:
                    m = match_descriptors(prev.descriptors, f.descriptors)
                    k0, k1 = prev.keypoints[m.idx[:, 0]], f.keypoints[m.idx[:, 1]]
                    ratio_magsac(Correspondences(k0, k1, prev.frames[m.idx[:, 0]], f.frames[m.idx[:, 1]], cam.normalize(k0),
                                                 cam.normalize(k1), m.ratio, m.mutual, cam.focal, (w, h), (w, h)))
                    base.append(1000 * (time.perf_counter() - t))
                prev = f
            row["baseline_ms"] = float(np.median(base))
            row["baseline_hz"] = 1000.0 / row["baseline_ms"]
            row["sift_detect_ms"] = float(np.median(sift_ms))  # the cheaper frame source (--detector sift), 2000 kp
            if reference and label == "640x480" and n == max(sizes):
                kornia = HessianAffine({"max_keypoints": n})
                row["reference_detect_ms"] = float(np.median(timeit(partial(kornia, imgs[1]), 3)))
                m = match_descriptors(feats[0].descriptors, feats[1].descriptors)
                k0, k1 = feats[0].keypoints[m.idx[:, 0]], feats[1].keypoints[m.idx[:, 1]]
                a0, a1 = feats[0].frames[m.idx[:, 0]], feats[1].frames[m.idx[:, 1]]
                c = Correspondences(k0, k1, a0, a1, cam.normalize(k0), cam.normalize(k1), m.ratio, m.mutual, cam.focal,
                                    (w, h), (w, h))
                nb = compatibility_neighbors(k0, a0, k1, a1)
                row["reference_nmnet_ms"] = float(np.median(timeit(partial(nmnet_logits, ref_model, c, nb), 5)))
                row["fast_nmnet_ms"] = float(np.median(timeit(partial(nmnet_logits, model, c, nb), 5)))
                if model32 is not None:
                    row["fast_nmnet_float32_ms"] = float(np.median(timeit(partial(nmnet_logits, model32, c, nb), 5)))
            out[f"{label}_N{n}"] = row
    return out


def bench_hd(frames: list[np.ndarray], camera: Camera, size: tuple[int, int] = (1920, 1080), width: int = 960,
             n: int = 2000) -> dict:
    """A high-resolution camera (the frames resized to ``size``): detection at full size and with
    ``resize_width`` = ``width``, and the pipelined rate of each, alternated A B B A."""
    import cv2

    from ..core.pipeline import Frontend, downscaled

    imgs = [cv2.resize(f, size, interpolation=cv2.INTER_LINEAR) for f in frames]
    cam = camera.resized(*size, (frames[0].shape[1], frames[0].shape[0]))
    fe = {w: Frontend(cam, {"max_keypoints": n, "resize_width": w}) for w in (0, width)}
    out: dict = {"size": list(size), "resize_width": width, "keypoints": n}
    for w, f in fe.items():
        with cpu_threads(1):  # a node stage's budget; the downscaling counts
            out[f"detect_ms_{w}"] = float(np.median(timeit(lambda f=f, w=w: f.detect(downscaled(imgs[1], w)), 3)))
    hz: dict[int, list[float]] = {0: [], width: []}
    for w in (0, width, width, 0):
        hz[w].append(pipelined_hz(fe[w], imgs))
    out["hz_0"], out[f"hz_{width}"] = (float(np.mean(hz[w])) for w in (0, width))
    return out


def main(args: argparse.Namespace) -> int:
    """Entry point of ``nmnet bench``."""
    output_file(args.json, "--json", "bench.json")
    if args.threads is None:
        return _run(args)
    with cpu_threads(args.threads):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    sizes = args.sizes
    print(f"torch threads: {torch.get_num_threads()}")
    res = {"neighbors": bench_neighbors(sizes, args.repeat)}
    print("| N | compatibility (median / p90 ms) | spatial kNN ms | per-correspondence loop ms | speed-up |")
    print("|---|---|---|---|---|")
    for n, r in res["neighbors"].items():
        print(f"| {n} | {r['compatibility_ms']:.1f} / {r['compatibility_p90_ms']:.1f} | {r['spatial_ms']:.1f} | "
              f"{r['loop_ms']:.1f} | {r['speedup_vs_loop']:.1f}x |")
    if args.pipeline:
        from ..io.bags import BagReader, read_frames
        from .options import SAMPLE_BAG

        it, _ = read_frames(BagReader(SAMPLE_BAG))
        frames = [f for _, f in zip(range(args.frames), it, strict=False)]
        res["pipeline"] = bench_pipeline([f.image for f in frames], frames[0].camera)
        stages = ("decode", "detect", "match", "neighbors", "nmnet", "pose", "total")
        print(f"\n{len(frames)} frames of the sample bag (KITTI-07, native 1241x376); median / p90 ms per stage")
        print("\n| size, keypoints | " + " | ".join(stages) + " | serial Hz | pipelined Hz | SIFT+ratio+MAGSAC++ Hz | ratio |")
        print("|---" * (len(stages) + 5) + "|")
        for key, r in res["pipeline"].items():
            cells = " | ".join(f"{r[s]['median']:.0f} / {r[s]['p90']:.0f}" for s in stages)
            print(f"| {key} | {cells} | {r['serial_hz']:.1f} | {r['end_to_end_hz']:.1f} | {r['baseline_hz']:.1f} | "
                  f"{r['end_to_end_hz'] / r['baseline_hz']:.2f}x |")
        split = [f"{key} {r['end_to_end_hz_match_stage2']:.1f} Hz (auto {r['end_to_end_hz'] / r['end_to_end_hz_match_stage2']:.2f}x)"
                 for key, r in res["pipeline"].items()]
        print("\npipelined with matching always in stage 2 (beside NM-Net; auto moves it beside detection when that "
              "shortens the slower stage): " + ", ".join(split))
        f32 = [f"{key} {r['end_to_end_hz_float32']:.1f} Hz (bfloat16 {r['end_to_end_hz'] / r['end_to_end_hz_float32']:.2f}x)"
               for key, r in res["pipeline"].items() if "end_to_end_hz_float32" in r]
        if f32:
            print("pipelined with NM-Net in float32 (auto runs it in bfloat16 on this CPU): " + ", ".join(f32))
            m32 = [f"{key} {r['end_to_end_hz_match_float32']:.1f} Hz (screen {r['end_to_end_hz'] / r['end_to_end_hz_match_float32']:.2f}x)"
                   for key, r in res["pipeline"].items()]
            print("pipelined with matching on the float32 GEMM (auto screens in bfloat16 on this CPU): " + ", ".join(m32))
        for key, r in res["pipeline"].items():
            if "reference_detect_ms" in r:
                print(f"\nsame process, {key}: kornia reference detector {r['reference_detect_ms']:.0f} ms vs fast "
                      f"{r['detect']['median']:.0f} ms ({r['reference_detect_ms'] / r['detect']['median']:.1f}x); reference NM-Net "
                      f"{r['reference_nmnet_ms']:.0f} ms vs fast {r['fast_nmnet_ms']:.0f} ms "
                      f"({r['reference_nmnet_ms'] / r['fast_nmnet_ms']:.1f}x)")
                if "fast_nmnet_float32_ms" in r:
                    print(f"same process, {key}: fast NM-Net float32 {r['fast_nmnet_float32_ms']:.0f} ms vs bfloat16 "
                          f"{r['fast_nmnet_ms']:.0f} ms ({r['fast_nmnet_float32_ms'] / r['fast_nmnet_ms']:.2f}x)")
        gemm = [f"{key} {r['match_float32']['median']:.1f} vs {r['match']['median']:.1f} ms "
                f"({r['match_float32']['median'] / r['match']['median']:.2f}x)" for key, r in res["pipeline"].items()
                if "match_float32" in r]
        if gemm:
            print("same process, matching with the float32 GEMM vs as run (auto: bfloat16 screen + float32 re-check "
                  "on this CPU): " + ", ".join(gemm))
        hd = res["hd"] = bench_hd([f.image for f in frames], frames[0].camera)
        w = hd["resize_width"]
        print(f"\n{hd['size'][0]}x{hd['size'][1]} frames (the sample's, upscaled), {hd['keypoints']} keypoints, 1 thread: "
              f"detect {hd['detect_ms_0']:.0f} ms at full size vs {hd[f'detect_ms_{w}']:.0f} ms with resize_width {w} "
              f"({hd['detect_ms_0'] / hd[f'detect_ms_{w}']:.1f}x); pipelined {hd['hz_0']:.1f} vs {hd[f'hz_{w}']:.1f} Hz "
              f"({hd[f'hz_{w}'] / hd['hz_0']:.1f}x)")
        sift = [f"{key.split('_')[0]} {r['sift_detect_ms']:.0f} ms" for key, r in res["pipeline"].items() if key.endswith("N2000")]
        print("\nOpenCV SIFT (2000 kp, similarity frames, --detector sift) detect+describe: " + ", ".join(sift))
    if args.json:
        write_json(args.json, res)
    return 0

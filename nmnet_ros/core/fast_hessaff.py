"""Fast Hessian-affine: the reference detector's method on OpenCV/numpy/torch primitives.

Same stages and conventions as the kornia path in :mod:`nmnet_ros.core.features` (which stays the
reference): Hessian-determinant scale space (scale-normalised by sigma^4), 3-D non-maximum
suppression with quadratic refinement, Baumberg affine adaptation, dominant gradient
orientation and RootSIFT on the normalised patch. What makes it fast is that every per-keypoint
step runs on all keypoints at once: one compiled (numba) bilinear sampler per pyramid level
samples every patch, the affine moments are batched tensor reductions, and orientation and
RootSIFT are compiled kernels that keep each keypoint's histograms in registers. The affine step
samples a smoothed structure tensor (image gradients computed once per level) instead of
differentiating patches, so a 10 x 10 grid suffices for its weighted sums. The scale space's
determinant of the Hessian (one pass per level) and its 3x3x3 maxima (one scan per octave) are compiled kernels too.

Patch convention (as kornia's ``extract_patches_from_pyramid``): cell (i, j) of a PS x PS patch
samples ``c + A @ (u_j, u_i)`` with ``u_k = (2k + 1) / PS - 1`` from pyramid level
``floor(log2(2 s / PS))``, s = sqrt(det A).
"""

from __future__ import annotations

import math

import cv2
import numba
import numpy as np
import torch

from .features import Features, to_gray_float
from .jit import launch

DEFAULT_CONFIG: dict = {
    "max_keypoints": 2000,
    "levels_per_octave": 3,
    "init_sigma": 1.6,
    "threshold": 1e-6,  # on the sigma^4-normalised Hessian determinant (image in [0, 1])
    "mr_size": 6.0,  # measurement region = mr_size * detection sigma, as the reference
    "affine_iterations": 3,  # Baumberg steps; 0 gives similarity frames
    "affine_patch": 16,  # equivalent patch sizes: they pick the pyramid level (as the reference's patches)
    "orientation_patch": 16,
    "patch_size": 16,  # descriptor
    "affine_grid": 10,  # samples per side for the second moments (of a pre-smoothed structure tensor)
    "orientation_grid": 12,
    "orientation_extent": 0.75,  # central part of the orientation patch that is sampled
    "descriptor_grid": 16,
    "upright": False,
    "chunk": 4096,  # keypoints per batch of patch work (bounds memory on huge images)
}


def _gaussian(ps: int, sigma: float) -> torch.Tensor:
    """Normalised (ps, ps) Gaussian window centred on the patch."""
    x = torch.arange(ps, dtype=torch.float32) - (ps - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    return g[:, None] * g[None, :]


def _sift_pooling_1d(ps: int, cells: int = 4) -> torch.Tensor:
    """(cells, ps) triangular pooling weights of kornia's SIFTDescriptor along one axis (ksize 2*floor(ps/5), stride ps/4)."""
    stride = ps // cells
    ks = 2 * int(ps / (cells + 1))
    if (ks - ps + (cells - 1) * stride) % 2:
        ks += 1
    centres = (ps - 1) / 2 + (torch.arange(cells, dtype=torch.float32) - (cells - 1) / 2) * stride
    x = torch.arange(ps, dtype=torch.float32)
    return (ks / 2 - (x[None, :] - centres[:, None]).abs()).clamp(min=0) / (ks / 2)


def upright(a: np.ndarray) -> np.ndarray:
    """Lower-triangular U with U U^T = A A^T (kornia ``make_upright``): same region, orientation 0."""
    r0 = np.hypot(a[:, 0, 0], a[:, 0, 1]) + 1e-9
    det = np.abs(a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0])
    u = np.zeros_like(a)
    u[:, 0, 0] = r0
    u[:, 1, 0] = (a[:, 1, 1] * a[:, 0, 1] + a[:, 1, 0] * a[:, 0, 0]) / r0
    u[:, 1, 1] = det / r0
    return u


class _Pyramid:
    """Gaussian pyramid with per-level gradient fields, sampled through LAFs for all keypoints at once.

    A patch-space gradient is ``A^T`` times the image gradient at the sample (chain rule), so the
    gradients are computed once per level (Sobel) and sampled, instead of differentiating every
    patch; the grid only has to be fine enough for the weighted sums it feeds.
    """

    def __init__(self, gray: np.ndarray, min_side: int) -> None:
        self.levels = [gray]
        while min(self.levels[-1].shape) // 2 >= min_side:
            self.levels.append(cv2.pyrDown(self.levels[-1]))
        self._fields: dict[tuple[str, int], np.ndarray] = {}
        self.tensor_sigma = 1.0

    def field(self, name: str, lv: int) -> np.ndarray:
        """'image': (H, W, 1) the level; 'tensor': (H, W, 3) gx^2, gx gy, gy^2 (normalised Sobel), smoothed."""
        key = (name, lv)
        if key not in self._fields:
            img = self.levels[lv]
            if name == "image":
                self._fields[key] = img[..., None]
                return self._fields[key]
            gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
            gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
            # smoothed at one pixel so that a coarse sampling grid integrates it faithfully
            self._fields[key] = cv2.GaussianBlur(cv2.merge([gx * gx, gx * gy, gy * gy]), (0, 0), self.tensor_sigma)
        return self._fields[key]

    def sample(self, name: str, frames: np.ndarray, centres: np.ndarray, ps: int, grid: int) -> np.ndarray:
        """(n, grid*grid, C) samples of a field at the cell centres of a grid x grid patch through the frames.

        The level is chosen as for a ps x ps patch: floor(log2(2 s / ps)), s = sqrt(det A); frames must
        come sorted by scale.
        """
        n = len(frames)
        top = 0
        while top + 1 < len(self.levels) and min(self.levels[top + 1].shape) >= ps:
            top += 1
        scale = np.sqrt(np.abs(frames[:, 0, 0] * frames[:, 1, 1] - frames[:, 0, 1] * frames[:, 1, 0]))
        level = np.clip(np.floor(np.log2(np.maximum(2 * scale / ps, 1e-12))), 0, top).astype(int)
        k = (2.0 ** -level).astype(np.float32)
        a = np.ascontiguousarray(np.asarray(frames, np.float32) * k[:, None, None])
        c = np.ascontiguousarray((np.asarray(centres, np.float32) + 0.5) * k[:, None] - 0.5)
        f0 = self.field(name, int(level[0]))
        out = np.empty((n, grid * grid, f0.shape[2]), np.float32)
        bounds = np.flatnonzero(np.diff(level)) + 1  # keypoints come sorted by scale: levels are runs
        for s, e in zip(np.r_[0, bounds], np.r_[bounds, n], strict=True):
            launch(_sample_kernel, self.field(name, int(level[s])), a[s:e], c[s:e], grid, out[s:e])
        return out


@numba.njit(parallel=True, fastmath=True, cache=True, boundscheck=False)
def _sample_kernel(field, a, c, grid, out):  # pragma: no cover - compiled
    """out[i, gi * grid + gj] = field at c_i + a_i (u_gj, u_gi), u_k = (2k + 1) / grid - 1:
    bilinear, border replicated (as cv2.remap's BORDER_REPLICATE, without its 1/32 px weights)."""
    h, w, nc = field.shape
    u = np.empty(grid, np.float32)
    for k in range(grid):
        u[k] = (2 * k + 1) / grid - 1
    for i in numba.prange(a.shape[0]):
        a00, a01, a10, a11, cx, cy = a[i, 0, 0], a[i, 0, 1], a[i, 1, 0], a[i, 1, 1], c[i, 0], c[i, 1]
        rx, ry = abs(a00) + abs(a01), abs(a10) + abs(a11)  # the patch lies within c +- (rx, ry)
        inside = cx - rx >= 0 and cx + rx < w - 1 and cy - ry >= 0 and cy + ry < h - 1
        for gi in range(grid):
            for gj in range(grid):
                x = cx + a00 * u[gj] + a01 * u[gi]
                y = cy + a10 * u[gj] + a11 * u[gi]
                if inside:
                    xa, ya = int(x), int(y)  # x, y >= 0: truncation is floor
                    fx, fy = x - xa, y - ya
                    xb, yb = xa + 1, ya + 1
                else:
                    x0, y0 = math.floor(x), math.floor(y)
                    fx, fy = x - x0, y - y0
                    xa, xb = min(max(int(x0), 0), w - 1), min(max(int(x0) + 1, 0), w - 1)
                    ya, yb = min(max(int(y0), 0), h - 1), min(max(int(y0) + 1, 0), h - 1)
                for ch in range(nc):
                    top = field[ya, xa, ch] + fx * (field[ya, xb, ch] - field[ya, xa, ch])
                    bot = field[yb, xa, ch] + fx * (field[yb, xb, ch] - field[yb, xa, ch])
                    out[i, gi * grid + gj, ch] = top + fy * (bot - top)


class FastHessianAffine:
    """Hessian-affine + RootSIFT, batched over keypoints (10-20x the kornia reference's speed)."""

    min_size = 32

    def __init__(self, config: dict | None = None) -> None:
        self.config = {**DEFAULT_CONFIG, **(config or {})}
        c = self.config
        g = c["affine_grid"]  # Gaussian windows of the reference, in units of the patch half-width: 1, 1/3, sqrt(2)
        self._w_aff = _gaussian(g, g / 2).reshape(-1)
        go = c["orientation_grid"]  # sigma 1/3 of the half-width, on a grid spanning orientation_extent of it
        self._w_ori = _gaussian(go, go / (6 * c["orientation_extent"])).reshape(-1).numpy()
        gd = c["descriptor_grid"]
        self._w_desc = _gaussian(gd, gd / math.sqrt(2)).reshape(-1).numpy()
        w = _sift_pooling_1d(gd)
        pool = torch.einsum("ay,bx->yxab", w, w).reshape(gd * gd, -1).numpy()  # (gd^2, 16) triangular cell weights
        nnz = int((pool > 0).sum(1).max())  # each sample feeds at most this many cells (4)
        self._cell_idx = np.ascontiguousarray(np.argsort(-pool, 1, kind="stable")[:, :nnz]).astype(np.int64)
        self._cell_w = np.ascontiguousarray(np.take_along_axis(pool, self._cell_idx, 1), np.float32)
        k = torch.exp(-((torch.arange(5, dtype=torch.float32) - 2) ** 2) / (2 * 1.6**2))
        self._ang_smooth = (k / k.sum()).numpy()
        # compile (or load from numba's disk cache) the sampler, orientation and descriptor kernels
        # now, not on the first frame: a noise image has keypoints at every pyramid level
        self(np.random.default_rng(0).integers(0, 256, (96, 96), dtype=np.uint8))

    @property
    def cache_key(self) -> str:
        """Identifies the settings, for on-disk feature caches."""
        c = self.config
        return (f"fasthesaff-k{c['max_keypoints']}-a{c['affine_iterations']}x{c['affine_patch']}"
                f"-o{c['orientation_patch']}-p{c['patch_size']}-g{c['affine_grid']}x{c['orientation_grid']}x{c['descriptor_grid']}-m{c['mr_size']}-u{int(c['upright'])}"
                "-s3")  # s3: the fused Hessian kernel (float32 rounding, ~1e-5 px; s2: the float sampler): older caches are not reused

    @torch.inference_mode()
    def __call__(self, image: np.ndarray) -> Features:
        """Detect and describe; a blank, tiny or empty image gives empty features."""
        gray = to_gray_float(image)
        if min(gray.shape) < self.min_size or float(gray.max() - gray.min()) < 1e-3:
            return Features.empty()
        c = self.config
        xy, sigma, resp = self.detect(gray)
        if len(xy) == 0:
            return Features.empty()
        frames = (c["mr_size"] * sigma)[:, None, None] * np.eye(2, dtype=np.float32)
        pyr = _Pyramid(gray, min(c["affine_patch"], c["orientation_patch"], c["patch_size"]))
        desc = np.empty((len(xy), 128), np.float32)
        for a in range(0, len(xy), c["chunk"]):  # chunks keep every per-patch array in cache
            sl = slice(a, a + c["chunk"])
            f = frames[sl]
            for _ in range(c["affine_iterations"]):
                f = self.adapt_shape(pyr, f, xy[sl])
            if not c["upright"]:
                f = self.orient(pyr, f, xy[sl])
            frames[sl], desc[sl] = f, self.describe(pyr, f, xy[sl])
        return Features(xy.astype(np.float32), frames.astype(np.float32), desc, resp.astype(np.float32))

    # -- detection ---------------------------------------------------------------------------
    def detect(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Scale-space maxima of the sigma^4-normalised Hessian determinant: centres, sigmas (px), responses."""
        c = self.config
        nl, s0 = c["levels_per_octave"], c["init_sigma"]
        sig = [s0 * 2 ** (i / nl) for i in range(nl + 2)]
        img = cv2.GaussianBlur(gray, (0, 0), math.sqrt(s0**2 - 0.25))
        found: list[np.ndarray] = []
        octave = 0
        while min(img.shape) >= 16:
            blurred = [img]
            for i in range(1, nl + 2):
                blurred.append(cv2.GaussianBlur(blurred[-1], (0, 0), math.sqrt(sig[i] ** 2 - sig[i - 1] ** 2)))
            resp = np.empty((nl + 2, *img.shape), np.float32)
            for i, b in enumerate(blurred):
                self._hessian(b, sig[i] ** 2, resp[i])
            found.append(self._extrema(resp, octave))
            img = blurred[nl][::2, ::2]
            octave += 1
        cand = np.concatenate(found) if found else np.zeros((0, 4), np.float32)
        if len(cand) > c["max_keypoints"]:
            cand = cand[np.argpartition(-cand[:, 3], c["max_keypoints"])[: c["max_keypoints"]]]
        cand = cand[np.argsort(cand[:, 2], kind="stable")]  # by scale: patch sampling goes level by level
        return cand[:, :2], cand[:, 2], cand[:, 3]

    @staticmethod
    def _hessian(img: np.ndarray, s2: float, out: np.ndarray) -> None:
        """sigma^4-normalised determinant of the Hessian (5x5 Sobel derivatives, as the reference's BlobHessian)."""
        launch(_hessian_kernel, img, np.float32(s2 / 48), out)

    def _extrema(self, r: np.ndarray, octave: int) -> np.ndarray:
        """3x3x3 maxima above threshold with quadratic (x, y, level) refinement -> rows (x, y, sigma, response)."""
        c = self.config
        nl, rows, cols = r.shape
        idx = np.empty(((nl - 2) * ((rows + 1) // 2) * ((cols + 1) // 2), 3), np.int32)  # room for any strict maxima
        n = _maxima_kernel(r, np.float32(c["threshold"]), idx)
        if n > len(idx):  # plateaus (ties) can give more: count known, run again
            idx = np.empty((n, 3), np.int32)
            _maxima_kernel(r, np.float32(c["threshold"]), idx)
        if n == 0:
            return np.zeros((0, 4), np.float32)
        li, y, x = idx[:n].T.astype(np.int64)
        v = r[li, y, x]
        g = np.stack([(r[li, y, x + 1] - r[li, y, x - 1]) / 2, (r[li, y + 1, x] - r[li, y - 1, x]) / 2,
                      (r[li + 1, y, x] - r[li - 1, y, x]) / 2], 1)
        h = np.empty((len(v), 3, 3), np.float64)
        h[:, 0, 0] = r[li, y, x + 1] + r[li, y, x - 1] - 2 * v
        h[:, 1, 1] = r[li, y + 1, x] + r[li, y - 1, x] - 2 * v
        h[:, 2, 2] = r[li + 1, y, x] + r[li - 1, y, x] - 2 * v
        h[:, 0, 1] = h[:, 1, 0] = (r[li, y + 1, x + 1] - r[li, y + 1, x - 1] - r[li, y - 1, x + 1] + r[li, y - 1, x - 1]) / 4
        h[:, 0, 2] = h[:, 2, 0] = (r[li + 1, y, x + 1] - r[li + 1, y, x - 1] - r[li - 1, y, x + 1] + r[li - 1, y, x - 1]) / 4
        h[:, 1, 2] = h[:, 2, 1] = (r[li + 1, y + 1, x] - r[li + 1, y - 1, x] - r[li - 1, y + 1, x] + r[li - 1, y - 1, x]) / 4
        ok = np.abs(np.linalg.det(h)) > 1e-30
        off = np.zeros((len(v), 3))
        if ok.any():
            off[ok] = -np.linalg.solve(h[ok], g[ok][:, :, None])[:, :, 0]
        off[~(np.abs(off) <= 0.6).all(1)] = 0  # unstable fit: keep the integer position
        sigma = c["init_sigma"] * 2 ** ((li + off[:, 2]) / c["levels_per_octave"])
        px, py = x + off[:, 0], y + off[:, 1]
        # as the reference: half the measurement region must stay 5 px (octave pixels) inside the image
        half = 0.5 * c["mr_size"] * sigma
        h, w = r.shape[1:]
        inside = (px - half >= 5) & (px + half <= w - 6) & (py - half >= 5) & (py + half <= h - 6)
        step = 2.0**octave
        out = np.stack([px * step, py * step, sigma * step, v + 0.5 * (g * off).sum(1)], 1)
        return out[inside].astype(np.float32)

    # -- affine shape, orientation, descriptor ------------------------------------------------
    def adapt_shape(self, pyr: _Pyramid, frames: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """One Baumberg step: U <- U M^-1/2 from the gradient second moments of the patch, scale kept (upright result).

        All 2x2 algebra is written out on (n,) arrays: U = [[p, 0], [q, r]] is the upright frame.
        """
        u = upright(frames).astype(np.float64)
        t = torch.from_numpy(pyr.sample("tensor", u, xy, self.config["affine_patch"], self.config["affine_grid"]))
        ma, mb, mc = (t.transpose(1, 2) @ self._w_aff).double().numpy().T  # image-frame moments [[a, b], [b, c]]
        p, q, r = u[:, 0, 0], u[:, 1, 0], u[:, 1, 1]
        m = np.stack([p * p * ma + 2 * p * q * mb + q * q * mc, r * (p * mb + q * mc), r * r * mc], 1)  # U^T M U
        bad = (np.abs(m) < 1e-10 * max(float(np.abs(m).max()), 1e-30)).sum(1) >= 2
        m = m / np.maximum(m.max(1, keepdims=True), 1e-30)
        a, b, c = m[:, 0], m[:, 1], m[:, 2]
        bad |= ~(a * c - b * b > 1e-6)
        a, b, c = np.where(bad, 1.0, a), np.where(bad, 0.0, b), np.where(bad, 1.0, c)
        # lower-triangular Cholesky factor E of inv([[a, b], [b, c]]) (kornia ellipse_to_laf), then U E
        sc = np.sqrt(c)
        bs = b / sc
        schur = np.sqrt(a - bs * bs)
        e00, e10, e11 = 1 / schur, -bs / (sc * schur), 1 / sc
        o00, o10, o11 = p * e00, q * e00 + r * e10, r * e11
        f = frames.astype(np.float64)
        k = np.sqrt(np.abs(f[:, 0, 0] * f[:, 1, 1] - f[:, 0, 1] * f[:, 1, 0]) / np.abs(o00 * o11))  # keep the scale
        out = np.zeros_like(f)
        out[:, 0, 0], out[:, 1, 0], out[:, 1, 1] = k * o00, k * o10, k * o11
        return out.astype(np.float32)

    def orient(self, pyr: _Pyramid, frames: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """Dominant gradient direction (36-bin histogram, smoothed, parabolic peak): A <- A R(angle).

        The reference's window (sigma = 1/3 of the patch half-width) leaves the outer ring nearly
        unweighted, so only the central ``orientation_extent`` of the patch is sampled.
        """
        g, ext = self.config["orientation_grid"], self.config["orientation_extent"]
        u = upright(frames)
        f = ext * (g + 2) / g
        p = pyr.sample("image", u * f, xy, self.config["orientation_patch"] * f, g + 2).reshape(-1, g + 2, g + 2)
        ang = np.empty(len(p))
        launch(_orientation_kernel, p, self._w_ori, self._ang_smooth, ang)
        ca, sa = np.cos(ang), np.sin(ang)
        rot = np.stack([np.stack([ca, sa], 1), np.stack([-sa, ca], 1)], 1)
        return (u.astype(np.float64) @ rot).astype(np.float32)

    def describe(self, pyr: _Pyramid, frames: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """RootSIFT (kornia layout: angle-major 8 x 4 x 4) on the normalised patch (central differences, as kornia)."""
        g = self.config["descriptor_grid"]
        n = len(frames)
        p = pyr.sample("image", frames * ((g + 2) / g), xy, self.config["patch_size"], g + 2).reshape(n, g + 2, g + 2)
        out = np.empty((n, 128), np.float32)
        launch(_rootsift_kernel, p, self._w_desc, self._cell_idx, self._cell_w, out)
        return out


@numba.njit(inline="always")
def _reflect101(i, n):  # pragma: no cover - compiled
    """Row index with OpenCV's default border (BORDER_REFLECT_101: -1 -> 1, n -> n - 2)."""
    return -i if i < 0 else (2 * n - 2 - i if i >= n else i)


@numba.njit(parallel=True, fastmath=True, cache=True, boundscheck=False)
def _hessian_kernel(img, k, out):  # pragma: no cover - compiled
    """out = k^2 (Dxx Dyy - Dxy^2) with cv2.Sobel's 5x5 derivatives (reflect-101 border), one row per task.

    Separable: the three column filters (smoothing [1 4 6 4 1], first [-1 -2 0 2 1] and second
    [1 0 -2 0 1] derivative) run once per row into three buffers, then the row filters; nothing
    image-sized is written but the result (three cv2.Sobel calls and the products took 8x longer).
    """
    h, w = img.shape
    for y in numba.prange(h):
        r0, r1, r2 = img[_reflect101(y - 2, h)], img[_reflect101(y - 1, h)], img[y]
        r3, r4 = img[_reflect101(y + 1, h)], img[_reflect101(y + 2, h)]
        s, d1, d2 = np.empty(w + 4, np.float32), np.empty(w + 4, np.float32), np.empty(w + 4, np.float32)
        for x in range(w):
            s[x + 2] = (r0[x] + r4[x]) + 4 * (r1[x] + r3[x]) + 6 * r2[x]
            d1[x + 2] = (r4[x] - r0[x]) + 2 * (r3[x] - r1[x])
            d2[x + 2] = (r0[x] + r4[x]) - 2 * r2[x]
        for b in range(2):  # reflect-101 along the row
            s[1 - b], d1[1 - b], d2[1 - b] = s[3 + b], d1[3 + b], d2[3 + b]
            s[w + 2 + b], d1[w + 2 + b], d2[w + 2 + b] = s[w - b], d1[w - b], d2[w - b]
        o = out[y]
        for x in range(w):
            dxx = (s[x] + s[x + 4]) - 2 * s[x + 2]
            dyy = (d2[x] + d2[x + 4]) + 4 * (d2[x + 1] + d2[x + 3]) + 6 * d2[x + 2]
            dxy = (d1[x + 4] - d1[x]) + 2 * (d1[x + 3] - d1[x + 1])
            o[x] = k * k * (dxx * dyy - dxy * dxy)


@numba.njit(fastmath=True, cache=True, boundscheck=False)
def _maxima_kernel(r, threshold, out):  # pragma: no cover - compiled
    """(level, y, x) of every inner-level sample above threshold and >= its 26 neighbours (image
    borders excluded), level by level in row-major order; writes up to len(out), returns the count.

    The 3x3 test within the level runs branch-free over a whole row (it rejects ~96 % of the
    samples); only its survivors are compared with the levels above and below.
    """
    nl, h, w = r.shape
    n = 0
    flag = np.zeros(w, np.bool_)
    for i in range(1, nl - 1):
        for y in range(1, h - 1):
            a, b, c = r[i, y - 1], r[i, y], r[i, y + 1]
            for x in range(1, w - 1):
                v = b[x]
                flag[x] = ((v > threshold) & (v >= b[x - 1]) & (v >= b[x + 1]) & (v >= a[x - 1]) & (v >= a[x])
                           & (v >= a[x + 1]) & (v >= c[x - 1]) & (v >= c[x]) & (v >= c[x + 1]))
            for x in range(1, w - 1):
                if flag[x]:
                    v, ok = b[x], True
                    for dl in (-1, 1):
                        for dy in range(-1, 2):
                            for dx in range(-1, 2):
                                ok &= r[i + dl, y + dy, x + dx] <= v
                    if ok:
                        if n < out.shape[0]:
                            out[n, 0], out[n, 1], out[n, 2] = i, y, x
                        n += 1
    return n


@numba.njit(parallel=True, fastmath=True, cache=True, boundscheck=False)
def _orientation_kernel(p, window, smooth, out):  # pragma: no cover - compiled
    """Dominant gradient angle of every (g+2, g+2) patch, one keypoint per task.

    3x3 Sobel gradient, magnitude times the window, 36-bin linear-interpolated histogram (bin b
    centred on -pi + 2 pi b / 36), circular 5-tap smoothing, parabolic peak: out = -(peak - pi).
    """
    n, gp, _ = p.shape
    g = gp - 2
    nb = 36
    for i in numba.prange(n):
        pos = np.empty(g * g, np.float32)
        mag = np.empty(g * g, np.float32)
        for y in range(g):
            for x in range(g):
                gu = (p[i, y, x + 2] - p[i, y, x]) + (p[i, y + 2, x + 2] - p[i, y + 2, x]) + 2 * (p[i, y + 1, x + 2] - p[i, y + 1, x])
                gv = (p[i, y + 2, x] - p[i, y, x]) + (p[i, y + 2, x + 2] - p[i, y, x + 2]) + 2 * (p[i, y + 2, x + 1] - p[i, y, x + 1])
                mag[y * g + x] = math.sqrt(gu * gu + gv * gv) * window[y * g + x]
                pos[y * g + x] = _bin_position(gu, gv, nb)
        h = np.zeros(nb + 1, np.float32)
        for s in range(g * g):
            b0 = int(pos[s])
            w1 = (pos[s] - b0) * mag[s]
            h[b0] += mag[s] - w1
            h[b0 + 1] += w1
        h[0] += h[nb]  # the wrap bin
        sm = np.zeros(nb, np.float32)
        for b in range(nb):
            for t in range(smooth.shape[0]):
                sm[b] += smooth[t] * h[(b + t - smooth.shape[0] // 2) % nb]
        idx = 0
        for b in range(1, nb):
            if sm[b] > sm[idx]:
                idx = b
        left, right, val = sm[(idx - 1) % nb], sm[(idx + 1) % nb], sm[idx]
        den = left + right - 2 * val
        sub = 0.5 * (left - right) / den if den != 0 else 0.0
        out[i] = -(2 * math.pi * (idx + sub) / nb - math.pi)


@numba.njit(parallel=True, fastmath=True, cache=True, boundscheck=False)
def _rootsift_kernel(p, window, cell_idx, cell_w, out):  # pragma: no cover - compiled
    """RootSIFT of every (g+2, g+2) patch, one keypoint per task, no (n, bins, g*g) intermediate.

    Per sample: central-difference gradient, magnitude times the Gaussian window, linear split
    between two of 8 orientation bins (bin b centred on -pi + 2 pi b / 8), triangular split
    among the <= 4 spatial cells (kornia SIFTDescriptor's pooling). Then kornia's layout (bin 0
    at angle 0, angle-major), L2 / clip 0.2 / L2, and RootSIFT (L1, sqrt, L2).
    """
    n, gp, _ = p.shape
    g = gp - 2
    nb = 8
    ncell = out.shape[1] // nb
    for i in numba.prange(n):
        pos = np.empty(g * g, np.float32)  # orientation in bin units, [0, nb)
        mag = np.empty(g * g, np.float32)
        for y in range(g):
            for x in range(g):  # vectorised: no calls, no scatter
                gu = p[i, y + 1, x + 2] - p[i, y + 1, x]
                gv = p[i, y + 2, x + 1] - p[i, y, x + 1]
                mag[y * g + x] = math.sqrt(gu * gu + gv * gv) * window[y * g + x]
                pos[y * g + x] = _bin_position(gu, gv, nb)
        h = np.zeros((ncell, nb + 1), np.float32)
        for s in range(g * g):
            b0 = int(pos[s])
            w1 = (pos[s] - b0) * mag[s]
            w0 = mag[s] - w1
            for q in range(cell_idx.shape[1]):
                c, cw = cell_idx[s, q], cell_w[s, q]
                h[c, b0] += w0 * cw
                h[c, b0 + 1] += w1 * cw
        d = out[i]
        for c in range(ncell):
            h[c, 0] += h[c, nb]  # the wrap bin
            for b in range(nb):
                d[((b - nb // 2) % nb) * ncell + c] = h[c, b]  # roll: bin 0 at angle 0, angle-major
        _scale(d, 1.0 / max(math.sqrt((d * d).sum()), 1e-12))
        for j in range(d.shape[0]):
            d[j] = min(max(d[j], 0.0), 0.2)
        _scale(d, 1.0 / max(math.sqrt((d * d).sum()), 1e-12))
        _scale(d, 1.0 / max(np.abs(d).sum(), 1e-12))
        for j in range(d.shape[0]):
            d[j] = math.sqrt(d[j] + 1e-10)
        _scale(d, 1.0 / max(math.sqrt((d * d).sum()), 1e-12))


@numba.njit(inline="always")
def _bin_position(gu, gv, nb):  # pragma: no cover - compiled
    """Angle of the gradient (gu, gv) in histogram-bin units, in [0, nb): bin b is centred on
    -pi + 2 pi b / nb (shared by the orientation and descriptor histograms)."""
    return min((_atan2(gv, gu) + math.pi) * (nb / (2 * math.pi)), nb - 1e-4)


@numba.njit(inline="always")
def _atan2(y, x):  # pragma: no cover - compiled
    """atan2 from the Abramowitz & Stegun 4.4.49 polynomial (|error| <= 2e-8 rad): inlined and
    vectorised, where a libm call per sample costs ~30 ns."""
    ax, ay = abs(x), abs(y)
    hi, lo = max(ax, ay), min(ax, ay)
    z = lo / hi if hi > 0 else np.float32(0.0)
    z2 = z * z
    r = z * (0.9999993329 + z2 * (-0.3332985605 + z2 * (0.1994653599 + z2 * (-0.1390853351 + z2 * (
        0.0964200441 + z2 * (-0.0559098861 + z2 * (0.0218612288 + z2 * -0.0040540580)))))))
    r = 0.5 * math.pi - r if ay > ax else r
    r = math.pi - r if x < 0 else r
    return -r if y < 0 else r


@numba.njit(inline="always")
def _scale(d, f):  # pragma: no cover - compiled
    for j in range(d.shape[0]):
        d[j] *= f


"""NM-Net (Zhao et al., CVPR 2019): correspondence classifier on compatibility-specific neighbours.

Input: N correspondences as 4-D normalised coordinates (x, y, x', y') and, per correspondence,
the indices of its k neighbours (itself first); ``ratio_input`` (not in the paper, off in the shipped
weights) adds each match's descriptor distance ratio as a fifth input. Output: one logit per correspondence.
C(32,1,4) embedding -> grouping (N x k map) -> 8 ResNet blocks with (1,3) convolutions along
the neighbour axis, stride 2 where the width doubles (k: 8 -> 4 -> 2 -> 1) -> 1x1 head.
Every convolution is followed by InstanceNorm (over the correspondences: global context),
BatchNorm and ReLU.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

DEFAULT_CONFIG: dict = {
    "k": 8,
    "widths": (32, 32, 64, 64, 128, 128, 256, 256),
    "neighbors": "compatibility",  # or "spatial" for NM-Net-sp
    "ratio_input": False,  # True: a fifth input per match, its descriptor distance ratio (not in the paper)
}
NEIGHBORS = {"nmnet": "compatibility", "nmnet-sp": "spatial"}  # each variant's neighbours (paper: NM-Net, NM-Net-sp)


def input_width(config: dict) -> int:
    """Inputs per correspondence: the paper's 4 coordinates, plus the ratio when ``ratio_input``."""
    return 5 if config["ratio_input"] else 4


def network_input(x0: np.ndarray, x1: np.ndarray, ratio: np.ndarray, config: dict) -> torch.Tensor:
    """(N, input_width) float32 input rows: normalised (x, y, x', y') and, when the config asks, the ratio."""
    cols = [x0, x1, ratio[:, None]] if config["ratio_input"] else [x0, x1]
    return torch.from_numpy(np.concatenate(cols, 1).astype(np.float32))


def _norm_act(c: int, act: bool = True) -> nn.Sequential:
    layers: list[nn.Module] = [nn.InstanceNorm2d(c, eps=1e-3), nn.BatchNorm2d(c)]
    if act:
        layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


class ResBlock(nn.Module):
    """Two (1,3) convolutions along the neighbour axis with IN+BN(+ReLU), residual shortcut."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        stride = (1, 2) if cout != cin else (1, 1)
        self.conv1 = nn.Conv2d(cin, cout, (1, 3), stride=stride, padding=(0, 1))
        self.norm1 = _norm_act(cout)
        self.conv2 = nn.Conv2d(cout, cout, (1, 3), padding=(0, 1))
        self.norm2 = _norm_act(cout, act=False)
        self.shortcut = nn.Conv2d(cin, cout, 1, stride=stride) if cout != cin else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, N, k) -> (B, C', N, k / stride): two convolutions, each normalised, plus the shortcut."""
        y = self.norm2(self.conv2(self.norm1(self.conv1(x))))
        return torch.relu(y + self.shortcut(x))


class NMNet(nn.Module):
    """NM-Net; the same class is NM-Net-sp when fed spatial neighbours."""

    def __init__(self, config: dict | None = None) -> None:
        super().__init__()
        self.config = {**DEFAULT_CONFIG, **(config or {})}
        self.score_threshold = 0.5  # probability cut; load_model sets the calibrated one
        self.calibrated = False  # whether score_threshold came from nmnet train's calibration
        w = list(self.config["widths"])
        self.embed = nn.Sequential(nn.Conv2d(1, w[0], (1, input_width(self.config))), _norm_act(w[0]))
        self.blocks = nn.Sequential(*[ResBlock(a, b) for a, b in zip([w[0]] + w[:-1], w, strict=True)])
        self.head = nn.Sequential(nn.Conv2d(w[-1], w[-1], 1), _norm_act(w[-1]), nn.Conv2d(w[-1], 1, 1))

    def forward(self, corr: torch.Tensor, neighbors: torch.Tensor) -> torch.Tensor:
        """corr (B,N,4 or 5) rows of ``network_input``, neighbors (B,N,k) indices -> logits (B,N)."""
        b, n, _ = corr.shape
        k = neighbors.shape[-1]
        f = self.embed(corr[:, None])  # (B,C,N,1)
        c = f.shape[1]
        idx = neighbors.reshape(b, 1, n * k).expand(b, c, n * k)
        g = torch.gather(f[..., 0], 2, idx).view(b, c, n, k)  # grouping: (B,C,N,k)
        g = self.blocks(g)
        if g.shape[-1] != 1:
            g = g.mean(-1, keepdim=True)  # only when k is not 8: keep one vector per correspondence
        return self.head(g)[:, 0, :, 0]


class WeightsError(ValueError):
    """A weights file is missing, unreadable or does not fit the network."""


def weights_dir() -> Path:
    """The package's shipped weights."""
    return Path(__file__).parents[1] / "weights"


def _load_failure(e: Exception) -> str:
    """torch.load's reason, in a line. Its weights-only refusal opens with advice to load the file unsafely
    (weights_only=False runs any code the file holds): not given here, the cause is."""
    text = str(e).strip()
    if "WeightsUnpickler error:" in text:
        cause = text.split("WeightsUnpickler error:", 1)[1].strip().splitlines()[0]
        return f"torch.load, loading weights only: {cause}: it holds more than tensors and numbers, or is no PyTorch file"
    return f"torch.load: {text.splitlines()[0] if text else type(e).__name__}"


def load_model(path: str | Path | None = None, variant: str = "nmnet") -> NMNet:
    """Build NM-Net and load weights (default: the shipped ones for ``variant``), eval mode."""
    path = Path(path) if path is not None else weights_dir() / f"{variant}.pt"
    if path.is_dir():  # a training run's folder (nmnet train --out) rather than its checkpoint
        inside = [p.name for p in sorted(path.glob("*.pt"))]
        hint = f"give {path / 'best.pt'}, the run's chosen weights" if "best.pt" in inside else (
            f"give one of its checkpoints ({', '.join(inside)})" if inside else "it holds no checkpoint (.pt)")
        raise WeightsError(f"{path}: a folder, not a weights file; {hint}")
    if not path.is_file():
        raise WeightsError(f"{path}: weights file not found")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch raises many types for bad files
        raise WeightsError(f"{path}: cannot read weights: not a checkpoint written by `nmnet train` (the shipped "
                           f"nmnet_ros/weights/nmnet.pt is one), or a damaged one ({_load_failure(e)})") from e
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt:
        raise WeightsError(f"{path}: not an NM-Net checkpoint (no 'state_dict')")
    model = NMNet(ckpt.get("config"))
    try:
        model.load_state_dict(ckpt["state_dict"])
    except RuntimeError as e:
        raise WeightsError(f"{path}: weights do not fit NM-Net: {str(e).splitlines()[0]}") from e
    model.score_threshold = float(ckpt.get("score_threshold", 0.5))  # calibrated on validation by nmnet train
    model.calibrated = "score_threshold" in ckpt
    return model.eval()

"""LPIPS and ST-LPIPS with an AlexNet trunk, in plain torch.

Why a reimplementation: the reference packages (``lpips`` 0.1.4 and ``stlpips-pytorch`` 0.0.2)
import torchvision (and IPython / torchsummary) at module level, and torchvision does not import
in this environment. Only their weight files are used here, located through
``importlib.util.find_spec`` without importing the packages. The layer layout and the parameter
names below copy the reference modules exactly (``lpips/pretrained_networks.py::alexnet``,
``stlpips_pytorch/invariant_networks.py::alexnet(variant="shift_tolerant")``,
``models_lpf/downsample.py::Downsample``), so their state dicts load with ``strict=True``.

Weight sources (never downloaded):
- ST-LPIPS: ``stlpips_pytorch/weights/vST0.0/alex_shift_tolerant.pth`` holds the complete network
  (scaling layer, the blur-pool trunk and the five linear layers).
- LPIPS v0.1: the linear layers from ``lpips/weights/v0.1/alex.pth`` plus torchvision's ImageNet
  AlexNet (``alexnet-owt-7be5be79.pth``) from the torch hub cache or an explicit path.
"""

from __future__ import annotations

import functools
import importlib.util
import logging
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from difftex.errors import DifftexError

log = logging.getLogger(__name__)

ALEXNET_CHECKPOINT = "alexnet-owt-7be5be79.pth"
CHANNELS = (64, 192, 384, 256, 256)
MIN_SIDE = 32  # smallest image side both trunks accept (classic AlexNet: conv1 must give >= 7)


class ScalingLayer(nn.Module):
    """LPIPS v0.1 input normalisation: ([-1,1] image - shift) / scale, ImageNet statistics."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188])[None, :, None, None])
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450])[None, :, None, None])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.shift) / self.scale


class BlurDownsample(nn.Module):
    """Anti-aliased stride-2 downsampling: reflect-pad, [1,2,1]^2/16 depthwise blur, subsample.

    ``pad_more`` (ST-LPIPS) pads filt_size-1 = 2 on every side instead of 1.
    """

    def __init__(self, channels: int, filt_size: int = 3, stride: int = 2, pad_more: bool = True) -> None:
        super().__init__()
        if filt_size != 3:
            raise ValueError("only the 3-tap blur filter of ST-LPIPS is implemented")
        a = torch.tensor([1.0, 2.0, 1.0], dtype=torch.float64)
        filt = (a[:, None] * a[None, :]) / (a.sum() ** 2)
        # The reference saves the filter as a persistent buffer named ``filt``; keep both.
        self.register_buffer("filt", filt.float()[None, None].repeat(channels, 1, 1, 1))
        pad = filt_size - 1 if pad_more else (filt_size - 1) // 2
        self.pad = (pad, pad, pad, pad)
        self.stride = stride

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.pad(x, self.pad, mode="reflect")
        return F.conv2d(x, self.filt, stride=self.stride, groups=x.shape[1])


def _seq(layers: dict[int, nn.Module]) -> nn.Sequential:
    return nn.Sequential(OrderedDict((str(i), m) for i, m in layers.items()))


class AlexTrunk(nn.Module):
    """AlexNet feature slices ending at relu1..relu5, indices as in the reference packages."""

    def __init__(self, shift_tolerant: bool) -> None:
        super().__init__()
        relu = lambda: nn.ReLU(inplace=False)  # noqa: E731
        if shift_tolerant:
            # invariant_networks.alexnet(variant="shift_tolerant"): stride-1 first conv, every
            # stride-2 step replaced by max (stride 1) + blur-pool with extra reflect padding.
            self.slice1 = _seq({0: nn.Conv2d(3, 64, 11, stride=1, padding=2), 1: BlurDownsample(64), 2: relu()})
            self.slice2 = _seq({3: nn.MaxPool2d(3, stride=1), 4: BlurDownsample(64),
                                5: nn.Conv2d(64, 192, 5, padding=2), 6: relu()})
            self.slice3 = _seq({7: nn.MaxPool2d(3, stride=1), 8: BlurDownsample(192),
                                9: nn.Conv2d(192, 384, 3, padding=1), 10: relu()})
            self.slice4 = _seq({11: nn.Conv2d(384, 256, 3, padding=1), 12: relu()})
            self.slice5 = _seq({13: nn.Conv2d(256, 256, 3, padding=1), 14: relu()})
        else:
            # torchvision.models.alexnet().features[0:12], sliced as lpips.pretrained_networks.alexnet.
            self.slice1 = _seq({0: nn.Conv2d(3, 64, 11, stride=4, padding=2), 1: relu()})
            self.slice2 = _seq({2: nn.MaxPool2d(3, stride=2), 3: nn.Conv2d(64, 192, 5, padding=2), 4: relu()})
            self.slice3 = _seq({5: nn.MaxPool2d(3, stride=2), 6: nn.Conv2d(192, 384, 3, padding=1), 7: relu()})
            self.slice4 = _seq({8: nn.Conv2d(384, 256, 3, padding=1), 9: relu()})
            self.slice5 = _seq({10: nn.Conv2d(256, 256, 3, padding=1), 11: relu()})

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        feats = []
        for s in (self.slice1, self.slice2, self.slice3, self.slice4, self.slice5):
            x = s(x)
            feats.append(x)
        return feats


class NetLinLayer(nn.Module):
    """1x1 conv without bias; index 0 stands for the reference's Dropout (identity at eval)."""

    def __init__(self, chn_in: int) -> None:
        super().__init__()
        self.model = nn.Sequential(nn.Identity(), nn.Conv2d(chn_in, 1, 1, bias=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model(x)


def _normalize_tensor(x: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    return x / (torch.sqrt(torch.sum(x**2, dim=1, keepdim=True)) + eps)


class LPIPSNet(nn.Module):
    """LPIPS v0.1 distance with the AlexNet trunk (classic or shift-tolerant)."""

    def __init__(self, shift_tolerant: bool) -> None:
        super().__init__()
        self.scaling_layer = ScalingLayer()
        self.net = AlexTrunk(shift_tolerant)
        for i, c in enumerate(CHANNELS):
            setattr(self, f"lin{i}", NetLinLayer(c))
        self.eval()
        self.requires_grad_(False)

    def layer_maps(self, a: torch.Tensor, b: torch.Tensor) -> list[torch.Tensor]:
        """Per-layer distance maps (N,1,h_l,w_l) for images (N,3,H,W) in [0,1]."""
        fa = self.net(self.scaling_layer(2 * a - 1))
        fb = self.net(self.scaling_layer(2 * b - 1))
        return [getattr(self, f"lin{i}")((_normalize_tensor(x) - _normalize_tensor(y)) ** 2)
                for i, (x, y) in enumerate(zip(fa, fb))]

    def forward(self, a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Distance per batch item (N,). ``mask`` (N,1,H,W) bool: average the spatial map over it."""
        maps = self.layer_maps(a, b)
        if mask is None:
            return sum(m.mean(dim=(1, 2, 3)) for m in maps)
        # As the reference's spatial=True mode: each layer map upsampled bilinearly to the input.
        full = sum(F.interpolate(m, size=a.shape[2:], mode="bilinear", align_corners=False) for m in maps)
        w = mask.to(full.dtype)
        return (full * w).sum(dim=(1, 2, 3)) / w.sum(dim=(1, 2, 3))


# --- weight discovery -------------------------------------------------------------------------


def _package_dir(name: str) -> Path | None:
    """Folder of an installed package, found without importing it (its imports fail here)."""
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0])


def stlpips_weights_path() -> Path | None:
    d = _package_dir("stlpips_pytorch")
    p = d / "weights" / "vST0.0" / "alex_shift_tolerant.pth" if d else None
    return p if p is not None and p.is_file() else None


def lpips_linear_weights_path() -> Path | None:
    d = _package_dir("lpips")
    p = d / "weights" / "v0.1" / "alex.pth" if d else None
    return p if p is not None and p.is_file() else None


def alexnet_weights_path(explicit: str | Path | None = None) -> Path | None:
    """torchvision's ImageNet AlexNet: ``explicit`` if given, else the torch hub cache."""
    if explicit is not None:
        p = Path(explicit)
        return p if p.is_file() else None
    p = Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_CHECKPOINT
    return p if p.is_file() else None


@dataclass(frozen=True)
class WeightSource:
    variant: str  # "lpips" or "stlpips"
    paths: tuple[Path, ...]


def find_weights(variant: str = "auto", alexnet_path: str | Path | None = None,
                 stlpips_path: str | Path | None = None) -> tuple[WeightSource | None, str]:
    """Pick the weights for ``variant`` ("auto" | "lpips" | "stlpips"); (None, reason) if missing."""
    if variant not in ("auto", "lpips", "stlpips"):
        raise DifftexError(f"LPIPS variant {variant!r} unknown (auto, lpips, stlpips)")
    reasons = []
    if variant in ("auto", "lpips"):
        lin, trunk = lpips_linear_weights_path(), alexnet_weights_path(alexnet_path)
        if lin is not None and trunk is not None:
            return WeightSource("lpips", (trunk, lin)), ""
        if lin is None:
            reasons.append("lpips package weights lpips/weights/v0.1/alex.pth not installed")
        if trunk is None:
            where = alexnet_path or Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_CHECKPOINT
            reasons.append(f"torchvision AlexNet weights not found at {where}")
    if variant in ("auto", "stlpips"):
        st = Path(stlpips_path) if stlpips_path is not None else stlpips_weights_path()
        if st is not None and st.is_file():
            return WeightSource("stlpips", (st,)), ""
        reasons.append(f"ST-LPIPS weights not found ({st or 'stlpips-pytorch not installed'})")
    return None, "; ".join(reasons)


def _torch_load(path: Path) -> dict[str, torch.Tensor]:
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is a bad weight file
        raise DifftexError(f"{path}: unreadable torch weight file ({exc.__class__.__name__})") from None
    if not isinstance(sd, dict):
        raise DifftexError(f"{path}: not a state dict")
    return sd


def _trunk_index_to_slice(shift_tolerant: bool) -> dict[int, int]:
    net = AlexTrunk(shift_tolerant)
    return {int(name): k + 1 for k, s in enumerate((net.slice1, net.slice2, net.slice3, net.slice4, net.slice5))
            for name, _ in s.named_children()}


def classic_state_dict(alexnet_file: Path, lin_file: Path) -> dict[str, torch.Tensor]:
    """Assemble the LPIPS v0.1 state dict from torchvision's AlexNet and lpips' linear layers."""
    trunk = _torch_load(alexnet_file)
    slot = _trunk_index_to_slice(False)
    sd: dict[str, torch.Tensor] = {}
    for key, val in trunk.items():
        if not key.startswith("features."):
            continue  # classifier layers are not part of LPIPS
        idx, rest = key[len("features."):].split(".", 1)
        if int(idx) not in slot:
            raise DifftexError(f"{alexnet_file}: unexpected AlexNet layer {key}")
        sd[f"net.slice{slot[int(idx)]}.{idx}.{rest}"] = val
    sd.update(_torch_load(lin_file))
    scaling = ScalingLayer()
    sd.setdefault("scaling_layer.shift", scaling.shift)
    sd.setdefault("scaling_layer.scale", scaling.scale)
    return sd


@functools.lru_cache(maxsize=4)
def load_network(source: WeightSource, device: str = "cpu") -> LPIPSNet:
    """Build and load a network; cached per weight files and device (strict loading)."""
    if source.variant == "stlpips":
        net, sd = LPIPSNet(shift_tolerant=True), _torch_load(source.paths[0])
    else:
        net, sd = LPIPSNet(shift_tolerant=False), classic_state_dict(*source.paths)
    try:
        net.load_state_dict(sd, strict=True)
    except RuntimeError as exc:
        first = str(exc).splitlines()[1].strip() if len(str(exc).splitlines()) > 1 else str(exc)
        raise DifftexError(f"{source.paths[0]}: weights do not fit the {source.variant} AlexNet ({first})") from None
    return net.to(device)


def _to_tensor(img: np.ndarray, device: str) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(img, dtype=np.float32)).permute(2, 0, 1)[None].to(device)


def distance(net: LPIPSNet, img_a: np.ndarray, img_b: np.ndarray, mask: np.ndarray | None = None,
             device: str = "cpu") -> float:
    """LPIPS distance between two (H,W,3) float images in [0,1], optionally averaged over a mask."""
    if min(img_a.shape[:2]) < MIN_SIDE:
        raise DifftexError(f"LPIPS needs images of at least {MIN_SIDE}x{MIN_SIDE} pixels, got "
                           f"{img_a.shape[1]}x{img_a.shape[0]}")
    with torch.no_grad():
        a, b = _to_tensor(img_a, device), _to_tensor(img_b, device)
        m = None if mask is None else torch.from_numpy(np.asarray(mask, bool))[None, None].to(device)
        return float(net(a, b, m)[0])

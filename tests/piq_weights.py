"""Stand-ins for classic LPIPS's two weight files (tests only): random tensors of the shapes of
piq's ``lpips_weights.pt`` and torchvision's ``vgg16-397923af.pth``, so that the piq path runs
offline. Nothing here is ever downloaded, and the values mean nothing perceptually."""

from __future__ import annotations

import math
from pathlib import Path

import torch

LPIPS_FILE = "lpips_weights.pt"  # piq.LPIPS._weights_url's file name
VGG16_FILE = "vgg16-397923af.pth"  # torchvision's VGG16_Weights.IMAGENET1K_V1
CHANNELS = (64, 128, 256, 512, 512)  # VGG16's relu1_2 ... relu5_3


def write_piq_weights(folder: Path, seed: int = 0) -> Path:
    """Write both files into ``folder``: the VGG16 file holds only the ``features.*`` tensors
    (59 MB; the real file's classifier, 470 MB more, is not read by difftex)."""
    from torchvision.models import vgg16

    folder.mkdir(parents=True, exist_ok=True)
    gen = torch.Generator().manual_seed(seed)
    with torch.device("meta"):
        shapes = {f"features.{k}": v.shape for k, v in vgg16(weights=None).features.state_dict().items()}
    sd = {}
    for key, shape in shapes.items():
        if len(shape) == 4:  # conv weight: He-scaled, so that the activations neither vanish nor explode
            sd[key] = torch.randn(shape, generator=gen) * math.sqrt(2.0 / math.prod(shape[1:]))
        else:
            sd[key] = 0.01 * torch.randn(shape, generator=gen)
    torch.save(sd, folder / VGG16_FILE)
    torch.save([torch.rand(1, c, 1, 1, generator=gen) for c in CHANNELS], folder / LPIPS_FILE)
    return folder

"""Which LPIPS network, built offline from which weight files: classic LPIPS through piq, or ST-LPIPS.

:func:`difftex.evaluation.metrics.lpips` computes the distance with the network this module
resolves and builds. Classic LPIPS is ``piq.LPIPS`` (VGG16), made from piq's and torchvision's
weight files in the torch hub cache or a configured folder (:func:`lpips_weight_files`); piq's own
constructor would download them, so it is rebuilt here from piq's parts. ST-LPIPS is
``stlpips_pytorch``'s shift-tolerant AlexNet, whose weights ship in its wheel. Nothing is ever
downloaded; docs/metrics.md says which files go where.
"""

from __future__ import annotations

import functools
import importlib.metadata
import warnings
from pathlib import Path

from difftex.errors import DifftexError

LPIPS_VARIANTS = ("auto", "lpips", "stlpips")
LPIPS_MIN_SIDE = 32  # smallest side the networks accept (four / five poolings of stride 2)
# piq.LPIPS: VGG16's relu1_2 ... relu5_3 (torchvision ``features`` indices 3, 8, 15, 22, 29) and
# their channel counts, which piq's linear weights must match
PIQ_LPIPS_LAYERS = ("relu1_2", "relu2_2", "relu3_3", "relu4_3", "relu5_3")
PIQ_LPIPS_CHANNELS = (64, 128, 256, 512, 512)


def lpips_weight_files(weights_dir: str | Path | None = None) -> dict[str, Path]:
    """The two files classic LPIPS through piq reads, in ``weights_dir`` or the torch hub cache.

    ``{"lpips": <dir>/lpips_weights.pt, "vgg16": <dir>/vgg16-397923af.pth}``: piq's linear layer
    weights (``piq.LPIPS._weights_url``'s file) and torchvision's ImageNet VGG16
    (``VGG16_Weights.IMAGENET1K_V1``), under the names ``piq.LPIPS()`` itself downloads them to,
    ``$TORCH_HOME/hub/checkpoints/`` (default ``~/.cache/torch/hub/checkpoints/``).
    """
    import torch
    from piq import LPIPS
    from torchvision.models import VGG16_Weights

    folder = Path(weights_dir).expanduser() if weights_dir is not None else Path(torch.hub.get_dir()) / "checkpoints"
    return {
        "lpips": folder / Path(LPIPS._weights_url).name,
        "vgg16": folder / Path(VGG16_Weights.IMAGENET1K_V1.url).name,
    }


def _import_error(module: str) -> str | None:
    """None if ``module`` imports, else why not (one line)."""
    import importlib

    try:
        importlib.import_module(module)
    except Exception as exc:  # noqa: BLE001 - any failure at import means the package is unusable
        return f"{module} does not import ({exc.__class__.__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
    return None


def classic_lpips_missing(weights_dir: str | Path | None = None) -> str | None:
    """Why classic LPIPS (piq) cannot run offline here, or None when it can."""
    why = _import_error("piq")
    if why is not None:
        return why
    files = lpips_weight_files(weights_dir)
    missing = [p.name for p in files.values() if not p.is_file()]
    if not missing:
        return None
    return (f"classic LPIPS (piq) needs {' and '.join(p.name for p in files.values())} in "
            f"{files['lpips'].parent} (missing: {', '.join(missing)}; never downloaded)")


def lpips_source(variant: str = "auto", weights_dir: str | Path | None = None) -> tuple[str | None, str]:
    """The network ``variant`` resolves to offline and its label: ("lpips" | "stlpips", label).

    ``"auto"`` is classic LPIPS (piq) when both of its weight files are on disk
    (:func:`lpips_weight_files`), else ST-LPIPS. When nothing fits: (None, "unavailable: <why>").
    Nothing is downloaded.
    """
    if variant not in LPIPS_VARIANTS:
        raise DifftexError(f"LPIPS variant {variant!r} unknown ({', '.join(LPIPS_VARIANTS)})")
    reasons = []
    if variant in ("auto", "lpips"):
        why = classic_lpips_missing(weights_dir)
        if why is None:
            files = lpips_weight_files(weights_dir)
            return "lpips", (f"LPIPS (piq {importlib.metadata.version('piq')}, VGG16: torchvision ImageNet weights "
                             f"{files['vgg16'].name} + piq linear weights {files['lpips'].name})")
        reasons.append(why)
    if variant in ("auto", "stlpips"):
        why = _import_error("stlpips_pytorch.stlpips")
        if why is None:
            return "stlpips", (f"ST-LPIPS (stlpips-pytorch {importlib.metadata.version('stlpips_pytorch')}, "
                               "alex shift-tolerant weights vST0.0)")
        reasons.append(why)
    return None, "unavailable: " + "; ".join(reasons)


def lpips_fallback_note(weights_dir: str | Path | None = None) -> str:
    """The one line that says ``"auto"`` reports ST-LPIPS because classic LPIPS cannot run."""
    return (f"LPIPS (auto): {classic_lpips_missing(weights_dir)}; reporting ST-LPIPS instead, whose values are "
            "not comparable (evaluate.lpips_weights names a folder holding both files; evaluate.lpips: stlpips "
            "chooses ST-LPIPS without this note)")


def _torch_load(path: Path, kind: type = dict):
    import torch

    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is a bad weight file
        raise DifftexError(f"{path}: unreadable torch weight file ({exc.__class__.__name__})") from None
    if not isinstance(data, kind):
        raise DifftexError(f"{path}: not a {'state dict' if kind is dict else 'list of tensors'}")
    return data


def _check_weights_loaded(net, path: Path, prefixes: tuple[str, ...]) -> None:
    """Raise unless ``path`` holds exactly the parameters of ``net`` under ``prefixes``.

    stlpips-pytorch loads its weight file with ``strict=False``, which would leave a mismatching
    layer at its random initialisation without a word.
    """
    have = set(_torch_load(path))
    # named_parameters/buffers name each tensor once (the package also lists lin0..4 as lins.0..4).
    want = {k for k, _ in [*net.named_parameters(), *net.named_buffers()] if k.startswith(prefixes)}
    if have != want:
        diff = sorted(want - have)[:2] + sorted(have - want)[:2]
        raise DifftexError(f"{path}: weights do not fit the network (differing keys: {', '.join(diff)})")


def _vgg16_features(path: Path):
    """torchvision's VGG16 ``features`` with the ``features.*`` tensors of ``path`` (strictly).

    The classifier's tensors of the file (90% of it) are not needed and not allocated.
    """
    import torch
    from torchvision.models import vgg16

    with torch.device("meta"):
        features = vgg16(weights=None).features
    sd = {k.removeprefix("features."): v for k, v in _torch_load(path).items() if k.startswith("features.")}
    features = features.to_empty(device="cpu")
    try:
        features.load_state_dict(sd, strict=True)
    except RuntimeError as exc:
        first = next((ln.strip() for ln in str(exc).splitlines()[1:] if ln.strip()), str(exc))
        raise DifftexError(f"{path}: not torchvision's VGG16 weights ({first[:120]})") from None
    return features


def _piq_linear_weights(path: Path) -> list:
    """piq's LPIPS layer weights from ``path``: five tensors of 64, 128, 256, 512, 512 values,
    shaped (1, C, 1, 1) to scale each layer's squared feature differences per channel."""
    data = _torch_load(path, (list, tuple))
    sizes = [int(getattr(w, "numel", lambda: -1)()) for w in data]
    if sizes != list(PIQ_LPIPS_CHANNELS):
        raise DifftexError(f"{path}: not piq's LPIPS weights (expected {len(PIQ_LPIPS_CHANNELS)} tensors of "
                           f"{', '.join(map(str, PIQ_LPIPS_CHANNELS))} values, got sizes {sizes})")
    return [w.float().reshape(1, -1, 1, 1) for w in data]


def _piq_lpips(weights_dir: str | None):
    """``piq.LPIPS()`` (reduction "none") built from the local files, never downloading.

    piq.LPIPS's own constructor fetches both files through ``torch.hub`` (a download when they are
    not in the hub cache); this builds the same network, piq's ``ContentLoss`` with piq's LPIPS
    arguments, from :func:`lpips_weight_files` (tests/test_metrics.py checks it against
    ``piq.LPIPS`` itself).
    """
    from piq import ContentLoss
    from piq.perceptual import IMAGENET_MEAN, IMAGENET_STD, VGG16_LAYERS

    files = lpips_weight_files(weights_dir)
    return ContentLoss(_vgg16_features(files["vgg16"]), layers=[VGG16_LAYERS[n] for n in PIQ_LPIPS_LAYERS],
                       weights=_piq_linear_weights(files["lpips"]), replace_pooling=False, distance="mse",
                       reduction="none", mean=IMAGENET_MEAN, std=IMAGENET_STD, normalize_features=True)


class _PiqLpips:
    """piq's LPIPS with the call of the ST-LPIPS network: ``(a, b, normalize=True)``, inputs in
    [0, 1]; the plain distance (piq's own forward), or with ``spatial`` the per-pixel map: each
    layer's weighted squared differences summed over channels and upsampled bilinearly to the
    input size (as the lpips reference package's ``spatial=True``), summed over the layers."""

    def __init__(self, net, spatial: bool):
        self.net, self.spatial = net, spatial

    def to(self, device):
        self.net = self.net.to(device)
        return self

    def __call__(self, a, b, normalize: bool = True):
        import torch.nn.functional as F

        if not self.spatial:
            return self.net(a, b)  # piq's LPIPS: spatial mean of each layer, summed
        fa, fb = self.net.get_features(a), self.net.get_features(b)
        out = 0
        for d, w in zip(self.net.compute_distance(fa, fb), self.net.weights):
            layer = (d * w.to(d)).sum(dim=1, keepdim=True)
            out = out + F.interpolate(layer, size=a.shape[2:], mode="bilinear", align_corners=False)
        return out


@functools.lru_cache(maxsize=8)
def network(kind: str, weights_dir: str | None, spatial: bool, device: str):
    """The network, built once per process per (weights folder, mode, device).

    ``spatial``: the per-pixel distance map (every layer's map upsampled bilinearly to the input
    size) instead of the mean.
    """
    if kind == "lpips":
        net = _piq_lpips(weights_dir).eval().requires_grad_(False)
        return _PiqLpips(net, spatial).to(device)
    with warnings.catch_warnings():
        # stlpips-pytorch calls torchvision's models with pretrained=, deprecated since 0.13.
        warnings.filterwarnings("ignore", category=UserWarning, module="torchvision")
        from stlpips_pytorch import stlpips

        net = stlpips.LPIPS(net="alex", variant="shift_tolerant", spatial=spatial, verbose=False)
        path = Path(stlpips.__file__).parent / "weights" / "vST0.0" / "alex_shift_tolerant.pth"
        _check_weights_loaded(net, path, ("",))
    return net.eval().requires_grad_(False).to(device)

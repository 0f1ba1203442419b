"""Which LPIPS network, built from which weight files: classic LPIPS through piq, or ST-LPIPS.

:func:`difftex.evaluation.metrics.lpips` computes the distance with the network this module
resolves and builds. Classic LPIPS is ``piq.LPIPS`` (VGG16), made from piq's and torchvision's
weight files in the torch hub cache or a configured folder (:func:`lpips_weight_files`). When
they are not in the hub cache, they are downloaded there once, as ``piq.LPIPS()`` would
(:func:`fetch_hub_weights`: a one-line notice and a progress bar); where that fails (no
network: a short probe, not a long wait) ST-LPIPS is reported instead, said in one line.
ST-LPIPS is ``stlpips_pytorch``'s shift-tolerant AlexNet, whose weights ship in its wheel. A
configured folder is only read, never downloaded into; ``DIFFTEX_OFFLINE=1`` turns every
download off. docs/metrics.md says which files go where.
"""

from __future__ import annotations

import functools
import importlib.metadata
import logging
import os
import sys
import threading
import warnings
from pathlib import Path

from difftex.errors import DifftexError

LPIPS_VARIANTS = ("auto", "lpips", "stlpips")
LPIPS_MIN_SIDE = 32  # smallest side the networks accept (four / five poolings of stride 2)
# piq.LPIPS: VGG16's relu1_2 ... relu5_3 (torchvision ``features`` indices 3, 8, 15, 22, 29) and
# their channel counts, which piq's linear weights must match
PIQ_LPIPS_LAYERS = ("relu1_2", "relu2_2", "relu3_3", "relu4_3", "relu5_3")
PIQ_LPIPS_CHANNELS = (64, 128, 256, 512, 512)
OFFLINE_ENV = "DIFFTEX_OFFLINE"  # set (to anything but "", "0"): never download weight files
PROBE_TIMEOUT_S = 5.0  # how long the check that a weight file's server answers may take
READ_TIMEOUT_S = 60.0  # a download that receives nothing for this long fails
VGG16_MB = 528  # torchvision's VGG16 file (piq's own layer weights are 7 kB)

log = logging.getLogger(__name__)


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


def weight_urls() -> dict[str, str]:
    """Where ``piq.LPIPS()`` downloads the two files of :func:`lpips_weight_files` from."""
    from piq import LPIPS
    from torchvision.models import VGG16_Weights

    return {"lpips": LPIPS._weights_url, "vgg16": VGG16_Weights.IMAGENET1K_V1.url}


def downloads_allowed() -> bool:
    """False when ``DIFFTEX_OFFLINE`` is set (the test suite sets it: no test uses the network)."""
    return os.environ.get(OFFLINE_ENV, "").strip() in ("", "0")


def probe(url: str, timeout: float = PROBE_TIMEOUT_S) -> str | None:
    """None when ``url``'s server answers a HEAD request within ``timeout`` seconds, else why not.

    The request runs in a daemon thread that is given up on after ``timeout``: urllib's own
    timeout does not bound the name lookup, which can take minutes on a machine without network.
    """
    from urllib.parse import urlsplit
    from urllib.request import Request, urlopen

    host = urlsplit(url).hostname or url
    outcome: list[str | None] = []

    def ask() -> None:
        try:
            with urlopen(Request(url, method="HEAD", headers={"User-Agent": "torch.hub"}), timeout=timeout):
                outcome.append(None)
        except Exception as exc:  # noqa: BLE001 - any failure means: no download from here
            reason = getattr(exc, "reason", None) or exc
            outcome.append(f"{host}: {str(reason).splitlines()[0] if str(reason) else exc.__class__.__name__}")

    thread = threading.Thread(target=ask, name="difftex-probe", daemon=True)
    thread.start()
    thread.join(timeout)
    if not outcome:
        return f"{host} did not answer within {timeout:g} s"
    return outcome[0]


def download(url: str, dst: Path, hash_prefix: str | None) -> None:
    """``url`` into ``dst`` through torch.hub (a temporary file renamed at the end, the SHA-256
    prefix checked), with tqdm's progress bar when stderr is a terminal; a stalled transfer
    fails after READ_TIMEOUT_S."""
    import socket

    import torch

    before = socket.getdefaulttimeout()
    socket.setdefaulttimeout(READ_TIMEOUT_S)  # torch.hub's urlopen takes no timeout of its own
    try:
        torch.hub.download_url_to_file(url, str(dst), hash_prefix=hash_prefix, progress=sys.stderr.isatty())
    finally:
        socket.setdefaulttimeout(before)


@functools.cache
def fetch_hub_weights(folder: str) -> str | None:
    """Download classic LPIPS's missing weight files into the hub cache ``folder``, once per
    process: None when both are there afterwards, else why not (one clause, for one line).

    Says what it downloads in one log line; a server that does not answer (no network) is found
    by :func:`probe` within seconds, and the failure is remembered for the process.
    """
    files = lpips_weight_files(folder)
    urls = weight_urls()
    missing = [k for k, p in files.items() if not p.is_file()]
    if not missing:
        return None
    for key in missing:  # both servers, before anything is written
        why = probe(urls[key])
        if why is not None:
            return f"not downloaded, no network: {why}"
    size = f", {VGG16_MB} MB" if "vgg16" in missing else ""
    log.warning("LPIPS: downloading piq's classic LPIPS weights (%s%s) into %s, once",
                " and ".join(files[k].name for k in missing), size, folder)
    try:
        import filelock

        Path(folder).mkdir(parents=True, exist_ok=True)
        # parallel evaluation jobs: one downloads, the others wait for its files
        with filelock.FileLock(str(Path(folder) / ".difftex-lpips.lock")):
            for key in missing:
                if not files[key].is_file():
                    name = files[key].name
                    prefix = name.rsplit("-", 1)[1].split(".")[0] if key == "vgg16" else None  # torch.hub's check
                    download(urls[key], files[key], prefix)
    except Exception as exc:  # noqa: BLE001 - a failed download falls back like a missing file
        first = str(exc).splitlines()[0] if str(exc) else ""
        return f"download failed: {exc.__class__.__name__}: {first}"
    return None


def classic_lpips_missing(weights_dir: str | Path | None = None, fetch: bool = True) -> str | None:
    """Why classic LPIPS (piq) cannot run here, or None when it can.

    With ``fetch`` and no ``weights_dir``, missing files are first downloaded into the torch hub
    cache (:func:`fetch_hub_weights`, once per process, unless ``DIFFTEX_OFFLINE`` is set).
    """
    why = _import_error("piq")
    if why is not None:
        return why
    files = lpips_weight_files(weights_dir)
    missing = [p.name for p in files.values() if not p.is_file()]
    if not missing:
        return None
    if weights_dir is not None:
        note = "a configured folder is never downloaded into"
    elif not downloads_allowed():
        note = f"not downloaded: {OFFLINE_ENV} is set"
    elif not fetch:
        note = "not downloaded"
    else:
        note = fetch_hub_weights(str(files["lpips"].parent))
        if note is None:
            return classic_lpips_missing(weights_dir, fetch=False)
    return (f"classic LPIPS (piq) needs {' and '.join(p.name for p in files.values())} in "
            f"{files['lpips'].parent} (missing: {', '.join(missing)}; {note})")


def lpips_source(variant: str = "auto", weights_dir: str | Path | None = None) -> tuple[str | None, str]:
    """The network ``variant`` resolves to and its label: ("lpips" | "stlpips", label).

    ``"auto"`` is classic LPIPS (piq) when both of its weight files are on disk
    (:func:`lpips_weight_files`) or could be downloaded into the torch hub cache
    (:func:`classic_lpips_missing`), else ST-LPIPS. When nothing fits: (None, "unavailable: <why>").
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
    """The one line that says ``"auto"`` reports ST-LPIPS because classic LPIPS cannot run (the
    download, if any, was tried already: its outcome is remembered, not tried again)."""
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
    """``piq.LPIPS()`` (reduction "none") built from the local files.

    piq.LPIPS's own constructor fetches both files through ``torch.hub`` and loads all of VGG16
    (528 MB, classifier included); this builds the same network, piq's ``ContentLoss`` with piq's LPIPS
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

"""Per-patch view selection in the spirit of "Let There Be Color!" (Waechter et al. 2014).

One polygon's texels are cut into square patches (the MRF's nodes; on a planar proxy a patch
plays the role of a mesh face). Each patch takes one photo (label) by minimising

    E(l) = sum_p D_p(l_p) + sum_{p~q} V(l_p, l_q),

- data term ``D_p(l) = n_p (1 - mean_{t in p} vis_l(t) cos_l(t) res_l(t))``: view quality as
  frontality x resolution (texel footprint in photo pixels relative to the best photo there),
  zero where photo l does not see the texel, so partially seen patches are expensive;
- photo consistency (LTBC's outlier removal, e.g. a tree in front of the facade in one photo):
  per patch, each photo's mean colour (normalised by the photo's mean over the polygon, so
  exposure differences do not count) is compared with the mode of all photos' means (a few
  mean-shift steps from the median); ``n_p * consistency * min(1, (d / sigma)^2)`` is added;
- Potts smoothness ``V = lambda * patch`` (the seam length in texels) between 4-neighbours
  with different labels;

solved by alpha-expansion graph cuts (PyMaxflow's ``fastmin.aexpansion_grid``, a maintained
wrapper of the Boykov-Kolmogorov max-flow). Then seam colour leveling: one gain per photo and
channel, least squares over the seams (log colour means of the two photos in a band around
each seam, regularised towards gain 1; Waechter's global leveling is per vertex, a per-photo
gain is its planar-proxy analogue), and a short feathering of the labels across seams.
Texels that their patch's photo does not see take the best-quality photo that does.

Outputs match the other baselines (texture.png, source.png, source.npz, coverage.png, report.json).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from difftex.sampling import SUPERSAMPLE
from difftex.sampling.photos import MappedPhoto, PhotoSet, PolygonInput, pick_device

MAP_CACHE_BYTES = 1 << 30  # mapped photos kept between the passes (else mapped again)


@dataclass(frozen=True)
class MRFConfig:
    patch: int = 16  # patch side in texels (the MRF node)
    smoothness: float = 1.0  # Potts weight per texel of seam, in units of the data term
    max_cycles: int = 5  # alpha-expansion sweeps over all labels
    leveling: bool = True  # per-photo colour gains across seams
    leveling_band: int = 4  # texels on each side of a seam used to compare colours
    leveling_prior: float = 0.1  # regularisation of log gains towards 0, relative to the seam weights
    feather: float = 2.0  # Gaussian sigma (texels) of the label blending across seams; 0: hard seams
    consistency: float = 1.0  # weight of the photo-consistency term (0: off)
    consistency_sigma: float = 0.2  # colour distance (exposure-normalised RGB) at which a view counts as an outlier
    supersample: int = SUPERSAMPLE  # photo samples per texel side (the CLI takes optimize.supersample)

    def __post_init__(self):
        if self.patch < 1 or self.max_cycles < 1 or self.smoothness < 0 or self.feather < 0:
            raise ValueError("patch and max_cycles must be >= 1, smoothness and feather >= 0")

    @classmethod
    def from_dict(cls, data: dict | None, where: str = "mrf") -> MRFConfig:
        from difftex.config import from_dict

        return from_dict(cls, data, where=where)


def patch_sums(field: np.ndarray, patch: int) -> np.ndarray:
    """Sum of an (H, W) field over patch x patch blocks (the last ones may be partial)."""
    H, W = field.shape
    ph, pw = -(-H // patch), -(-W // patch)
    pad = np.zeros((ph * patch, pw * patch), np.float64)
    pad[:H, :W] = field
    return pad.reshape(ph, patch, pw, patch).sum((1, 3))


def solve_labels(unary: np.ndarray, smooth: float, max_cycles: int) -> np.ndarray:
    """Alpha-expansion with a Potts pairwise cost ``smooth`` on a 4-connected grid of nodes."""
    import maxflow.fastmin as fm

    L = unary.shape[-1]
    if L == 1:
        return np.zeros(unary.shape[:-1], np.int64)
    V = smooth * (1.0 - np.eye(L))
    init = np.argmin(unary, axis=-1).astype(np.int64)
    if smooth == 0:
        return init
    return np.asarray(fm.aexpansion_grid(unary.astype(np.float64), V, max_cycles=max_cycles, labels=init), np.int64)


def energy(unary: np.ndarray, labels: np.ndarray, smooth: float) -> float:
    """E(labels) for a grid MRF with Potts smoothness (for tests and the report)."""
    e = float(np.take_along_axis(unary, labels[..., None], -1).sum())
    e += smooth * float((labels[1:, :] != labels[:-1, :]).sum() + (labels[:, 1:] != labels[:, :-1]).sum())
    return e


def _gauss(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of (C, H, W)."""
    if sigma <= 0:
        return x
    r = max(1, int(3 * sigma))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=x.dtype, device=x.device) / sigma) ** 2)
    k = k / k.sum()
    C = x.shape[0]
    y = F.conv2d(F.pad(x[None], (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1).expand(C, 1, 1, -1), groups=C)
    y = F.conv2d(F.pad(y, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1).expand(C, 1, -1, 1), groups=C)
    return y[0]


def level_gains(
    pairs: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, int]], labels: list[int], prior: float
) -> dict[int, np.ndarray]:
    """Per-photo RGB gains g minimising sum_ab w_ab (log g_a + log m_a - log g_b - log m_b)^2 + prior * sum log^2 g."""
    if not pairs:
        return {n: np.ones(3) for n in labels}
    pos = {n: i for i, n in enumerate(labels)}
    L = len(labels)
    wtot = sum(w for _, _, w in pairs.values())
    A = np.eye(L) * prior * wtot / max(L, 1)
    b = np.zeros((L, 3))
    for (a, c), (ma, mc, w) in pairs.items():
        i, j = pos[a], pos[c]
        d = np.log(np.maximum(mc, 1e-3)) - np.log(np.maximum(ma, 1e-3))  # want x_i - x_j = d
        A[i, i] += w
        A[j, j] += w
        A[i, j] -= w
        A[j, i] -= w
        b[i] += w * d
        b[j] -= w * d
    x = np.linalg.solve(A, b)
    return {n: np.exp(x[pos[n]]) for n in labels}


def consistency_penalty(means: np.ndarray, ok: np.ndarray, sigma: float, steps: int = 5) -> np.ndarray:
    """(L, ph, pw) penalty in [0, 1] of each photo's patch mean colour against the patches' colour mode.

    The mode: mean shift with a Gaussian kernel of width ``sigma`` started at the per-channel
    median of the photos that see the patch (``ok``); needs at least 3 such photos, else 0.
    """
    okf = ok.astype(np.float64)
    cnt = okf.sum(0)
    masked = np.where(ok[..., None], means, np.nan)
    import warnings

    with warnings.catch_warnings():  # patches no photo sees fully: all-NaN, handled below
        warnings.simplefilter("ignore", RuntimeWarning)
        mode = np.nanmedian(masked, axis=0)
    mode = np.nan_to_num(mode)
    for _ in range(steps):
        d2 = ((means - mode[None]) ** 2).sum(-1)
        w = np.exp(-0.5 * d2 / sigma**2) * okf
        mode = np.where(
            (w.sum(0) > 1e-9)[..., None], (w[..., None] * means).sum(0) / np.maximum(w.sum(0), 1e-9)[..., None], mode
        )
    d2 = ((means - mode[None]) ** 2).sum(-1)
    pen = np.minimum(1.0, d2 / sigma**2)
    return np.where(ok & (cnt >= 3)[None], pen, 0.0)


def mrf_texture(
    inp: PolygonInput, cfg: MRFConfig = MRFConfig(), device="cpu"
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """(U (H, W, 3), weight sum (H, W), dominant photo (H, W), info), like baselines.baseline_texture."""
    t0 = time.perf_counter()
    device = pick_device(device)
    photos = PhotoSet.load(inp, device, supersample=cfg.supersample)
    frame, mask = inp.frame, inp.texel_mask
    H, W = frame.shape
    labels = sorted(photos.samplers)
    keep = len(labels) * H * W * 4 * 9 <= MAP_CACHE_BYTES
    cache: dict[int, MappedPhoto | None] = {}

    def mapped(n: int) -> MappedPhoto | None:
        if n in cache:
            return cache[n]
        mp = photos.map(n, frame, mask)
        if keep:
            cache[n] = mp
        return mp

    if not labels:
        return (
            np.zeros((H, W, 3), np.float32),
            np.zeros((H, W), np.float32),
            np.full((H, W), -1),
            {"method": "mrf", "labels": 0},
        )
    # Pass 1: view quality per texel and photo, patch mean colours -> patch data costs.
    qual = np.zeros((len(labels), H, W), np.float32)
    vis = np.zeros((len(labels), H, W), bool)
    fps = np.zeros((len(labels), H, W), np.float32)
    P = cfg.patch
    n_p = patch_sums(mask.astype(np.float64), P)
    means = np.zeros((len(labels), *n_p.shape, 3))
    seen_share = np.zeros((len(labels), *n_p.shape))
    for i, n in enumerate(labels):
        mp = mapped(n)
        if mp is None:
            continue
        v = mp.visible.cpu().numpy()
        vis[i] = v
        fps[i] = np.where(v, mp.footprint.cpu().numpy(), 0.0)
        qual[i] = np.where(v, mp.cos.cpu().numpy(), 0.0)
        if cfg.consistency > 0 and len(labels) > 2:
            col = mp.colour.cpu().numpy()
            vv = mp.visible.cpu().numpy()
            norm = col[:, vv].mean(1) + 1e-3 if vv.any() else np.ones(3)
            cnt = patch_sums(vv.astype(np.float64), P)
            seen_share[i] = cnt / np.maximum(n_p, 1)
            for c in range(3):
                means[i, ..., c] = patch_sums(col[c] * vv / norm[c], P) / np.maximum(cnt, 1)
    fp_max = fps.max(0)
    # footprint = texel size in pixels: a larger one means more photo pixels per texel
    res = np.where(fp_max > 0, fps / np.maximum(fp_max, 1e-12), 0.0)
    qual *= res
    unary = np.stack([n_p - patch_sums(qual[i] * mask, P) for i in range(len(labels))], -1)
    outliers = 0
    if cfg.consistency > 0 and len(labels) > 2:
        pen = consistency_penalty(means, seen_share >= 0.5, cfg.consistency_sigma)
        unary += np.moveaxis(pen, 0, -1) * (cfg.consistency * n_p)[..., None]
        outliers = int((pen >= 1).sum())
    t_solve = time.perf_counter()
    lab = solve_labels(unary, cfg.smoothness * P, cfg.max_cycles)
    t_solve = time.perf_counter() - t_solve
    lab_tex = np.repeat(np.repeat(lab, P, 0), P, 1)[:H, :W]  # label index (into labels) per texel
    # Texels the patch's photo does not see: the best-quality photo that does.
    best = np.where(vis.any(0), qual.argmax(0), -1)
    chosen_sees = np.take_along_axis(vis, lab_tex[None], 0)[0]
    lab_tex = np.where(chosen_sees, lab_tex, best)
    # Pass 2: seam leveling (colour means of both photos in a band around each seam).
    gains = {i: np.ones(3) for i in range(len(labels))}
    pairs_info = []
    if cfg.leveling and len(labels) > 1:
        r = cfg.leveling_band
        onehot = torch.from_numpy(np.stack([(lab_tex == i) & mask for i in range(len(labels))]).astype(np.float32))
        dil = (
            (F.max_pool2d(onehot[None], 2 * r + 1, stride=1, padding=r)[0] > 0).numpy() if r > 0 else onehot.numpy() > 0
        )
        pair_ids = [
            (a, b) for a in range(len(labels)) for b in range(a + 1, len(labels)) if (dil[a] & dil[b] & mask).any()
        ]
        bands = {(a, b): dil[a] & dil[b] & vis[a] & vis[b] for a, b in pair_ids}
        bands = {k: v for k, v in bands.items() if v.sum() >= 16}
        sums: dict[tuple[int, int], dict[int, np.ndarray]] = {k: {} for k in bands}
        for i, n in enumerate(labels):
            if not any(i in k for k in bands):
                continue
            mp = mapped(n)
            col = mp.colour.cpu().numpy()
            for k, band in bands.items():
                if i in k:
                    sums[k][i] = col[:, band].mean(1)
        pairs = {k: (sums[k][k[0]], sums[k][k[1]], int(bands[k].sum())) for k in bands}
        gains = level_gains(pairs, list(range(len(labels))), cfg.leveling_prior)
        pairs_info = [
            {"photos": [inp.photos[labels[a]].name, inp.photos[labels[b]].name], "band_texels": w}
            for (a, b), (_, _, w) in pairs.items()
        ]
    # Pass 3: composition with feathered labels and gains.
    acc = torch.zeros(3, H, W, device=device)
    wsum = torch.zeros(H, W, device=device)
    for i, n in enumerate(labels):
        sel = torch.from_numpy((lab_tex == i).astype(np.float32))
        if not bool(sel.any()):
            continue
        w = _gauss(sel[None], cfg.feather)[0].to(device) * torch.from_numpy(vis[i]).to(device)
        # keep hard ownership inside a region: feathering only reaches across seams
        w = torch.maximum(w, sel.to(device) * torch.from_numpy(vis[i]).to(device))
        mp = mapped(n)
        g = torch.as_tensor(gains[i], dtype=torch.float32, device=device)[:, None, None]
        acc += (mp.colour * g).clamp(0, 1) * w[None]
        wsum += w
    U = torch.where(wsum[None] > 0, acc / wsum.clamp_min(1e-12)[None], torch.zeros_like(acc))
    dominant = np.where(lab_tex >= 0, np.asarray(labels)[np.clip(lab_tex, 0, None)], -1)
    dominant = np.where(mask, dominant, -1)
    n_seams = int((lab[1:] != lab[:-1]).sum() + (lab[:, 1:] != lab[:, :-1]).sum())
    info = {
        "method": "mrf",
        "config": cfg.__dict__,
        "patches": list(lab.shape),
        "labels": len(labels),
        "photos_used": sorted({inp.photos[labels[i]].name for i in np.unique(lab_tex[lab_tex >= 0])}),
        "seam_edges": n_seams,
        "consistency_outliers": outliers,
        "energy": energy(unary, lab, cfg.smoothness * P),
        "energy_unary_only": energy(unary, np.argmin(unary, -1), cfg.smoothness * P),
        "gains": {inp.photos[labels[i]].name: [round(float(x), 4) for x in g] for i, g in gains.items()},
        "leveling_pairs": pairs_info,
        "time_solve_s": t_solve,
        "time_s": time.perf_counter() - t0,
    }
    return U.permute(1, 2, 0).cpu().numpy(), wsum.cpu().numpy(), dominant, info


def run_polygon(inp: PolygonInput, out_dir, cfg: MRFConfig = MRFConfig(), device="cpu") -> dict:
    """Texture one polygon and write the baseline outputs; returns the report."""
    from difftex.evaluation.baselines import write_baseline_polygon

    t0 = time.perf_counter()
    U, wsum, dominant, info = mrf_texture(inp, cfg, device)
    return write_baseline_polygon(inp, U, wsum, dominant, info, out_dir, t0)

"""DiffTex as published (``preset=paper``): every term of the paper's objective, as the code
computes it, against a direct numpy evaluation of the paper's equation on small random inputs;
the data-quality rules (3-sigma elimination, tau_w photo drop), Q = Q_a Q_c and the quantile HSV
histogram matching likewise; the preset file against the published values; extremes; and a
short run of the preset on the analytic wall.

Equations and sections are the paper's (DiffTex, ACM TOG 2025): eq. 3 L, eq. 4 L_Render, eq. 5-6
L_Persp, eq. 7-9 L_Para, Sec. 4.2 Q and a_k, Sec. 4.3 data elimination and brightness.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from difftex.compose.histmatch import transfers_from_mapped
from difftex.method import losses
from difftex.method.config import PUBLISHED, OptimizeConfig
from difftex.method.elimination import eliminate_pixels, photo_zero_share, photos_to_drop, update_activation
from difftex.method.gradient import texel_data, texel_value_and_grad
from difftex.method.objective import objective
from difftex.method.quality import quality
from difftex.sampling.colour import QUANTILES, apply_transfer
from difftex.workflow import glue as wf

from analytic import make_input, make_photo, optimize, paint_occluder, photo_masks, render

torch.set_num_threads(1)
REPO = Path(__file__).resolve().parents[1]
# the preset as the workflow reads it (config.yaml < presets/paper.yaml): the published method
PAPER = OptimizeConfig.from_dict(wf.resolve_config(REPO, {"preset": "paper"})["optimize"])


def sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def np_blend(w, a):
    """W_k = a_k w_k / sum_j a_j w_j (Sec. 4.1); an even blend of the active slots where every
    active weight is zero (the code's rule there: the paper does not say)."""
    aw = a * w
    s = aw.sum(0, keepdims=True)
    even = a / np.maximum(a.sum(0, keepdims=True), 1)
    return np.where(s > 0, aw / np.where(s > 0, s, 1), even)


def np_bilinear(U, x, y):
    """U (3, H, W) at continuous texel coordinates (x, y) (texel i spans [i, i + 1))."""
    xi, yi = x - 0.5, y - 0.5
    x0, y0 = np.floor(xi).astype(int), np.floor(yi).astype(int)
    fx, fy = xi - x0, yi - y0
    return (U[:, y0, x0] * (1 - fx) * (1 - fy) + U[:, y0, x0 + 1] * fx * (1 - fy)
            + U[:, y0 + 1, x0] * (1 - fx) * fy + U[:, y0 + 1, x0 + 1] * fx * fy)


def np_para(Wd, ad, U, G, mask, lam):
    """eq. 7-9 on dense per-photo fields Wd, ad (N, H, W): sum over up and left neighbours q of
    each texel o and over photos k of C |a_k W_k(o) - a_k W_k(q)|, C = m_k(o) D + lambda_s,
    D = S(|U(o) - U(q)|) (1 + G(o)), m_k(o) = 1 where photo k and another photo are selected."""
    m = ad & (ad.sum(0, keepdims=True) >= 2)
    aW = ad * Wd
    total = 0.0
    for o, q in (((slice(1, None), slice(None)), (slice(None, -1), slice(None))),
                 ((slice(None), slice(1, None)), (slice(None), slice(None, -1)))):
        ko, kq = (slice(None), *o), (slice(None), *q)  # all photos at the texels o, and at their q
        D = sigmoid(np.linalg.norm(U[ko] - U[kq], axis=0)) * (1 + G[o])
        C = m[ko] * D[None] + lam
        total += ((C * np.abs(aW[ko] - aW[kq])).sum(0) * (mask[o] & mask[q])).sum()
    return total


def random_case(seed, K=3, H=5, W=6):
    """A fixed slot layout (slot k = photo k), random weights, colours, Q, costs and pixels."""
    r = np.random.default_rng(seed)
    active = r.random((K, H, W)) > 0.25
    active[0, :, 0] = True
    w = r.uniform(0.05, 1.0, (K, H, W))
    colours = r.random((K, 3, H, W))
    Q = r.random((K, H, W))
    cost = r.random((K, H, W))
    G = r.random((H, W))
    mask = np.ones((H, W), bool)
    mask[0, -1] = False
    # rendered pixels: 7 per photo at interior texel coordinates, each counting ``scale`` times
    pix = [r.uniform(1.0, [W - 1.0, H - 1.0], (7, 2)) for _ in range(K)]
    cols = [r.random((7, 3)) for _ in range(K)]
    scales = [float(4 ** r.integers(0, 3)) for _ in range(K)]
    return SimpleNamespace(K=K, H=H, W=W, active=active, w=w, colours=colours, Q=Q, cost=cost, G=G, mask=mask,
                           pix=pix, cols=cols, scales=scales)


def np_objective(c, w):
    """The paper's L (eq. 3) and its terms, as written, on case ``c`` with weights ``w``."""
    a = c.active.astype(float)
    Wb = np_blend(w, a)
    U = (Wb[:, None] * c.colours).sum(0)
    render = 0.0
    for k in range(c.K):  # eq. 4: sum_k ||a_k Q (R_k - I_k)||^2 over the photo's pixels
        x, y = c.pix[k][:, 0], c.pix[k][:, 1]
        tx, ty = np.floor(x).astype(int), np.floor(y).astype(int)
        aq = a[k, ty, tx] * c.Q[k, ty, tx]
        R = np_bilinear(U, x, y).T
        render += c.scales[k] * (aq[:, None] ** 2 * (R - c.cols[k]) ** 2).sum()
    l1 = np.abs(a * w).sum()  # eq. 4: + sum_k sum_o |W_k(t_o)|, on the weights in use
    persp = (Wb * c.cost).sum()  # eq. 5: sum_k ||W_k . V_k . V_k||_1, |V_k|^2 = cost
    para = np_para(Wb, c.active, U, c.G, c.mask, PUBLISHED["lambda_s"])
    al, be, om = PUBLISHED["alpha"], PUBLISHED["beta"], PUBLISHED["omega"]
    total = al * (render + PUBLISHED["sparsity"] * l1) + be * persp + om * para
    return {"render": render, "sparsity": l1, "persp": persp, "para": para, "total": total}


def torch_case(c):
    """The code's inputs for case ``c``: tensors, the pixel batch, the L_Para slot matches."""
    t = {k: torch.from_numpy(getattr(c, k)) for k in ("active", "colours", "Q", "cost", "G", "mask")}
    sets = []
    for k in range(c.K):
        x, y = c.pix[k][:, 0], c.pix[k][:, 1]
        grid = torch.from_numpy(np.stack([x / c.W * 2 - 1, y / c.H * 2 - 1], -1))[None, :, None]
        texel = torch.from_numpy(np.floor(y).astype(np.int64) * c.W + np.floor(x).astype(np.int64))
        sets.append(losses.PixelSet(grid=grid, colour=torch.from_numpy(c.cols[k]), texel=texel,
                                    slot=torch.full((7,), k), scale=c.scales[k]))
    batch = losses.PixelBatch(
        grid=torch.cat([s.grid for s in sets], 1), colour=torch.cat([s.colour for s in sets]),
        texel=torch.cat([s.texel for s in sets]), slot=torch.cat([s.slot for s in sets]),
        scale=torch.cat([torch.full((7,), s.scale, dtype=torch.float64) for s in sets]),
        den=torch.ones(7 * c.K, dtype=torch.float64),  # interior pixels: the full support
    )
    idx = torch.arange(c.K)[:, None, None].expand(c.K, c.H, c.W)
    matches = {a: losses.neighbour_match(idx, t["mask"], a, fixed=True) for a in (1, 2)}
    support = torch.ones(c.H, c.W, dtype=torch.bool)
    return t, batch, matches, support


def code_objective(c, w, cfg=PAPER):
    t, batch, matches, support = torch_case(c)
    n_tex = float(c.mask.sum())
    return objective(w, t["active"], t["colours"], t["Q"], t["cost"], None, matches, batch, support, n_tex, cfg,
                     0.0, t["G"]), n_tex


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_each_term_and_the_total_are_the_papers_equations(seed):
    c = random_case(seed)
    ref = np_objective(c, c.w)
    terms, n_tex = code_objective(c, torch.from_numpy(c.w))
    for key in ("render", "sparsity", "persp", "para", "total"):  # the code divides every sum by n_tex
        assert float(terms[key]) * n_tex == pytest.approx(ref[key], rel=1e-10), key


def test_gradient_is_that_of_the_papers_objective():
    """autograd through the code (normalised weights, live L_Para edges) equals central
    differences of the numpy L: D's dependence on U is differentiated, as eq. 9 is written."""
    c = random_case(3)
    w = torch.from_numpy(c.w).requires_grad_(True)
    terms, n_tex = code_objective(c, w)
    terms["total"].backward()
    num = np.zeros_like(c.w)
    h = 1e-6
    for i in np.ndindex(c.w.shape):
        if not c.active[i]:
            continue
        wp, wm = c.w.copy(), c.w.copy()
        wp[i] += h
        wm[i] -= h
        num[i] = (np_objective(c, wp)["total"] - np_objective(c, wm)["total"]) / (2 * h)
    assert np.allclose(w.grad.numpy() * n_tex, num, rtol=1e-5, atol=1e-6)
    # with fixed edges (the project's) the gradient leaves D out, so it differs
    w2 = torch.from_numpy(c.w).requires_grad_(True)
    t, batch, matches, support = torch_case(c)
    U = losses.compose(losses.blend_weights(w2.detach(), t["active"], "normalised"), t["colours"])
    D = losses.edge_weights(U, t["G"], (1, 2))
    fixed = dataclasses.replace(PAPER, para_edges="fixed")
    objective(w2, t["active"], t["colours"], t["Q"], t["cost"], D, matches, batch, support, n_tex, fixed,
              0.0, t["G"])["total"].backward()
    assert not np.allclose(w2.grad.numpy() * n_tex, num, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("fixed", [True, False])
def test_normalised_texel_gradient_matches_autograd(fixed):
    """The written-out texel-space gradient (fixed edges) with the paper's weights and L1 term."""
    r = np.random.default_rng(5)
    K, H, W, N = 3, 6, 7, (3 if fixed else 6)
    idx = torch.arange(K)[:, None, None].expand(K, H, W).clone() if fixed else torch.from_numpy(
        np.stack([r.permutation(N)[:K] for _ in range(H * W)], -1).reshape(K, H, W))
    active = torch.from_numpy(r.random((K, H, W)) > 0.2)
    active[0] = True
    mask = torch.ones(H, W, dtype=torch.bool)
    colours, Q, cost = (torch.from_numpy(r.random(s)) for s in ((K, 3, H, W), (K, H, W), (K, H, W)))
    w = torch.from_numpy(r.uniform(0.05, 1.0, (K, H, W)))
    G = torch.from_numpy(r.random((H, W)))
    cfg = dataclasses.replace(PAPER, loss_mode="texel", para_edges="fixed")
    matches = {a: losses.neighbour_match(idx, mask, a, fixed=fixed) for a in (1, 2)}
    D = losses.edge_weights(losses.compose(losses.blend_weights(w, active, "normalised"), colours), G, (1, 2))
    wr = w.clone().requires_grad_(True)
    ref = objective(wr, active, colours, Q, cost, D, matches, None, None, float(H * W), cfg)
    ref["total"].backward()
    terms, grad = texel_value_and_grad(w, active, texel_data(colours, Q, cost, float(H * W)), D, matches, cfg)
    for k in ("total", "render", "sparsity", "persp", "para"):
        assert float(terms[k]) == pytest.approx(float(ref[k].detach()), rel=1e-9), k
    assert torch.allclose(grad, wr.grad, rtol=1e-7, atol=1e-10)


def test_para_with_lambda_s_on_a_per_texel_slot_layout():
    """eq. 7-9 with photos in different slots at neighbouring texels: the code matches slots by
    photo; photos one texel has and its neighbour lacks pay lambda_s |W| (m_k = 0 there)."""
    r = np.random.default_rng(7)
    K, H, W, N = 3, 5, 6, 6
    idx = np.stack([r.permutation(N)[:K] for _ in range(H * W)], -1).reshape(K, H, W)
    active = r.random((K, H, W)) > 0.3
    active[0] = True
    Wb = np_blend(r.random((K, H, W)), active.astype(float))
    U = r.random((3, H, W))
    G = r.random((H, W))
    mask = r.random((H, W)) > 0.1
    Wd = np.stack([(Wb * (idx == n)).sum(0) for n in range(N)])
    ad = np.stack([(active & (idx == n)).any(0) for n in range(N)])
    for lam in (0.5, 2.0):
        ref = np_para(Wd, ad, U, G, mask, lam)
        m = {a: losses.neighbour_match(torch.from_numpy(idx), torch.from_numpy(mask), a) for a in (1, 2)}
        val = losses.para_loss(torch.from_numpy(Wb), torch.from_numpy(U), torch.from_numpy(active),
                               torch.from_numpy(G), m, lam, 1.0)
        assert float(val) == pytest.approx(ref, rel=1e-10)


def test_guidance_direction_and_persp_cost():
    """v~ = 0.5 sum v_k / |sum v_k| - 0.5 n (text before eq. 5); |V^_k - v~|^2 per texel (eq. 6)."""
    r = np.random.default_rng(2)
    v = r.normal(size=(4, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    n = np.array([0.0, -1.0, 0.0])
    vt = 0.5 * v.sum(0) / np.linalg.norm(v.sum(0)) - 0.5 * n
    code = losses.guidance_direction(torch.from_numpy(v), torch.from_numpy(n)).numpy()
    assert np.allclose(code, vt)
    field = r.normal(size=(4, 3, 2, 3))
    cost = losses.persp_cost(torch.from_numpy(field), torch.from_numpy(vt)).numpy()
    assert np.allclose(cost, ((field - vt[None, :, None, None]) ** 2).sum(1))


def test_q_is_qa_times_the_gaussian_qc():
    """Q = Q_a Q_c (Sec. 4.2), Q_c = Gaussian(I_k, mu, sigma) with mu, sigma the mean and variance
    of the texel's candidate colours; with resolution_weight 0 the level's Q and the initial
    weights w = Q are that."""
    r = np.random.default_rng(4)
    N, h, w = 5, 3, 4
    cols = r.random((N, 3, h, w))
    vis = r.random((N, h, w)) > 0.3
    vis[0] = True
    cos = r.random((N, h, w))
    cnt = vis.sum(0)
    mu = (cols * vis[:, None]).sum(0) / cnt
    msd = (((cols - mu[None]) ** 2).sum(1) * vis).sum(0) / cnt
    floor = PAPER.sigma_min
    for k in range(N):
        ref = np.where(vis[k], cos[k] * np.exp(-((cols[k] - mu) ** 2).sum(0) / (2 * (msd + floor**2))), 0)
        got = quality(*(torch.from_numpy(x) for x in (cos[k], cols[k], mu, msd, vis[k])), floor).numpy()
        assert np.allclose(got, ref, rtol=1e-12)


def test_the_level_starts_from_w_equal_to_q_and_renders_per_pixel():
    from difftex.method.levels import build_level
    from difftex.method.render import build_pixel_sets
    from difftex.sampling.photos import PhotoSet
    from difftex.sampling.texels import level_frame

    photos = [make_photo("a", -20.0), make_photo("b", 0.0), make_photo("c", 25.0)]
    inp = make_input(photos, [render(p) for p in photos], long_side=40)
    inp.a_bbox, inp.a_masks = photo_masks(inp)
    ps = PhotoSet.load(inp, "cpu")
    frame = level_frame(inp.frame, 40)
    lv = build_level(ps, frame, PAPER)
    # Q = Q_a Q_c, recomputed from the mapped photos (slot k is photo k: three fit in 16 slots)
    mp = [ps.map(n, frame, inp.texel_mask, None) for n in range(3)]
    vis = torch.stack([m.visible for m in mp]).double()
    cols = torch.stack([m.colour for m in mp]).double()
    mu = (cols * vis[:, None]).sum(0) / vis.sum(0).clamp_min(1)
    msd = (((cols - mu) ** 2).sum(1) * vis).sum(0) / vis.sum(0).clamp_min(1)
    for n in range(3):
        qc = torch.exp(-((cols[n] - mu) ** 2).sum(0) / (2 * (msd + PAPER.sigma_min**2)))
        q = mp[n].cos * qc
        q = torch.where(mp[n].visible, q, 0.0)
        assert torch.allclose(lv.Q[n].double(), q, atol=1e-5)
    assert torch.equal(lv.z0, lv.Q * lv.visible)  # Sec. 4.2: w_k initialised to Q
    # eq. 4 sums over the photos' pixels: rendered at pyramid level L, a pixel counts 4^L
    pb = build_pixel_sets(ps, lv, None, "pixels")
    assert set(pb.scale.unique().tolist()) <= {1.0, 4.0, 16.0, 64.0}
    for n in range(3):  # the weighted sum counts about the photo's own pixels on the polygon
        assert float(pb.scale[pb.slot == n].sum()) == pytest.approx(float(inp.a_masks[n].sum()), rel=0.15)
    texels = build_pixel_sets(ps, lv, None, "texels")  # the project's: each photo on the texel scale
    assert not torch.equal(texels.scale, pb.scale)


def test_three_sigma_elimination_is_the_papers_test():
    """Sec. 4.3: per texel, the mean and standard deviation of the selected colours; every
    selected pixel beyond three deviations goes. A pixel is at most sqrt(n - 1) deviations from
    the mean of n, so fewer than 11 selected photos never lose one."""
    r = np.random.default_rng(8)
    K, h, w = 16, 4, 5
    cols = 0.5 + 0.01 * r.normal(size=(K, 3, h, w))
    cols[3, :, 1, 2] = 0.0  # an outlier among 16
    cols[5, :, 2, :] += r.choice([0.0, 0.3], size=(3, w))
    active = r.random((K, h, w)) > 0.1
    active[:, 0, :] = False
    active[:8, 0, :] = True  # n = 8 in the first row: no elimination whatever the colours
    cols[0, :, 0, :] = 5.0
    active[:, 3, 4] = False
    active[0, 3, 4] = True  # one photo
    a = active.astype(float)
    n = a.sum(0)
    mu = (cols * a[:, None]).sum(0) / n
    d2 = ((cols - mu[None]) ** 2).sum(1)
    var = (d2 * a).sum(0) / n
    ref = active & (d2 > 9.0 * var[None])
    lv = SimpleNamespace(colours=torch.from_numpy(cols))
    got = eliminate_pixels(lv, torch.from_numpy(active), torch.rand(K, h, w).double(), PAPER).numpy()
    assert np.array_equal(got, ref) and got[3, 1, 2] and got.sum() >= 1
    assert not got[:, 0].any() and not got[:, 3, 4].any()
    same = SimpleNamespace(colours=torch.full((K, 3, h, w), 0.3, dtype=torch.float64))
    assert not eliminate_pixels(same, torch.ones(K, h, w, dtype=torch.bool), torch.ones(K, h, w), PAPER).any()


def test_photo_drop_at_tau_w():
    """Sec. 4.3 i): a photo whose weight is zero (<= tau, deselected) on more than tau_w of the
    texels it could serve is excluded; the paper's weights w are what tau reads."""
    r = np.random.default_rng(9)
    K, h, w, N = 3, 8, 9, 5
    idx = np.stack([r.permutation(N)[:K] for _ in range(h * w)], -1).reshape(K, h, w)
    base = r.random((K, h, w)) > 0.2
    wts = r.random((K, h, w)) * (r.random((K, h, w)) > np.array([0.0, 0.5, 0.97, 0.2, 0.99])[idx])
    sel = losses.selection_weights(torch.from_numpy(wts), torch.from_numpy(base), "normalised")
    lv = SimpleNamespace(idx=torch.from_numpy(idx))
    share = photo_zero_share(lv, torch.from_numpy(base), sel, PAPER.tau, N).numpy()
    for k in range(N):
        served = base & (idx == k)
        zero = served & (np.where(base, wts, 0) <= PAPER.tau)
        assert share[k] == pytest.approx(zero.sum() / served.sum())
    want = [k for k in range(N) if share[k] > PAPER.tau_w]
    assert photos_to_drop(lv, torch.from_numpy(base), sel, PAPER.tau, PAPER.tau_w, N) == want and want


def test_histogram_matching_is_a_quantile_map_in_hsv():
    """Sec. 4.3, Brightness Adjustment: every photo's H, S and V mapped by a monotone quantile
    map onto the histogram of all the photos (pooled: the paper names no reference)."""
    from skimage.color import rgb2hsv

    r = np.random.default_rng(11)
    h, w = 24, 30
    base = r.random((h, w, 3)) * 0.6 + 0.2
    # exposures that clip nothing: a monotone map cannot split a point mass at 1
    photos = {n: np.clip(base * g + 0.02 * r.normal(size=base.shape), 0, 1) for n, g in enumerate((0.7, 0.85, 1.1))}
    vis = {n: torch.from_numpy(r.random((h, w)) > 0.2) for n in photos}
    col = {n: torch.from_numpy(p.transpose(2, 0, 1).astype(np.float32)) for n, p in photos.items()}
    front = {n: torch.ones(h, w) for n in photos}
    cfg = PAPER
    tr, _ = transfers_from_mapped(col, vis, front, cfg.histmatch_reference, cfg.histmatch_channels,
                                  model=cfg.histmatch_model)
    hsv = {n: rgb2hsv(photos[n].astype(np.float32)) for n in photos}
    for c in range(3):
        pooled = np.concatenate([hsv[n][..., c][vis[n].numpy()] for n in photos])
        for n in photos:
            src = hsv[n][..., c][vis[n].numpy()]
            xs = np.maximum.accumulate(np.concatenate([[0.0], np.quantile(src, QUANTILES), [1.0]]))
            ys = np.maximum.accumulate(np.concatenate([[0.0], np.quantile(pooled, QUANTILES), [1.0]]))
            assert np.allclose(tr[n][c, 0], xs, atol=2e-4) and np.allclose(tr[n][c, 1], ys, atol=2e-4)
    # the defining property: each photo's S and V after the map have the pooled histogram
    for c in (1, 2):
        pooled = np.concatenate([hsv[n][..., c][vis[n].numpy()] for n in photos])
        for n in photos:
            out = rgb2hsv(apply_transfer(photos[n].astype(np.float32), tr[n]))[..., c][vis[n].numpy()]
            p = np.linspace(0.05, 0.95, 10)
            assert np.abs(np.quantile(out, p) - np.quantile(pooled, p)).max() < 0.02


def test_extremes_all_weights_zero_one_photo_and_an_unseen_texel():
    K, H, W = 3, 2, 3
    active = torch.zeros(K, H, W, dtype=torch.bool)
    active[:, 0, 0] = True  # three photos, every weight zero
    active[0, 0, 1] = True  # one photo
    # texels (0, 2) and row 1: no photo sees them
    w = torch.zeros(K, H, W, dtype=torch.float64)
    w[0, 0, 1] = 0.3
    wr = w.clone().requires_grad_(True)
    Wb = losses.blend_weights(wr, active, "normalised")
    Wd = Wb.detach()
    assert torch.allclose(Wd[:, 0, 0], torch.full((3,), 1 / 3, dtype=torch.float64))  # even, not 0 / 0
    assert float(Wd[0, 0, 1]) == 1.0 and float(Wd[:, 0, 2].abs().sum() + Wd[:, 1].abs().sum()) == 0.0
    (Wb * torch.rand(K, H, W, dtype=torch.float64)).sum().backward()
    assert torch.isfinite(wr.grad).all() and float(wr.grad.abs().sum()) == 0.0  # one photo or none: no lever
    assert torch.equal(losses.sparsity_grad(w, active, 1.0)[:, 0, 0], torch.zeros(3, dtype=torch.float64))
    # the L1 term took the only active photo to zero: it stays, not the frozen photo beside it
    prev = torch.zeros(K, 1, 1, dtype=torch.bool)
    prev[0] = True
    z = torch.tensor([0.0, 0.005, 0.0]).reshape(K, 1, 1)
    act = update_activation(z, torch.ones(K, 1, 1, dtype=torch.bool), 0.01, "normalised", prev)
    assert act[:, 0, 0].tolist() == [True, False, False]
    # the whole objective at these extremes, with rendered pixels on the unseen texels too
    c = random_case(6, K=K, H=4, W=5)
    c.active[:] = False
    c.active[:, 1, 1] = True
    c.active[0, 2, 2] = True
    w0 = np.where(c.active, c.w, 0.0)
    w0[:, 1, 1] = 0.0
    terms, n_tex = code_objective(c, torch.from_numpy(w0).requires_grad_(True))
    terms["total"].backward()
    ref = np_objective(c, w0)
    assert all(np.isfinite(float(v.detach())) for v in terms.values())
    assert float(terms["total"].detach()) * n_tex == pytest.approx(ref["total"], rel=1e-10)


def test_one_photo_run_stays_the_photo():
    ph = make_photo("a", 10.0)
    inp = make_input([ph], [render(ph)], long_side=40)
    inp.a_bbox, inp.a_masks = photo_masks(inp)
    cfg = dataclasses.replace(PAPER, long_side_start=16, max_iters_per_level=(30, 10), histogram_matching=False)
    res = optimize(inp, cfg)
    seen = inp.texel_mask & inp.texel_visible.any(0)
    assert np.isfinite(res.U).all() and np.allclose(res.W.sum(0)[seen], 1.0)
    assert res.stats["coverage"] == 1.0


def test_preset_paper_is_the_published_method():
    cfg = wf.resolve_config(REPO, {"preset": "paper"})
    wf.validate(cfg, REPO / "workflow" / "schemas" / "config.schema.yaml")  # what the workflow checks first
    opt = OptimizeConfig.from_dict(cfg["optimize"])
    assert opt.departures() == []
    for key, value in PUBLISHED.items():
        assert getattr(opt, key) == value, key
    assert (opt.lr, opt.betas, opt.long_side_start, opt.level_step) == (0.005, (0.9, 0.99), 256, 2.0)
    # Sec. 4.3: 256 -> 2048, doubling; every photo a candidate
    assert cfg["texture"]["density"] is None and cfg["texture"]["long_side"] == 2048
    assert cfg["visibility"]["texel_candidates"] is None
    from difftex.geometry.frames import level_sides

    assert level_sides(2048, opt.long_side_start, opt.coarse_to_fine, opt.level_step) == [256, 512, 1024, 2048]
    # every key of the preset says where in the paper it comes from, or that it is open or the project's
    text = (REPO / "config" / "presets" / "paper.yaml").read_text()
    keys = [ln for ln in text.splitlines() if re.match(r"^\s+\w+:\s*\S", ln)]
    assert keys and all("#" in ln for ln in keys), [ln for ln in keys if "#" not in ln]
    # the project's defaults are unchanged, and depart from the paper
    default = OptimizeConfig.from_dict(wf.resolve_config(REPO, {})["optimize"])
    assert default == OptimizeConfig()
    assert {"weights", "sparsity", "loss_mode", "lr", "resolution_weight", "ghost"} <= set(default.departures())
    with pytest.raises(ValueError, match="sparsity needs weights: normalised"):
        OptimizeConfig(sparsity=1.0)


def test_short_preset_paper_run_on_the_analytic_wall():
    """The preset as the workflow reads it, on the analytic wall with an occluded frontal photo,
    with short caps (a test): two levels from 256, doubling; its stats name the mode that ran."""
    cfg = wf.resolve_config(REPO, {"preset": "paper"})
    opt = dataclasses.replace(OptimizeConfig.from_dict(cfg["optimize"]), max_iters_per_level=(20, 10))
    photos = [make_photo("front", 0.0), make_photo("left", -30.0), make_photo("right", 30.0)]
    imgs = [paint_occluder(photos[0], render(photos[0]))] + [render(p) for p in photos[1:]]
    inp = make_input(photos, imgs, long_side=320)
    inp.a_bbox, inp.a_masks = photo_masks(inp)
    res = optimize(inp, opt)
    st = res.stats
    assert st["departures_from_paper"] == [] and st["weights"] == "normalised"
    assert st["config"]["loss_mode"] == "render" and st["config"]["para_edges"] == "live"
    assert [lv["long_side"] for lv in st["levels"]] == [256, 320]
    assert all(max(lv["loss"]["sparsity"]) > 0 and lv["render_pixels"] > 0 for lv in st["levels"])
    seen = inp.texel_mask & inp.texel_visible.any(0)
    assert np.isfinite(res.U).all() and np.allclose(res.W.sum(0)[seen], 1.0, atol=1e-5)
    assert st["coverage"] == 1.0

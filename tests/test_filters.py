"""The Gaussian blur of texel maps (difftex.method.filters): the same values as the separable
convolution it replaced, at the extremes of sigma and map size, and differentiable."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from difftex.method.filters import blur, gaussian_kernel


def _conv_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """The previous implementation: two one-channel conv2d passes over the replicate-padded maps."""
    g = gaussian_kernel(sigma)
    r = len(g) // 2
    y = F.conv2d(F.pad(x[:, None], (r, r, 0, 0), mode="replicate"), g.view(1, 1, 1, -1))
    return F.conv2d(F.pad(y, (0, 0, r, r), mode="replicate"), g.view(1, 1, -1, 1))[:, 0]


@pytest.mark.parametrize("sigma", [0.2, 1.0, 2.5, 7.0])
@pytest.mark.parametrize("shape", [(1, 1, 1), (3, 1, 40), (2, 37, 3), (4, 64, 53)])
def test_blur_equals_the_separable_convolution(sigma, shape):
    x = torch.rand(shape, generator=torch.Generator().manual_seed(1)) * 10 - 5
    assert torch.allclose(blur(x, sigma), _conv_blur(x, sigma), rtol=0, atol=1e-5)


def test_blur_keeps_constants_and_the_mean_and_spreads_a_point():
    c = torch.full((2, 9, 30), 0.3)
    assert torch.allclose(blur(c, 4.0), c, atol=1e-6)  # replicated edges: no darkening at the border
    pt = torch.zeros(1, 41, 41)
    pt[0, 20, 20] = 1.0
    out = blur(pt, 2.0)[0]
    assert abs(float(out.sum()) - 1.0) < 1e-5
    var = float((out * (torch.arange(41.0) - 20)[None, :] ** 2).sum())
    assert abs(var - 4.0) < 0.05  # the variance of the Gaussian, sigma^2
    assert torch.allclose(out, out.T, atol=1e-7)  # the same along both axes


def test_blur_of_sigma_zero_is_the_input_and_bad_shapes_are_refused():
    x = torch.rand(3, 5, 5)
    assert blur(x, 0.0) is x
    with pytest.raises(ValueError):
        blur(torch.rand(5, 5), 1.0)


def test_blur_is_differentiable_as_the_convolution():
    x = torch.rand(2, 12, 15, dtype=torch.float32, requires_grad=True)
    w = torch.rand(2, 12, 15)
    (g1,) = torch.autograd.grad((blur(x, 1.5) * w).sum(), x)
    (g2,) = torch.autograd.grad((_conv_blur(x, 1.5) * w).sum(), x)
    assert torch.allclose(g1, g2, atol=1e-6)


def test_gaussian_kernel_is_normalised_and_three_sigma_wide():
    for sigma in (0.1, 1.0, 3.3):
        g = gaussian_kernel(sigma)
        assert len(g) == 2 * max(1, int(np.ceil(3 * sigma))) + 1
        assert abs(float(g.sum()) - 1.0) < 1e-6
        assert torch.equal(g, g.flip(0))


@pytest.mark.gpu
def test_blur_on_a_gpu_is_the_cpus():
    """On a GPU blur keeps the library convolution; its values are the written-out sum's."""
    if not torch.cuda.is_available():
        pytest.skip("no CUDA")
    x = torch.rand(3, 70, 90, generator=torch.Generator().manual_seed(5))
    for sigma in (0.7, 3.0):
        assert torch.allclose(blur(x.cuda(), sigma).cpu(), blur(x, sigma), atol=1e-5)

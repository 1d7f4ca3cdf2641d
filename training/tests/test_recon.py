"""Kernel application and inverse transforms against independent numpy implementations."""

import numpy as np
import pytest
import torch

from mcdenoise_train.contract import EPS, KERNEL_TAPS
from mcdenoise_train.recon import (
    apply_kernel,
    inverse_diffuse,
    inverse_specular,
    reconstruct,
)


def tap(dy, dx):
    return (dy + 10) * 21 + (dx + 10)


def numpy_filter(logits, color):
    """Brute force: softmax over taps, then sum over the 441 clamped neighbours."""
    n, _, h, w = logits.shape
    wts = np.exp(logits - logits.max(axis=1, keepdims=True))
    wts /= wts.sum(axis=1, keepdims=True)
    out = np.zeros(color.shape, dtype=np.float64)
    ys, xs = np.arange(h), np.arange(w)
    for dy in range(-10, 11):
        for dx in range(-10, 11):
            src = color[:, :, np.clip(ys + dy, 0, h - 1)][:, :, :, np.clip(xs + dx, 0, w - 1)]
            out += wts[:, tap(dy, dx)][:, None] * src
    return out


def numpy_box21(color):
    """21x21 mean with edge replication (pad + sliding windows)."""
    padded = np.pad(color, ((0, 0), (0, 0), (10, 10), (10, 10)), mode="edge")
    win = np.lib.stride_tricks.sliding_window_view(padded, (21, 21), axis=(2, 3))
    return win.mean(axis=(-2, -1))


def rand(*shape, seed=0):
    return torch.from_numpy(np.random.default_rng(seed).standard_normal(shape))


def test_identity_kernel_is_exact():
    color = rand(2, 3, 9, 14).float()
    logits = torch.zeros(2, KERNEL_TAPS, 9, 14)
    logits[:, tap(0, 0)] = 1e4
    assert torch.equal(apply_kernel(logits, color), color)


def test_tap_order_rows_are_dy():
    """A kernel on tap (dy=+1, dx=-2) reads the pixel one row down, two columns left."""
    color = rand(1, 3, 6, 8, seed=1).float()
    logits = torch.zeros(1, KERNEL_TAPS, 6, 8)
    logits[:, tap(1, -2)] = 1e4
    c = color.numpy()
    ys = np.clip(np.arange(6) + 1, 0, 5)
    xs = np.clip(np.arange(8) - 2, 0, 7)
    expect = c[:, :, ys][:, :, :, xs]
    assert np.array_equal(apply_kernel(logits, color).numpy(), expect)


@pytest.mark.parametrize("h,w", [(30, 27), (5, 7)])
def test_uniform_kernel_is_box_filter(h, w):
    color = rand(1, 3, h, w, seed=2)
    out = apply_kernel(torch.zeros(1, KERNEL_TAPS, h, w, dtype=torch.float64), color)
    np.testing.assert_allclose(out.numpy(), numpy_box21(color.numpy()), rtol=0, atol=1e-12)


def test_random_kernel_matches_brute_force():
    logits = rand(2, KERNEL_TAPS, 12, 23, seed=3) * 3.0
    color = rand(2, 3, 12, 23, seed=4)
    out = apply_kernel(logits, color)
    np.testing.assert_allclose(out.numpy(), numpy_filter(logits.numpy(), color.numpy()), atol=1e-12)
    # float32 agrees to float32 precision
    out32 = apply_kernel(logits.float(), color.float())
    np.testing.assert_allclose(out32.numpy(), out.numpy(), atol=1e-5)


def test_gradient_conserves_mass():
    """Kernels sum to 1, so d(sum out)/d(color) sums to the number of outputs."""
    color = rand(1, 3, 8, 6, seed=5).requires_grad_(True)
    logits = (rand(1, KERNEL_TAPS, 8, 6, seed=6)).requires_grad_(True)
    apply_kernel(logits, color).sum().backward()
    assert torch.isclose(color.grad.sum(), torch.tensor(3 * 8 * 6, dtype=torch.float64))
    assert torch.isfinite(logits.grad).all() and logits.grad.abs().sum() > 0


def test_shape_checks():
    with pytest.raises(ValueError):
        apply_kernel(torch.zeros(1, 440, 4, 4), torch.zeros(1, 3, 4, 4))
    with pytest.raises(ValueError):
        apply_kernel(torch.zeros(1, KERNEL_TAPS, 4, 4), torch.zeros(1, 3, 4, 5))


def test_inverse_transforms():
    assert EPS == 0.00316
    rng = np.random.default_rng(7)
    d = torch.from_numpy(rng.uniform(0, 5, (1, 3, 4, 5)))
    a = torch.from_numpy(rng.uniform(0, 1, (1, 3, 4, 5)))
    a[0, 0, 0, 0] = 0.0
    s = torch.from_numpy(rng.exponential(2.0, (1, 3, 4, 5)))
    torch.testing.assert_close(inverse_diffuse(d / (a + EPS), a), d)
    torch.testing.assert_close(inverse_specular(torch.log1p(s)), s)
    assert inverse_specular(torch.zeros(1)).item() == 0.0


def test_reconstruct_identity_returns_noisy_components():
    rng = np.random.default_rng(8)
    shape = (1, 3, 7, 9)
    d = torch.from_numpy(rng.uniform(0, 2, shape))
    s = torch.from_numpy(rng.exponential(1.0, shape))
    a = torch.from_numpy(rng.uniform(0, 1, shape))
    dcol = torch.cat([d / (a + EPS), torch.from_numpy(rng.normal(size=(1, 7, 7, 9)))], 1)
    scol = torch.cat([torch.log1p(s), torch.from_numpy(rng.normal(size=(1, 7, 7, 9)))], 1)
    ident = torch.zeros(1, KERNEL_TAPS, 7, 9, dtype=torch.float64)
    ident[:, tap(0, 0)] = 1e4
    r = reconstruct(ident, ident, dcol, scol, a)
    torch.testing.assert_close(r.diffuse, d)
    torch.testing.assert_close(r.specular, s)
    torch.testing.assert_close(r.total, d + s)
    assert torch.equal(r.diffuse_pre, dcol[:, :3])


def test_fast_filter_matches_autograd_of_the_reference_loop():
    """The hand-written backward (color without gradient) equals autograd's."""
    torch.manual_seed(3)
    logits = torch.randn(2, 441, 13, 11, dtype=torch.float64, requires_grad=True)
    color = torch.rand(2, 3, 13, 11, dtype=torch.float64)
    fast = apply_kernel(logits, color)
    (g_fast,) = torch.autograd.grad((fast * fast).sum(), logits)
    ref = apply_kernel(logits, color.clone().requires_grad_(True))  # reference path
    (g_ref,) = torch.autograd.grad((ref * ref).sum(), logits)
    assert torch.allclose(fast, ref, atol=1e-12)
    assert torch.allclose(g_fast, g_ref, atol=1e-12)

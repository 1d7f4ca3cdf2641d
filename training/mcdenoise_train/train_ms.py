"""Train the production network (contract v2, `msnet.py`) on a CPU or a GPU.

    python -m mcdenoise_train.train_ms --data DATA [--data DATA2 ...] --out runs/ms [options]

Recipe:

- **Data**: every noisy frame of the manifests' training scenes (all sample counts) with
  its reference, held as raw buffers (`preprocess.RAW`) on the training device; validation
  frames are the manifests' `val` scenes. Test scenes are never read here.
- **Crops and augmentation** (on the device, per patch): random crops, flips and
  transposes, a permutation of R, G, B shared by the radiance, albedo and references,
  exposure scaled by 2^U(-e, e) (radiance ×k, variances ×k²), and, in a fraction of the
  patches, injected fireflies: a few isolated samples of 10–10,000× the local level added
  to the noisy diffuse or specular buffer (and its variance), never to the reference, so the
  network learns not to pass them through. The patches are then preprocessed by
  `preprocess.py`, the engine's transform in PyTorch.
- **Covariance dropout**: in a fraction of the patches the covariance channels are
  zeroed, so one network serves frames with and without covariance: `full` is exported
  as is, `nocov` with the covariance inputs cut (`export_ms.nocov_from_full`).
- **Loss** (`losses.py`): SMAPE of each component in its preprocessed domain (Lin et al.
  2020), plus L1 of the final color after the transfer function log(1 + x) (robust to HDR
  outliers), plus `--perceptual W` × the VGG-16 feature loss when the weights are present,
  plus `--ssim W` × DSSIM, `--msssim W` × (1 − MS-SSIM, five scales: structure at the
  coarse scales too, where low sample counts leave blotches) and `--relmse W` × RelMSE of
  the final color (`relmse_huber`: the few pixels beside an emitter's edge that carry most
  of the metric weigh as in it).
- **Variance dropout** (`--var-dropout P`): in a fraction of the patches every variance
  is zeroed and the albedo is prefiltered by the variance estimated from it, as the engine
  sees a frame written without variance buffers (Blender Cycles, most production
  renderers): the same networks serve frames with and without variances. With a teacher,
  the teacher sees each patch whole.
- **Beauty** (`--beauty`): every patch as a frame with only a beauty, albedo and normal
  (`preprocess.as_beauty`: the sum of both components in the diffuse slot, no variances, no
  covariance, the depth dropped in half the patches); exported as the `beauty` variant.
- **Distillation** (`--teacher CKPT --distill W`): the loss is (1 − W) × the loss above
  against the reference plus W × the same loss against a trained network's output on the
  same patch, for a cheaper shape learning from the shipped one (`--init … --reshape`); at
  W = 1 the references are not compared (`step_loss`).
- **Blends kept open** (`--blend-bound Z`): a penalty on blend logits beyond ±Z, so that no
  pyramid level's blend saturates at 0 or 1, where it passes almost no gradient and shuts
  the levels below it for good (docs/training.md, "The blends had shut the coarse levels").
- **Every level a denoiser** (`--level-loss W`): W × the SMAPE of each component's coarser
  pyramid levels (the reconstruction of level l and below, at 1/2^l of the resolution)
  against the target averaged to that level (`losses.level_smape`), so that the coarse
  kernels learn to denoise even while the blend above them is shut, and a blend that opens
  lets in a filtered image rather than an untrained one (docs/training.md, "Every level a
  denoiser").
- **Detail gains** (`--detail-gain`): per-pixel gains on each pyramid level's own detail
  (`MSNet.add_detail_gain`; a fine-tune adds them near one); `--train-only gains` trains
  those heads alone, every other weight kept as the checkpoint's (docs/training.md, "Detail
  gains"); `--train-only gains,blends` (or any set of `gains`, `blends`, `kernels`) the
  1x1 heads named.
- **Schedule**: Adam, one-cycle learning rate (`--lr` peak, cosine; by default 2e-3 for the
  production network, 5e-5 for the paper's, `PEAK_LR`), bf16 autocast on CUDA; with
  `--ema D`, an exponential moving average of the weights (decay D per step, from the
  first weights) is what is validated, kept and exported.
- **Checkpoints** (`runs` directory, `checkpoint.py`): `best.pt` (network weights and
  config, selected on the validation frames by mean log RelMSE + mean log DSSIM),
  `state.pt` (network, its moving average, optimizer, scheduler, step: `--resume`
  continues), `log.jsonl`,
  `val.jsonl`.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from . import losses
from .checkpoint import load_checkpoint, load_msnet, load_state, save_checkpoint, save_msnet, save_state
from .contract import FEATURES_FULL, NOCOV_INDICES
from .data import manifest_frames
from .export import export_onnx, networks_from_onnx
from .exr import read_exr
from .files import append_jsonl, atomic_path, open_append
from .model import DenoiserNet, paper_config
from .msnet import MSNet, add_shape_arguments, from_arguments, pad_to_multiple, transplant
from .preprocess import (ALBEDO, ALBEDO_PASSES, DIFFUSE, EPS, RAW, SPECULAR, VAR, as_beauty, preprocess,
                         raw_from_channels, targets)
from .recon import reconstruct as _recon_v1
from .recon_ms import reconstruct

COV_FEATURES = [i for i in range(len(FEATURES_FULL)) if i not in NOCOV_INDICES]
#: Where a run of `--var-dropout` keeps, after `RAW`, the albedo the engine gives the networks
#: when the file has no variances (prefiltered by an estimated variance, `raw_from_channels`).
ALBEDO_WITHOUT_VARIANCES = slice(len(RAW), len(RAW) + 3)


# ----- data ---------------------------------------------------------------------------


def load_raw(record: dict, cache: Path | None, albedo_prefilter: bool = True,
             keep_albedo: bool = False) -> dict[str, np.ndarray | float]:
    """One record's raw noisy buffers (the albedo prefiltered as the engine does by default,
    unless `albedo_prefilter` is false; with `keep_albedo` followed by the albedo the engine
    gives the networks when the file has no variances, `ALBEDO_WITHOUT_VARIANCES`), reference
    diffuse/specular and frame maxima (cached as .npz beside the data when `cache` is given)."""
    if cache is not None:
        # The prefilter's parameters name the file: a cache of another prefilter is not read.
        prefilter = "-albedo-" + ("-".join(f"{k:g}" for k in ALBEDO_PASSES) if albedo_prefilter else "off")
        prefilter += "-kept" if keep_albedo else ""
        p = cache / (Path(record["noisy"]).stem + prefilter + ".npz")
        if p.exists() and p.stat().st_mtime >= max(os.path.getmtime(record["noisy"]), os.path.getmtime(record["reference"])):
            with np.load(p) as z:
                return {k: z[k] for k in z.files}
    channels = read_exr(record["noisy"])
    raw, dmax, cmax = raw_from_channels(channels, albedo_prefilter=albedo_prefilter)
    if keep_albedo:
        bare = {k: v for k, v in channels.items() if "Variance" not in k}
        raw = np.concatenate([raw, raw_from_channels(bare, albedo_prefilter=albedo_prefilter)[0][ALBEDO]])
    ref = read_exr(record["reference"])
    refs = np.stack([ref[f"{b}.{c}"] for b in ("diffuse", "specular") for c in "RGB"]).astype(np.float32)
    out = {"raw": raw, "ref": np.nan_to_num(refs), "maxima": np.array([dmax, cmax], np.float32)}
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
        with atomic_path(p) as tmp, open(tmp, "wb") as f:
            np.savez(f, **out)
    return out


def tile_to(arrays: list[dict], h: int, w: int) -> list[dict]:
    """Frames cut into non-overlapping tiles of h x w (a remainder at the right and bottom
    is dropped; a frame smaller than a tile gives none); every tile keeps its frame's
    maxima, which the preprocessing normalises by, and its name, sample count and scene."""
    out = []
    for a in arrays:
        H, W = a["raw"].shape[-2:]
        for y in range(0, H - h + 1, h):
            for x in range(0, W - w + 1, w):
                out.append({"raw": a["raw"][..., y:y + h, x:x + w], "ref": a["ref"][..., y:y + h, x:x + w],
                            "maxima": a["maxima"], "meta": a["meta"]})
    return out


def tile_to_smallest(arrays: list[dict]) -> list[dict]:
    """Frames of several sizes as tiles of the smallest height and width ([`tile_to`])."""
    return tile_to(arrays, min(a["raw"].shape[-2] for a in arrays), min(a["raw"].shape[-1] for a in arrays))


class FrameSet:
    """Frames of one split as device tensors: raw [F, 20, H, W] (23 with `keep_albedo`: the
    albedo of the frame without variances after `RAW`), ref [F, 6, H, W], maxima [F, 2].

    `refresh()` adds the frames of scenes completed since (a data set still being rendered
    beside the training), cut to the set's size like the first ones."""

    def __init__(self, dirs: list[str], split: str, device: torch.device, limit: int | None = None,
                 cache: bool = False, albedo_prefilter: bool = True, keep_albedo: bool = False):
        self.dirs, self.split, self.device, self.limit, self.cache = dirs, split, device, limit, cache
        self.albedo_prefilter, self.keep_albedo = albedo_prefilter, keep_albedo
        self.loaded: set[str] = set()  # noisy frame paths
        self.names, self.spp, self.scenes = [], [], []
        self.raw = self.ref = self.maxima = None
        self.refresh()

    def refresh(self) -> int:
        """Loads the frames not loaded yet; returns how many tiles (frames) were added."""
        recs = []
        for d in self.dirs:
            if (Path(d) / "manifest.jsonl").exists():
                recs += [(r, Path(d)) for r in manifest_frames(d) if r.get("split", "train") == self.split]
        recs = [rd for rd in recs[:self.limit] if rd[0]["noisy"] not in self.loaded]
        if not recs:
            return 0
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1)) as pool:
            arrays = list(pool.map(lambda rd: load_raw(rd[0], rd[1] / "raw-cache" if self.cache else None,
                                                    self.albedo_prefilter, self.keep_albedo), recs))
        for (r, _), a in zip(recs, arrays):
            a["meta"] = (Path(r["noisy"]).stem, int(r.get("spp", 0)), str(r.get("scene", "")))
            self.loaded.add(r["noisy"])
        # Frames of several sizes (128² from a CPU beside 256² from a GPU) are cut into tiles
        # of the smallest; frames added later, into tiles of the size the set has.
        if self.raw is None:
            arrays = tile_to_smallest(arrays)
        else:
            h, w = self.raw.shape[-2:]
            small = sum(a["raw"].shape[-2] < h or a["raw"].shape[-1] < w for a in arrays)
            if small:
                print(f"{small} {self.split} frames smaller than {w}x{h} left out", file=sys.stderr, flush=True)
            arrays = tile_to(arrays, h, w)
        if not arrays:
            return 0
        self.names += [a["meta"][0] for a in arrays]
        self.spp += [a["meta"][1] for a in arrays]
        self.scenes += [a["meta"][2] for a in arrays]
        new = {k: torch.from_numpy(np.stack([a[k] for a in arrays])).to(self.device) for k in ("raw", "ref", "maxima")}
        if self.raw is None:
            self.raw, self.ref, self.maxima = new["raw"], new["ref"], new["maxima"]
        else:
            self.raw = torch.cat([self.raw, new["raw"]])
            self.ref = torch.cat([self.ref, new["ref"]])
            self.maxima = torch.cat([self.maxima, new["maxima"]])
        return len(arrays)

    def __len__(self) -> int:
        return len(self.names)


def augment(raw: torch.Tensor, ref: torch.Tensor, g: torch.Generator, a: argparse.Namespace):
    """Flips, transposes, RGB permutation, exposure and injected fireflies, per patch.

    Whole-batch tensor operations, with the random draws made on the host and no value read
    back from the device: a GPU step stays asynchronous."""
    n = raw.shape[0]
    dev = raw.device
    flips = torch.randint(0, 2, (n, 3), generator=g).bool()
    ops = [(flips[:, 0], lambda x: x.flip(-1)), (flips[:, 1], lambda x: x.flip(-2))]
    if raw.shape[-1] == raw.shape[-2]:
        ops.append((flips[:, 2], lambda x: x.transpose(-1, -2)))
    for m, op in ops:
        if m.any():
            m = m.to(dev)[:, None, None, None]
            raw, ref = torch.where(m, op(raw), raw), torch.where(m, op(ref), ref)
    # RGB permutation, shared by both components' colour and the albedo (their variances are
    # one channel each): one gather along the channel axis.
    perm = torch.stack([torch.randperm(3, generator=g) for _ in range(n)])  # [n, 3]
    idx = torch.arange(raw.shape[1]).repeat(n, 1)
    for base in (DIFFUSE.start, SPECULAR.start, ALBEDO.start) + ((ALBEDO_WITHOUT_VARIANCES.start,) if raw.shape[1] > len(RAW) else ()):
        idx[:, base:base + 3] = base + perm
    ref_idx = torch.cat([perm, 3 + perm], 1)
    raw = torch.gather(raw, 1, idx.to(dev)[:, :, None, None].expand_as(raw))
    ref = torch.gather(ref, 1, ref_idx.to(dev)[:, :, None, None].expand_as(ref))
    # Exposure: radiance x k, its variances x k^2 (albedo, normal, depth, covariance unchanged).
    k = torch.exp2((torch.rand(n, 1, 1, 1, generator=g) * 2 - 1) * a.exposure).to(dev)
    raw = raw.clone()
    raw[:, DIFFUSE] *= k
    raw[:, SPECULAR] *= k
    raw[:, VAR["diffuse"]:VAR["specular"] + 1] *= k * k
    ref = ref * k
    if a.fireflies > 0:
        inject_fireflies(raw, g, a.fireflies)
    return raw, ref


def inject_fireflies(raw: torch.Tensor, g: torch.Generator, fraction: float, per_patch: int = 4) -> None:
    """In place: in `fraction` of the patches, `per_patch` isolated samples of 10–10^4 x the
    local level (the mean over 7x7 around it) added to the diffuse or the specular buffer,
    variance raised to match."""
    n, _, h, w = raw.shape
    dev = raw.device
    chosen = torch.nonzero(torch.rand(n, generator=g) < fraction).flatten()
    m = len(chosen) * per_patch
    if m == 0:
        return
    i = chosen.repeat_interleave(per_patch)
    y, x = torch.randint(0, h, (m,), generator=g), torch.randint(0, w, (m,), generator=g)
    specular = torch.rand(m, generator=g) < 0.5
    gain = 10.0 ** (1 + 3 * torch.rand(m, generator=g))
    tint = torch.rand(m, 3, generator=g) * 0.5 + 0.5
    i, y, x, specular, gain, tint = (t.to(dev) for t in (i, y, x, specular, gain, tint))
    base = torch.where(specular, SPECULAR.start, DIFFUSE.start)
    chan = base[:, None] + torch.arange(3, device=dev)  # [m, 3]
    both = torch.stack([raw[:, DIFFUSE], raw[:, SPECULAR]], 1).view(n, 6, h, w)
    local = torch.nn.functional.avg_pool2d(both, 7, stride=1, padding=3, count_include_pad=False).view(n, 2, 3, h, w)
    level = local[i, specular.long(), :, y, x].mean(1).clamp(min=1e-2)  # [m]
    added = level[:, None] * gain[:, None] * tint  # [m, 3]
    raw.index_put_((i[:, None].expand(-1, 3), chan, y[:, None].expand(-1, 3), x[:, None].expand(-1, 3)), added,
                   accumulate=True)
    var = torch.where(specular, VAR["specular"], VAR["diffuse"])
    raw.index_put_((i, var, y, x), added.mean(1) ** 2, accumulate=True)


def crops(fs: FrameSet, n: int, patch: int, g: torch.Generator):
    """`n` random crops of side patch + 1 (the extra row and column give the last pixel's
    forward gradient; it is dropped after preprocessing), gathered in one indexing operation."""
    f = torch.randint(0, len(fs), (n,), generator=g)
    h, w = fs.raw.shape[-2:]
    p = patch + 1
    ys = torch.randint(0, h - p + 1, (n,), generator=g)
    xs = torch.randint(0, w - p + 1, (n,), generator=g)
    dev = fs.raw.device
    rows = (ys[:, None] + torch.arange(p)).to(dev)[:, :, None]  # [n, p, 1]
    cols = (xs[:, None] + torch.arange(p)).to(dev)[:, None, :]  # [n, 1, p]
    fi = f.to(dev)[:, None, None]
    raw = fs.raw[fi, :, rows, cols].permute(0, 3, 1, 2)  # [n, p, p, C] -> [n, C, p, p]
    ref = fs.ref[fi, :, rows, cols].permute(0, 3, 1, 2)
    return raw.contiguous(), ref.contiguous(), fs.maxima[f.to(dev)]


def without_variances(raw: torch.Tensor) -> torch.Tensor:
    """Raw frames `[N, 23, H, W]` (with `ALBEDO_WITHOUT_VARIANCES`) as the engine sees them
    written without any variance buffer: `[N, 20, H, W]`, every variance 0 and the albedo
    prefiltered by the variance the engine estimates from it."""
    out = raw[:, :len(RAW)].clone()
    out[:, ALBEDO] = raw[:, ALBEDO_WITHOUT_VARIANCES]
    out[:, VAR["diffuse"]:VAR["covariance"] + 1] = 0
    return out


def batch_inputs(raw, ref, maxima, cov_dropout: float, g: torch.Generator, crop: int | None = None,
                 var_dropout: float = 0.0):
    """Preprocessed network inputs and targets of raw patches (covariance zeroed in a
    `cov_dropout` fraction; with `var_dropout`, raw patches of 23 channels seen
    `without_variances` in that fraction and the inputs of the whole patches kept as
    `teacher_*`), cropped to `crop` pixels."""
    whole = None
    if var_dropout > 0:
        drop = (torch.rand(raw.shape[0], generator=g) < var_dropout).to(raw.device).view(-1, 1, 1, 1)
        whole = raw[:, :len(RAW)]
        raw = torch.where(drop, without_variances(raw), whole)
    inp = preprocess(raw, maxima[:, 0], maxima[:, 1], "full")
    tgt = targets(ref[:, 0:3], ref[:, 3:6], inp["albedo"])
    taught = {} if whole is None else preprocess(whole, maxima[:, 0], maxima[:, 1], "full")
    if cov_dropout > 0:
        keep = (torch.rand(raw.shape[0], generator=g) >= cov_dropout).to(raw.device, raw.dtype)
        for t in (inp, taught):
            if t:
                t["features"][:, COV_FEATURES] *= keep.view(-1, 1, 1, 1)
    out = {**inp, **tgt, **{f"teacher_{k}": v for k, v in taught.items()}}
    if crop is not None:
        out = {k: v[..., :crop, :crop] for k, v in out.items()}
    return out


# ----- training -----------------------------------------------------------------------


class Lin2020Pair(nn.Module):
    """The paper's network (Lin et al. 2020 at its published size, contract v1): one
    `DenoiserNet` per component, trained here with the same data and recipe as `MSNet`."""

    size_multiple = 1

    def __init__(self, in_features: int = len(FEATURES_FULL), **config):
        super().__init__()
        cfg = {**paper_config(in_features), **config}
        self.diffuse, self.specular = DenoiserNet(**cfg), DenoiserNet(**cfg)
        self.config = {"arch": "lin2020", **self.diffuse.config}

    def forward(self, diffuse, specular, features):
        return self.diffuse(diffuse, features), self.specular(specular, features)

    def flops_per_pixel(self) -> int:
        return self.diffuse.flops_per_pixel() + self.specular.flops_per_pixel()

    def description(self) -> str:
        return "lin2020 pair: " + self.diffuse.description()


def outputs(net, b: dict[str, torch.Tensor], autocast: bool) -> list[torch.Tensor]:
    """The network's outputs on a batch, in float32 (the graph's outputs, before any reconstruction)."""
    with torch.autocast(device_type=b["diffuse"].device.type, dtype=torch.bfloat16, enabled=autocast):
        out = net(b["diffuse"], b["specular"], b["features"])
    return [o.float() for o in out]


def reconstructed(net, out: list[torch.Tensor], b: dict[str, torch.Tensor]):
    """The filtered batch from the network's `outputs`."""
    if isinstance(net, Lin2020Pair):
        return _recon_v1(out[0], out[1], b["diffuse"][:, :3], b["specular"][:, :3], b["albedo"])
    return reconstruct(out, net.levels, b["diffuse"], b["specular"], b["albedo"],
                       specular_pyramid=net.specular_pyramid)


def forward(net, b: dict[str, torch.Tensor], autocast: bool):
    return reconstructed(net, outputs(net, b, autocast), b)


def blend_excess(out: list[torch.Tensor], levels: int, bound: float) -> torch.Tensor:
    """Mean over the blend outputs of (|logit| − bound)² where |logit| exceeds `bound` (0
    inside): a penalty that keeps every pyramid level's blend within sigmoid(±bound), where
    it still passes gradient (a saturated blend shuts the levels below it and does not
    reopen: docs/training.md, "The blends had shut the coarse levels")."""
    blends = out[levels:]
    return sum(torch.relu(b.abs() - bound).square().mean() for b in blends) / max(1, len(blends))


@torch.no_grad()
def distill_batch(teacher, b: dict[str, torch.Tensor], autocast: bool) -> dict[str, torch.Tensor]:
    """The batch with the teacher's output on it as the targets (knowledge distillation): its
    components in their preprocessed domains and its final color; the teacher sees the
    batch's `teacher_*` inputs where there are (`batch_inputs`), the batch itself elsewhere."""
    whole = {k[len("teacher_"):]: v for k, v in b.items() if k.startswith("teacher_")}
    t = forward(teacher, whole or b, autocast)
    # With inputs of its own (`--var-dropout`) the teacher's diffuse is demodulated by the
    # student's albedo, as the reference's is (`targets`).
    diffuse = t.diffuse / (b["albedo"] + EPS) if whole else t.diffuse_pre
    return {**b, "diffuse_target": diffuse, "specular_target": t.specular_pre, "reference": t.total}


def step_loss(net, out_b: list[torch.Tensor], rec, b: dict[str, torch.Tensor], a: argparse.Namespace,
              perceptual=None, teacher=None, autocast: bool = False) -> tuple[torch.Tensor, dict[str, float]]:
    """One batch's training loss and its logged parts: `losses.ms_loss` against the
    references, mixed with the same loss against the teacher's output (`--distill W`: the
    teacher's share; at W = 1 the references' loss is not computed), then the blend penalty
    (`--blend-bound`), which keeps its full weight whatever W is."""
    def loss_to(target: dict) -> tuple[torch.Tensor, dict[str, float]]:
        return losses.ms_loss(rec, target, l1_weight=a.l1, ssim_weight=a.ssim, perceptual=perceptual,
                              perceptual_weight=a.perceptual, relmse_weight=a.relmse, level_weight=a.level_loss,
                              specular_pyramid=getattr(net, "specular_pyramid", "log"), msssim_weight=a.msssim)

    w = a.distill if teacher is not None else 0.0
    loss, parts = loss_to(b) if w < 1.0 else (rec.total.new_zeros(()), {})
    if teacher is not None:
        taught, _ = loss_to(distill_batch(teacher, b, autocast))
        parts["distill"] = float(taught.detach())
        loss = (1.0 - w) * loss + w * taught
    if a.blend_bound > 0:
        excess = blend_excess(out_b, net.levels, a.blend_bound)
        parts["blend_excess"] = float(excess.detach())
        loss = loss + a.blend_penalty * excess
    return loss, parts


@torch.no_grad()
def denoise_whole(net, raw: torch.Tensor, maxima: torch.Tensor, zero_cov: bool = False) -> torch.Tensor:
    """Whole frames [N, 20, H, W] denoised (padded to the network's size multiple): [N, 3, H, W]."""
    h, w = raw.shape[-2:]
    b = preprocess(raw, maxima[:, 0], maxima[:, 1], "full")
    if zero_cov:
        b["features"][:, COV_FEATURES] = 0
    b = {k: pad_to_multiple(v, net.size_multiple) for k, v in b.items()}
    rec = forward(net, b, autocast=False)
    return rec.total[..., :h, :w]


def validate(net: MSNet, val: FrameSet, zero_cov: bool = False, beauty: bool = False,
             no_variances: bool = False) -> dict[str, float]:
    net.eval()
    rel, dssim, inp = [], [], []
    for i in range(len(val)):
        raw = val.raw[i:i + 1]
        raw = as_beauty(raw) if beauty else without_variances(raw) if no_variances else raw[:, :len(RAW)]
        out = denoise_whole(net, raw, val.maxima[i:i + 1], zero_cov)
        ref = val.ref[i:i + 1, 0:3] + val.ref[i:i + 1, 3:6]
        noisy = val.raw[i:i + 1, DIFFUSE] + val.raw[i:i + 1, SPECULAR]
        rel.append(float(losses.relmse(out, ref)))
        dssim.append(float(losses.dssim(out, ref)))
        inp.append(float(losses.relmse(noisy, ref)))
    v = {"relmse": float(np.mean(rel)), "dssim": float(np.mean(dssim)), "input_relmse": float(np.mean(inp)),
         "score": float(np.mean(np.log(rel)) + np.mean(np.log(np.maximum(dssim, 1e-6))))}
    if isinstance(net, Lin2020Pair) and len(val) and not zero_cov:
        v["kernel_peak"] = kernel_peak(net, val.raw[0:1], val.maxima[0:1])
    net.train()
    return v


def scored(net, val: FrameSet, a) -> dict:
    """The validation row of `net`: its scores, those without covariance (`nocov`) and, for
    a run of `--var-dropout`, those without any variance or covariance (`novar`)."""
    v = validate(net, val, beauty=a.beauty)
    if not a.beauty:
        v["nocov"] = validate(net, val, zero_cov=True)
    if a.var_dropout > 0:
        # A frame without variances usually has no covariance either (Cycles).
        v["novar"] = validate(net, val, zero_cov=True, no_variances=True)
    return v


def selection_score(v: dict, select: str) -> float:
    """The score checkpoints are chosen by: the network's with covariance (`full`), or the
    mean of that and its score without (`both`; frames from most renderers carry no
    covariance and are served by `nocov`), or the mean of those and the score without any
    variance (`all`, for a run of `--var-dropout`)."""
    if select == "both" and "nocov" in v:
        return 0.5 * (v["score"] + v["nocov"]["score"])
    if select == "all" and "nocov" in v and "novar" in v:
        return (v["score"] + v["nocov"]["score"] + v["novar"]["score"]) / 3
    return v["score"]


def save_best(path: Path, net, step: int, v: dict, a) -> None:
    """Keeps `net` as the run's best.pt: an msnet checkpoint, or the paper's pair."""
    if isinstance(net, Lin2020Pair):
        save_checkpoint(path, {"diffuse": net.diffuse, "specular": net.specular}, step=step, val=v,
                        train_config=vars(a))
    else:
        save_msnet(path, net, step=step, val=v)


def baseline(net, val: FrameSet, a, out: Path) -> float:
    """Scores the network a fine-tune starts from (`--init`) as step 0 of val.jsonl and keeps
    it as best.pt; returns its score, the one later checkpoints must beat."""
    v = scored(net, val, a)
    v.update(step=0, time=0.0, init=str(a.init))
    append_jsonl(out / "val.jsonl", v)
    print(f"validation of {a.init} (the start): RelMSE {v['relmse']:.5f} DSSIM {v['dssim']:.4f}",
          file=sys.stderr, flush=True)
    save_best(out / "best.pt", net, 0, v, a)
    return selection_score(v, a.select)


@torch.no_grad()
def kernel_peak(net: Lin2020Pair, raw: torch.Tensor, maxima: torch.Tensor) -> float:
    """The mean over pixels and both components of a frame of the largest weight of each
    21x21 kernel: 1/441 for a box, 1 for one-hot kernels (saturated, they pass no gradient)."""
    b = preprocess(raw, maxima[:, 0], maxima[:, 1], "full")
    peaks = [torch.softmax(sub(b[c], b["features"]).float(), 1).amax(1).mean()
             for c, sub in (("diffuse", net.diffuse), ("specular", net.specular))]
    return float(sum(peaks) / len(peaks))


def export_lin2020(checkpoint: Path, models: Path) -> None:
    """The paper's pair as contract-v1 files in `models/lin2020/`, named variant `lin2020`,
    their weights stored in float16 (computed in float32): 4.5 MB a component instead of 8.9,
    since the repository's working tree is what a GPU lease carries (64 MiB at most)."""
    nets, _ = load_checkpoint(checkpoint)
    for c, net in nets.items():
        path = models / "lin2020" / f"{c}.onnx"
        export_onnx(net, path, c, "full", name="lin2020", half_weights=True)
        print(f"{path}: {net.param_count()} params, {net.flops_per_pixel()} FLOP/px", file=sys.stderr)


# Peak learning rates by architecture. The paper's network at its width (8 residual blocks
# of 64 channels per extractor, a 3x3 head over 128 channels; no normalisation) grows its
# activations under Adam at the production network's rate until its softmax saturates: one-hot
# kernels, which pass no gradient (docs/training.md, "The paper's network at its width").
PEAK_LR = {"msnet": 2e-3, "lin2020": 5e-5}


# The heads --train-only can train alone: their parameters' prefixes in MSNet.
HEAD_MODULES = {"gains": "gain_heads.", "blends": "blend_heads.", "kernels": "kernel_heads."}


def train_only(value: str) -> str:
    """`all`, or a comma-separated set of HEAD_MODULES' names (argparse type)."""
    if value == "all":
        return value
    heads = value.split(",")
    unknown = [h for h in heads if h not in HEAD_MODULES]
    if unknown:
        raise argparse.ArgumentTypeError(f"{value!r}: `all` or a comma-separated set of {', '.join(HEAD_MODULES)}")
    return ",".join(dict.fromkeys(heads))


def parse(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", action="append", required=True, help="data set directory (repeatable)")
    p.add_argument("--out", required=True)
    p.add_argument("--steps", type=int, default=20000)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--patch", type=int, default=128)
    p.add_argument("--lr", type=float, default=None,
                   help="peak learning rate of the one-cycle schedule (default by --arch: "
                        + ", ".join(f"{k} {v:g}" for k, v in PEAK_LR.items()) + ")")
    p.add_argument("--exposure", type=float, default=2.0, help="exposure augmentation range in stops (±)")
    p.add_argument("--fireflies", type=float, default=0.25, help="fraction of patches with injected fireflies")
    p.add_argument("--cov-dropout", type=float, default=0.3, help="fraction of patches with covariance zeroed")
    p.add_argument("--var-dropout", type=float, default=0.0,
                   help="fraction of patches seen as a frame without variance buffers: every variance zeroed, "
                        "the albedo prefiltered by the variance estimated from it (as the engine sees such a frame)")
    p.add_argument("--select", choices=("full", "both", "all"), default="full",
                   help="the validation score best.pt is chosen by: with covariance (`full`), the mean of "
                        "that and the score without it (`both`: `full` and `nocov` alike), or the mean of those "
                        "and the score without any variance (`all`, with --var-dropout)")
    p.add_argument("--l1", type=float, default=1.0, help="weight of L1 on log(1 + color)")
    p.add_argument("--ssim", type=float, default=0.0, help="weight of DSSIM of the final color")
    p.add_argument("--msssim", type=float, default=0.0,
                   help="weight of 1 - MS-SSIM of the final color (five scales, losses.ms_ssim)")
    p.add_argument("--relmse", type=float, default=0.0,
                   help="weight of RelMSE of the final color (losses.relmse_huber: the metric's per-pixel "
                        "term, linear beyond 10x a pixel's scale)")
    p.add_argument("--perceptual", type=float, default=0.0)
    p.add_argument("--albedo-prefilter", choices=("on", "off"), default="on",
                   help="prefilter the albedo as the engine does (`mcdenoise run --albedo-prefilter`, on by default)")
    p.add_argument("--val-every", type=int, default=500)
    p.add_argument("--val-frames", type=int, default=None)
    p.add_argument("--raw-cache", action="store_true",
                   help="keep each frame's raw buffers as .npz beside the data (faster loading next time)")
    p.add_argument("--time-limit", type=float, default=None, help="stop (saving state) after this many seconds of this run (a resumed run counts afresh)")
    p.add_argument("--deadline", type=float, default=None,
                   help="unix time by which training, validation and export must be done: caps --time-budget "
                        "and --time-limit at what is left after loading the data, less a minute for the export")
    p.add_argument("--time-budget", type=float, default=None,
                   help="fit the schedule to this many seconds of training: after 50 steps the step count is set "
                        "from the measured rate (and kept on resume)")
    p.add_argument("--reload-every", type=float, default=0.0, metavar="S",
                   help="every S seconds, add the training frames of scenes completed since (a data set being "
                        "rendered beside the training); 0: never. Validation frames stay those of the start")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=os.cpu_count())
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--resume", action="store_true")
    p.add_argument("--init", default=None,
                   help="start from this checkpoint's weights (its shape; a fresh optimizer and schedule): "
                        "fine-tuning, e.g. with other loss weights; with --arch lin2020 a lin2020 run's best.pt or a "
                        "served pair's directory (models/lin2020)")
    p.add_argument("--reshape", action="store_true",
                   help="with --init: train the shape the shape options give (fewer extractor blocks, narrower "
                        "decoder levels), started from the checkpoint's weights where they fit (msnet.transplant)")
    p.add_argument("--blend-shift", type=float, default=0.0, metavar="B",
                   help="with --init: add B to every blend logit's bias of the network it starts from, reopening "
                        "coarse pyramid levels whose blends have saturated at 0 (docs/training.md); the network to "
                        "beat, kept as best.pt until a validation does, stays the one before the shift")
    p.add_argument("--blend-bound", type=float, default=0.0, metavar="Z",
                   help="penalise blend logits beyond ±Z (0: off; 4 keeps every blend within 0.018–0.982), so that "
                        "no pyramid level's blend saturates and stops passing gradient (docs/training.md)")
    p.add_argument("--blend-penalty", type=float, default=0.01, metavar="W",
                   help="weight of the --blend-bound penalty (mean squared excess of the logits beyond the bound)")
    p.add_argument("--level-loss", type=float, default=0.0, metavar="W",
                   help="add W x the SMAPE of every coarser pyramid level's reconstruction against the target "
                        "averaged to that level (losses.level_smape; 0: off)")
    p.add_argument("--train-only", type=train_only, default="all",
                   help="`all`, or a comma-separated set of the 1x1 heads to train, every other weight kept as it "
                        "starts: `gains` (the detail-gain heads, with --detail-gain), `blends`, `kernels`; e.g. "
                        "`gains,blends`")
    p.add_argument("--teacher", default=None,
                   help="distil from this msnet checkpoint: the loss also compares the output with the teacher's "
                        "on the same patch (weight --distill)")
    p.add_argument("--distill", type=float, default=0.5,
                   help="with --teacher: the teacher's share of the loss, the reference's is 1 - W")
    p.add_argument("--ema", type=float, default=0.0, metavar="DECAY",
                   help="validate, keep and export an exponential moving average of the weights (decay per step, "
                        "e.g. 0.999; started at the first weights, those of --init for a fine-tune); 0: the weights "
                        "as trained")
    p.add_argument("--arch", choices=("msnet", "lin2020"), default="msnet")
    p.add_argument("--lin-width", type=int, default=64, help="lin2020: extractor width (paper: 64)")
    p.add_argument("--lin-blocks", type=int, default=8, help="lin2020: residual blocks (paper: 8)")
    p.add_argument("--lin-predictor-width", type=int, default=128, help="lin2020: predictor width (paper: 128)")
    p.add_argument("--beauty", action="store_true",
                   help="train the `beauty` variant: patches with only a beauty, albedo and normal (see above)")
    add_shape_arguments(p)
    p.add_argument("--export", default=None, help="export best.pt as contract-v2 full and nocov (with --beauty: beauty) into this models directory")
    return p.parse_args(argv)


# Steps at which a run with a time budget fits its schedule's length to the measured rate.
FIT_AT = (50, 250, 1000)


def fitted_steps(step: int, rate: float, budget: float, elapsed: float) -> int:
    """The schedule's length for a run at `step` going `rate` steps/s with `elapsed` of its
    `budget` seconds spent. Validation passes take time too: they are budgeted at 5 %. The
    schedule always has some steps left, so a late fit still anneals the learning rate."""
    return max(step + max(50, step // 10), int(step + rate * (0.95 * budget - elapsed)))


def main(argv=None) -> int:
    a = parse(argv)
    if a.blend_shift and (not a.init or a.reshape or a.arch != "msnet"):
        raise SystemExit("--blend-shift raises the blends of the network a fine-tune starts from: it needs --init "
                         "(without --reshape)")
    if a.reshape and a.arch != "msnet":
        raise SystemExit("--reshape narrows the production network (--arch msnet); lin2020 keeps its checkpoint's shape")
    if a.reshape and not a.init:
        raise SystemExit("--reshape needs --init (the checkpoint whose weights start the new shape)")
    if a.blend_bound < 0 or a.blend_penalty < 0:
        raise SystemExit(f"--blend-bound {a.blend_bound} --blend-penalty {a.blend_penalty}: neither may be negative")
    if a.blend_bound > 0 and a.arch != "msnet":
        raise SystemExit("--blend-bound bounds the production network's blends (--arch msnet); lin2020 has none")
    if a.level_loss < 0:
        raise SystemExit(f"--level-loss {a.level_loss}: may not be negative")
    if a.level_loss > 0 and a.arch != "msnet":
        raise SystemExit("--level-loss weighs the production network's pyramid levels (--arch msnet); lin2020 has none")
    if a.teacher and a.arch != "msnet":
        raise SystemExit("--teacher distils into the production network (--arch msnet)")
    if a.lr is None:
        a.lr = PEAK_LR[a.arch]
    if not 0.0 <= a.ema < 1.0:
        raise SystemExit(f"--ema {a.ema}: the decay per step is at least 0 and below 1")
    if not 0.0 <= a.distill <= 1.0:
        raise SystemExit(f"--distill {a.distill}: the teacher's share of the loss is between 0 and 1")
    if not 0.0 <= a.var_dropout <= 1.0:
        raise SystemExit(f"--var-dropout {a.var_dropout}: a fraction of the patches, between 0 and 1")
    if a.var_dropout > 0 and (a.beauty or a.arch != "msnet"):
        raise SystemExit("--var-dropout trains the production network with and without variances (--arch msnet, "
                         "not --beauty, which sees no variances at all)")
    if a.select == "all" and not a.var_dropout:
        raise SystemExit("--select all scores frames without variances too: it needs --var-dropout")
    torch.set_num_threads(max(1, a.threads))
    torch.set_flush_denormal(True)
    dev = torch.device(a.device)
    autocast = dev.type == "cuda"
    if autocast:
        torch.backends.cudnn.benchmark = True
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    t_load = time.time()
    prefilter = a.albedo_prefilter == "on"
    keep = a.var_dropout > 0  # the albedo of each frame without variances, for the patches seen so
    train = FrameSet(a.data, "train", dev, cache=a.raw_cache, albedo_prefilter=prefilter, keep_albedo=keep)
    val = FrameSet(a.data, "val", dev, a.val_frames, cache=a.raw_cache, albedo_prefilter=prefilter, keep_albedo=keep)
    if not len(train):
        raise SystemExit(f"{a.data}: no training frames")
    if min(train.raw.shape[-2:]) < a.patch + 1:
        raise SystemExit(f"--patch {a.patch} needs frames of at least {a.patch + 1} pixels a side "
                         f"(the training frames are {train.raw.shape[-1]}x{train.raw.shape[-2]})")
    print(f"{len(train)} training / {len(val)} validation frames loaded in {time.time() - t_load:.0f} s",
          file=sys.stderr, flush=True)
    if a.deadline is not None:
        left = a.deadline - time.time() - 60
        a.time_budget = left if a.time_budget is None else min(a.time_budget, left)
        a.time_limit = left if a.time_limit is None else min(a.time_limit, left)
    torch.manual_seed(a.seed)
    if a.beauty:
        a.cov_dropout = 0.0  # no covariance at all
    unshifted = None  # with --blend-shift, the --init network as it was (the one to beat)
    if a.arch == "lin2020":
        if a.beauty:
            raise SystemExit("--beauty trains the production network (--arch msnet)")
        if a.init:  # a pair trained before (its shape), on for another lease
            # A run's best.pt, or a served pair's directory (models/lin2020): its files
            # carry their torch configuration and weights.
            nets = networks_from_onnx(a.init) if Path(a.init).is_dir() else load_checkpoint(a.init)[0]
            net = Lin2020Pair(**nets["diffuse"].config)
            for c in ("diffuse", "specular"):
                getattr(net, c).load_state_dict(nets[c].state_dict())
        else:
            net = Lin2020Pair(width=a.lin_width, blocks=a.lin_blocks, predictor_width=a.lin_predictor_width)
        a.cov_dropout = 0.0  # the paper's network always has covariance
    elif a.init and a.reshape:
        source = load_msnet(a.init)[0]
        a.specular_pyramid = a.specular_pyramid or source.specular_pyramid
        net = from_arguments(a, len(FEATURES_FULL))
        for note in transplant(source, net):
            print(f"--reshape: {note}", file=sys.stderr)
        net.train()
    elif a.init:
        net = load_msnet(a.init)[0].train()
        if a.specular_pyramid:  # the weights do not depend on it: a fine-tune may switch
            net.specular_pyramid = a.specular_pyramid
        if a.detail_gain and not net.detail_gain:
            # Heads at sigmoid(GAIN_START): the start is nearly the checkpoint, and the network
            # to beat, kept as best.pt until a validation does, is the checkpoint itself.
            unshifted = copy.deepcopy(net)
            net.add_detail_gain()
        if a.blend_shift:
            unshifted = unshifted or copy.deepcopy(net)
            # A blend at sigmoid(-6) passes almost no gradient, so the levels below it neither
            # contribute nor learn; raising the logits lets the fine-tune decide again.
            with torch.no_grad():
                for head in net.blend_heads:
                    head.bias += a.blend_shift
        for k, v in net.config.items():  # the run's config shows the shape it trained
            if k in ("enc", "dec"):
                v = ",".join(map(str, v))
            if k != "arch" and k != "in_features":
                setattr(a, k, v)
    else:
        net = from_arguments(a, len(FEATURES_FULL))
    net = net.to(dev).to(memory_format=torch.channels_last)
    if a.train_only != "all":
        heads = a.train_only.split(",")
        if "gains" in heads and not getattr(net, "detail_gain", False):
            raise SystemExit("--train-only gains trains the detail-gain heads: it needs --detail-gain")
        # Every other weight stays the checkpoint's (with `gains` alone, its kernels and blends
        # exactly, so that what the run changes is how much of each level's detail passes).
        prefixes = tuple(HEAD_MODULES[h] for h in heads)
        for name, p in net.named_parameters():
            p.requires_grad_(name.startswith(prefixes))
    opt = torch.optim.Adam([p for p in net.parameters() if p.requires_grad], lr=a.lr)
    teacher = None
    if a.teacher:
        teacher = load_msnet(a.teacher)[0].to(dev).to(memory_format=torch.channels_last).eval()
        teacher.requires_grad_(False)
        print(f"distilling from {a.teacher} ({teacher.flops_per_pixel() / 1e6:.3f} MFLOP/px), weight {a.distill}",
              file=sys.stderr, flush=True)

    def schedule(total: int, done: int = 0):
        """One-cycle schedule over `total` steps, advanced past the `done` steps taken (the
        schedule is a function of the step alone, so a resumed run may also be longer)."""
        for group in opt.param_groups:
            group.pop("initial_lr", None)
        sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=a.lr, total_steps=total, pct_start=0.15,
                                                    anneal_strategy="cos", div_factor=25.0, final_div_factor=1e3)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for _ in range(done):
                sched.step()
        return sched

    sched = schedule(a.steps)
    perceptual = None
    if a.perceptual > 0:
        from .perceptual import PerceptualLoss

        perceptual = PerceptualLoss().to(dev)
    step, best, elapsed, fitted = 0, math.inf, 0.0, False
    state_path = out / "state.pt"
    st = None
    if a.resume and state_path.exists():
        st = load_state(state_path, map_location=dev)
        net.load_state_dict(st["model"])
        opt.load_state_dict(st["opt"])
        step, best, elapsed = st["step"], st["best"], st["elapsed"]
        if st.get("fitted"):  # a schedule fitted to a time budget keeps its length
            a.steps, a.time_budget, fitted = st["steps"], None, True
        sched = schedule(a.steps, done=step)
        print(f"resumed at step {step}", file=sys.stderr)
        frames_changed = st.get("val_names") not in (None, list(val.names))
        select_changed = st.get("select", "full") != a.select
        if (frames_changed or select_changed) and isinstance(net, MSNet) and (out / "best.pt").exists():
            # The validation scenes changed since (a data set rendered between the runs), or
            # the score that selects: a score on other frames, or another score, does not
            # compare, so best.pt is scored again.
            best = selection_score(scored(load_msnet(out / "best.pt")[0].to(dev), val, a), a.select)
            why = (f"validation frames changed ({len(st['val_names'])} -> {len(val)})" if frames_changed
                   else f"selection changed ({st.get('select', 'full')} -> {a.select})")
            print(f"{why}: best.pt scored again, {best:.3f}", file=sys.stderr, flush=True)
    # The weights validated, kept and exported: the trained ones, or their moving average,
    # which starts at the weights the run starts with (a fine-tune averages away from the
    # network it starts from) or, resumed, continues from the saved one.
    ema = None
    if a.ema > 0:
        ema = AveragedModel(net, multi_avg_fn=get_ema_multi_avg_fn(a.ema), use_buffers=True)
        ema.update_parameters(net)
        if st is not None and st.get("ema") is not None:
            ema.load_state_dict(st["ema"])
    judged = ema.module if ema is not None else net
    (out / "config.json").write_text(json.dumps(vars(a), indent=2))
    print(f"training: {net.description()}; {net.flops_per_pixel() / 1e6:.3f} MFLOP/px", file=sys.stderr, flush=True)
    if a.init and not a.reshape and step == 0 and len(val):
        # A fine-tune starts from a trained network: that network, scored on the same
        # validation frames, is the one to beat, so best.pt is never worse than the start
        # (with --blend-shift, the network as it was before the shift).
        best = baseline(unshifted if unshifted is not None else judged, val, a, out)
    log = open_append(out / "log.jsonl")
    t0 = time.time() - elapsed
    g = torch.Generator().manual_seed(a.seed * 1_000_003 + step)

    def save_resume():
        save_state(state_path, model=net.state_dict(), opt=opt.state_dict(), fitted=fitted,
                   ema=ema.state_dict() if ema is not None else None,
                   step=step, steps=a.steps, best=best, elapsed=time.time() - t0, val_names=list(val.names),
                   select=a.select)

    stop = False
    t_fit = t_run = t_reload = time.time()
    fit_from = step
    while step < a.steps and not stop:
        if a.reload_every > 0 and time.time() - t_reload >= a.reload_every:
            t_reload = time.time()
            added = train.refresh()
            if added:
                print(f"step {step}: {added} training frames added, {len(train)} in all", file=sys.stderr, flush=True)
        raw, ref, maxima = crops(train, a.batch, a.patch, g)
        raw, ref = augment(raw, ref, g, a)
        if a.beauty:
            raw, ref = as_beauty(raw, ref, keep_depth=torch.rand(a.batch, generator=g) < 0.5)
        b = batch_inputs(raw, ref, maxima, a.cov_dropout, g, crop=a.patch, var_dropout=a.var_dropout)
        b = {k: v.contiguous(memory_format=torch.channels_last) for k, v in b.items()}
        out_b = outputs(net, b, autocast)
        rec = reconstructed(net, out_b, b)
        loss, parts = step_loss(net, out_b, rec, b, a, perceptual, teacher, autocast)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        sched.step()
        if ema is not None:
            ema.update_parameters(net)
        step += 1
        if a.time_budget is not None and step in FIT_AT:
            # The first steps are slower (cuDNN's autotuning, allocator growth, a renderer
            # starting beside): the length is fitted again on the rates of later steps.
            rate = (step - fit_from) / (time.time() - t_fit)
            a.steps = fitted_steps(step, rate, a.time_budget, time.time() - t0)
            a.val_every = max(50, a.steps // 8)
            sched = schedule(a.steps, done=step)
            fitted = True
            fit_from, t_fit = step, time.time()
            print(f"{rate:.1f} steps/s: schedule fitted to {a.steps} steps", file=sys.stderr, flush=True)
        if step % 20 == 0:
            row = {"step": step, "loss": float(loss.detach()), **parts, "lr": sched.get_last_lr()[0], "time": time.time() - t0,
                   "frames": len(train)}
            log.write(json.dumps(row) + "\n")
            log.flush()
            if step % 100 == 0:
                print(f"step {step}/{a.steps} loss {row['loss']:.4f} {row['time']:.0f}s", file=sys.stderr, flush=True)
        stop = a.time_limit is not None and time.time() - t_run > a.time_limit
        if step % a.val_every == 0 or step == a.steps or stop:
            v = scored(judged, val, a) if len(val) else {"score": float(loss.detach()), "relmse": float("nan")}
            v.update(step=step, time=time.time() - t0)
            append_jsonl(out / "val.jsonl", v)
            peak = f", largest kernel weight {v['kernel_peak']:.3f}" if "kernel_peak" in v else ""
            print(f"validation at {step}: RelMSE {v['relmse']:.5f} DSSIM {v.get('dssim', float('nan')):.4f} "
                  f"(input {v.get('input_relmse', float('nan')):.4f}){peak}", file=sys.stderr, flush=True)
            score = selection_score(v, a.select)
            if score < best:
                best = score
                save_best(out / "best.pt", judged, step, v, a)
            save_resume()
    log.close()
    if a.export and a.arch == "lin2020":
        export_lin2020(out / "best.pt", Path(a.export))
    elif a.export:
        from . import export_ms

        variants = ["--variants", "beauty"] if a.beauty else []
        export_ms.main(["--checkpoint", str(out / "best.pt"), "--out", a.export, *variants])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

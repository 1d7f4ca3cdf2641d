"""Train the diffuse and specular networks of one variant (`full` or `nocov`).

    python -m mcdenoise_train.train --data DATA --out runs/NAME --variant full [options]

What happens (Lin et al. 2020, Sec. 5; KPCN patch selection):

- frames are preprocessed by the engine (`data.py`), patches drawn by importance;
- the two networks are independent (own parameters, own Adam optimizer at lr 1e-4,
  Xavier initialisation); each step trains both on the same patches;
- the diffuse loss compares the filtered irradiance `d'` with the reference irradiance,
  the specular loss compares in the log domain `ln(1 + s)`, as in the paper;
- the loss is SMAPE, plus `--perceptual W` times the perceptual loss on ImageNet VGG-16
  features (`perceptual.py`), plus `--log-l1 W` times an L1 term in the log domain
  (`log_l1`: SMAPE alone gives no gradient against bright leaks onto dark targets);
- every `--val-every` steps the whole validation frames are denoised (both networks,
  inverse transforms, diffuse + specular) and RelMSE / DSSIM against the reference are
  logged; the best checkpoint by validation RelMSE is kept as `best.pt`;
- `state.pt` holds everything needed to resume (networks, optimizers, step, data
  sampler seed); `--resume` continues from it (both files: `checkpoint.py`);
- `log.jsonl` (training losses), `val.jsonl` and `curves.png` record progress.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from .checkpoint import load_state, save_checkpoint, save_state
from .contract import COMPONENTS, feature_count
from .data import PatchSampler, load_frames
from .files import append_jsonl, open_append, read_jsonl
from .losses import log_l1, relmse, smape
from .model import DenoiserNet
from .recon import apply_kernel, inverse_diffuse, inverse_specular


TARGET = {"diffuse": "diffuse_target", "specular": "specular_target"}
COLOR = {"diffuse": "diffuse_color", "specular": "specular_color"}


def component_loss(net: DenoiserNet, batch: dict[str, torch.Tensor], component: str, perceptual=None,
                   perceptual_weight: float = 0.0, l1_weight: float = 0.0) -> tuple[torch.Tensor, dict[str, float]]:
    color = batch[COLOR[component]]
    out = apply_kernel(net(color, batch["features"]), color[:, :3])
    target = batch[TARGET[component]]
    loss = smape(out, target)
    parts = {"smape": float(loss.detach())}
    if l1_weight > 0:
        l1 = log_l1(out, target, component)
        parts["log_l1"] = float(l1.detach())
        loss = loss + l1_weight * l1
    if perceptual is not None and perceptual_weight > 0:
        # The perceptual features see the component in its own (irradiance / log) domain.
        p = perceptual(out, target)
        parts["perceptual"] = float(p.detach())
        loss = loss + perceptual_weight * p
    return loss, parts


@torch.no_grad()
def denoise_frame(models: dict[str, DenoiserNet], arrays: dict[str, np.ndarray]) -> np.ndarray:
    """Whole-frame denoising with both networks: the final color `[3, H, W]`."""
    t = {k: torch.from_numpy(v)[None] for k, v in arrays.items()}
    filtered = {}
    for c in COMPONENTS:
        color = t[COLOR[c]]
        filtered[c] = apply_kernel(models[c](color, t["features"]), color[:, :3])
    out = inverse_diffuse(filtered["diffuse"], t["albedo"]) + inverse_specular(filtered["specular"])
    return out[0].numpy()


def validate(models, frames) -> dict[str, float]:
    for m in models.values():
        m.eval()
    rows = []
    for f in frames:
        out = denoise_frame(models, f.arrays)
        rows.append((float(relmse(out, f.arrays["reference"])), float(relmse(f.arrays["noisy"], f.arrays["reference"]))))
    for m in models.values():
        m.train()
    return {"relmse": float(np.mean([r[0] for r in rows])), "input_relmse": float(np.mean([r[1] for r in rows]))}


def plot_curves(out_dir: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    log = read_jsonl(out_dir / "log.jsonl", missing_ok=True)
    val = read_jsonl(out_dir / "val.jsonl", missing_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for c in COMPONENTS:
        steps = [r["step"] for r in log]
        vals = [r[f"{c}_loss"] for r in log]
        k = max(1, len(vals) // 100)
        smooth = np.convolve(vals, np.ones(k) / k, mode="valid") if vals else []
        axes[0].plot(steps[k - 1:], smooth, label=c)
    axes[0].set(xlabel="step", ylabel="training loss", title="training loss (moving average)", yscale="log")
    axes[0].legend()
    if val:
        axes[1].plot([r["step"] for r in val], [r["relmse"] for r in val], "o-", label="denoised")
        axes[1].plot([r["step"] for r in val], [r["input_relmse"] for r in val], "--", label="noisy input")
    axes[1].set(xlabel="step", ylabel="RelMSE", title="validation RelMSE (final color)", yscale="log")
    axes[1].legend()
    fig.tight_layout()
    fig.savefig(out_dir / "curves.png", dpi=90)
    plt.close(fig)


def parse(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="data set directory (manifest.jsonl)")
    p.add_argument("--out", required=True, help="run directory (checkpoints, logs, plots)")
    p.add_argument("--variant", choices=("full", "nocov"), default="full")
    p.add_argument("--arch", choices=("separate", "joint", "kpcn"), default="separate")
    p.add_argument("--width", type=int, default=64)
    p.add_argument("--blocks", type=int, default=8)
    p.add_argument("--predictor-width", type=int, default=128)
    p.add_argument("--predictor-depth", type=int, default=4)
    p.add_argument("--head-kernel", type=int, default=3)
    p.add_argument("--kpcn-layers", type=int, default=9)
    p.add_argument("--kpcn-kernel", type=int, default=5)
    p.add_argument("--steps", type=int, default=50000)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--patch", type=int, default=128)
    p.add_argument("--lr", type=float, default=1e-4)
    p.add_argument("--perceptual", type=float, default=0.0, help="weight of the perceptual loss (0: SMAPE only)")
    p.add_argument("--log-l1", type=float, default=0.0, help="weight of an L1 term in the log domain (see log_l1)")
    p.add_argument("--val-every", type=int, default=500)
    p.add_argument("--val-frames", type=int, default=None, help="at most this many validation frames")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=os.cpu_count())
    p.add_argument("--resume", action="store_true")
    p.add_argument("--export", default=None, help="after training, export best.pt as contract-v1 ONNX into this models directory")
    return p.parse_args(argv)


def build_models(a: argparse.Namespace) -> dict[str, DenoiserNet]:
    cfg = dict(arch=a.arch, in_features=feature_count(a.variant))
    if a.arch == "kpcn":
        cfg.update(width=a.width, layers=a.kpcn_layers, conv_kernel=a.kpcn_kernel)
    else:
        cfg.update(width=a.width, blocks=a.blocks, predictor_width=a.predictor_width,
                   predictor_depth=a.predictor_depth, head_kernel=a.head_kernel)
    torch.manual_seed(a.seed)
    # channels_last: about 2.4x faster convolutions on CPU than NCHW.
    return {c: DenoiserNet(**cfg).to(memory_format=torch.channels_last) for c in COMPONENTS}


def main(argv=None) -> int:
    a = parse(argv)
    torch.set_num_threads(max(1, a.threads))
    torch.set_flush_denormal(True)  # real frames have near-zero values; denormals are slow
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    train = load_frames(a.data, "train", a.variant)
    val = load_frames(a.data, "val", a.variant, a.val_frames)
    if not train:
        raise SystemExit(f"{a.data}: no training frames in the manifest")
    sampler = PatchSampler(train, a.patch)
    models = build_models(a)
    opts = {c: torch.optim.Adam(models[c].parameters(), lr=a.lr) for c in COMPONENTS}
    perceptual = None
    if a.perceptual > 0:
        from .perceptual import PerceptualLoss

        perceptual = PerceptualLoss()

    step, best, elapsed = 0, math.inf, 0.0
    state_path = out / "state.pt"
    if a.resume and state_path.exists():
        st = load_state(state_path)
        for c in COMPONENTS:
            models[c].load_state_dict(st["models"][c])
            opts[c].load_state_dict(st["opts"][c])
        step, best, elapsed = st["step"], st["best"], st.get("elapsed", 0.0)
        print(f"resumed at step {step}", file=sys.stderr)
    (out / "config.json").write_text(json.dumps(vars(a), indent=2))

    info = {c: models[c].description() for c in COMPONENTS}
    print(f"training {a.variant}: {len(train)} train / {len(val)} val frames; {info['diffuse']}", file=sys.stderr)
    log = open_append(out / "log.jsonl")
    t0 = time.time() - elapsed
    while step < a.steps:
        rng = np.random.default_rng([a.seed, step])
        batch = {k: torch.from_numpy(v).contiguous(memory_format=torch.channels_last)
                 for k, v in sampler.sample(a.batch, rng).items()}
        row = {"step": step + 1}
        for c in COMPONENTS:
            loss, parts = component_loss(models[c], batch, c, perceptual, a.perceptual, a.log_l1)
            opts[c].zero_grad(set_to_none=True)
            loss.backward()
            opts[c].step()
            row[f"{c}_loss"] = float(loss.detach())
            row.update({f"{c}_{k}": v for k, v in parts.items()})
        step += 1
        row["time"] = time.time() - t0
        log.write(json.dumps(row) + "\n")
        if step % 10 == 0:
            log.flush()
            print(f"step {step}/{a.steps}  diffuse {row['diffuse_loss']:.4f}  specular {row['specular_loss']:.4f}  "
                  f"{row['time']:.0f}s", file=sys.stderr, flush=True)
        if step % a.val_every == 0 or step == a.steps:
            v = validate(models, val) if val else {"relmse": float(row["diffuse_loss"] + row["specular_loss"]), "input_relmse": float("nan")}
            v.update(step=step, time=time.time() - t0)
            append_jsonl(out / "val.jsonl", v)
            print(f"validation at {step}: RelMSE {v['relmse']:.5f} (input {v['input_relmse']:.5f})", file=sys.stderr, flush=True)
            if v["relmse"] < best:
                best = v["relmse"]
                save_checkpoint(out / "best.pt", models, step=step, val=v, train_config=vars(a))
            save_state(state_path, models={c: models[c].state_dict() for c in COMPONENTS},
                       opts={c: opts[c].state_dict() for c in COMPONENTS},
                       step=step, best=best, elapsed=time.time() - t0)
            log.flush()
            plot_curves(out)
    log.close()
    if a.export:
        from . import export

        export.main(["--checkpoint", str(out / "best.pt"), "--out", a.export])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

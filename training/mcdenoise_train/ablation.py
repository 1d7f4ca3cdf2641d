"""The paper's ablations on our data: each variant trained with the same data, seed, steps
and optimiser as the baseline, exported through the contract-v1 exporter and evaluated by
the Rust engine on held-out scenes.

    python -m mcdenoise_train.ablation --data data --test-data data-test --out runs/ablation \\
        --steps 600 --threads 1

Variants (Lin et al. 2020 figure in brackets):
- ``baseline``: the shipped architecture (separate colour / feature extractors, 4-layer
  kernel predictor), with covariance, SMAPE + log-domain L1;
- ``nocov``: without the covariance features (Fig. 9/10, the paper's "structure only");
- ``joint``: one extractor over colour and features concatenated (Fig. 13);
- ``deep-predictor``: a 10-layer kernel predictor instead of 4 (Fig. 12);
- ``perceptual``: baseline loss + perceptual loss on ImageNet VGG-16 features (Fig. 11);
- ``kpcn``: vanilla KPCN, a plain 9-layer CNN predicting the 21x21 kernel (the baseline
  of the paper; Bako et al. 2017).

Each variant runs in its own directory (``OUT/NAME``, resumable: finished variants are
skipped); the table (``OUT/ablation.md``) lists parameters, FLOPs per pixel, and the mean
RelMSE / DSSIM / PSNR on the validation scenes (never trained on; they also choose the
checkpoint) and on the separate test scenes (never seen at all).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from . import evaluate, export, train
from .checkpoint import load_checkpoint
from .files import read_jsonl

# The shipped architecture (Makefile TRAIN_ARGS), shared by every variant unless overridden.
BASE = ["--width", "24", "--blocks", "4", "--predictor-width", "48", "--predictor-depth", "4",
        "--head-kernel", "1", "--patch", "64", "--batch", "4", "--lr", "1e-4", "--log-l1", "1"]

VARIANTS: dict[str, list[str]] = {
    "baseline": [],
    "nocov": ["--variant", "nocov"],
    "joint": ["--arch", "joint"],
    "deep-predictor": ["--predictor-depth", "10"],
    "perceptual": ["--perceptual", "0.05"],
    "kpcn": ["--arch", "kpcn", "--width", "28", "--kpcn-layers", "9", "--kpcn-kernel", "5"],
}


def variant_of(args: list[str]) -> str:
    return args[args.index("--variant") + 1] if "--variant" in args else "full"


def run_variant(name: str, a: argparse.Namespace) -> dict:
    run = Path(a.out) / name
    done = run / "summary.json"
    if done.exists():
        return json.loads(done.read_text())
    args = BASE + VARIANTS[name] + ["--steps", str(a.steps), "--val-every", str(a.val_every),
                                    "--threads", str(a.threads), "--seed", str(a.seed)]
    print(f"== {name}: train {' '.join(VARIANTS[name]) or '(baseline)'}", file=sys.stderr, flush=True)
    train.main(["--data", a.data, "--out", str(run), "--resume"] + args)
    models = run / "models"
    export.main(["--checkpoint", str(run / "best.pt"), "--out", str(models)])
    variant = variant_of(args)
    nets, meta = load_checkpoint(run / "best.pt")
    summary = {"name": name, "args": VARIANTS[name], "steps": a.steps, "best_step": meta.get("step"),
               "params": nets["diffuse"].param_count(), "flops_per_pixel": nets["diffuse"].flops_per_pixel(),
               "train_seconds": read_jsonl(run / "log.jsonl")[-1]["time"]}
    for split, data in (("val", a.data), ("test", a.test_data)):
        if not data:
            continue
        ev = run / f"eval-{split}"
        evaluate.main(["--data", data, "--split", a.test_split if split == "test" else "val",
                       "--method", f"{name}={models}:{variant}", "--threads", str(a.threads), "--out", str(ev)])
        rows = read_jsonl(ev / "results.jsonl")
        for method in ("input", name):
            sel = [r for r in rows if r["method"] == method]
            key = "input" if method == "input" else "model"
            summary[f"{split}_{key}"] = {m: float(np.mean([r[m] for r in sel])) for m in evaluate.METRICS}
            summary[f"{split}_{key}"]["frames"] = len(sel)
    done.write_text(json.dumps(summary, indent=2))
    return summary


def table(summaries: list[dict]) -> str:
    lines = ["| variant | params / component | FLOP/px / component | best step | "
             "val RelMSE | val DSSIM | val PSNR | test RelMSE | test DSSIM | test PSNR |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    first = summaries[0]
    cells = lambda s, split, k: (f"{s[f'{split}_{k}']['relmse']:.4g} | {s[f'{split}_{k}']['dssim']:.4f} | "
                                 f"{s[f'{split}_{k}']['psnr']:.2f}") if f"{split}_{k}" in s else "– | – | –"
    lines.append(f"| noisy input | | | | {cells(first, 'val', 'input')} | {cells(first, 'test', 'input')} |")
    for s in summaries:
        lines.append(f"| {s['name']} | {s['params']:,} | {s['flops_per_pixel']:,} | {s['best_step']} | "
                     f"{cells(s, 'val', 'model')} | {cells(s, 'test', 'model')} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="training data set (train and val splits)")
    p.add_argument("--test-data", default=None, help="a data set of scenes never used in training or selection")
    p.add_argument("--test-split", default="val", help="split of --test-data to evaluate")
    p.add_argument("--out", required=True)
    p.add_argument("--steps", type=int, default=600)
    p.add_argument("--val-every", type=int, default=200)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--only", action="append", choices=list(VARIANTS), help="run just these variants")
    a = p.parse_args(argv)
    Path(a.out).mkdir(parents=True, exist_ok=True)
    summaries = [run_variant(n, a) for n in (a.only or VARIANTS)]
    md = table(summaries)
    (Path(a.out) / "ablation.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Quality evaluation on held-out frames: the noisy input, our models and Intel Open Image
Denoise, with the engine's own metrics.

    python -m mcdenoise_train.evaluate --data DATA --split val \\
        --method full=models:full --method nocov=models:nocov --oidn --out eval/

Each `--method NAME=MODELS_DIR[:VARIANT]` denoises every frame with `mcdenoise run`
(tiled, as served). `--oidn` runs OIDN (pyoidn, HDR, with albedo and normal, quality
high) on the same frames' color (diffuse + specular). All metrics (RelMSE, DSSIM, PSNR,
SMAPE) come from the engine (`mcdenoise run --reference` / `mcdenoise metrics`), so every
method is measured by the same code. Writes `results.jsonl` (one row per frame and
method) and `results.md` (means per method, per scene and per sample count).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from .data import engine_binary, read_manifest
from .frames import read_exr, write_exr

METRICS = ("relmse", "dssim", "psnr", "smape")


def run_engine(noisy: str, reference: str, models: str, variant: str | None, out: Path, threads: int) -> dict:
    cmd = [engine_binary(), "run", noisy, "-o", str(out), "--reference", reference, "--models", models,
           "--threads", str(threads)]
    if variant:
        cmd += ["--variant", variant]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"mcdenoise run {noisy}: {res.stderr.strip()}")
    return json.loads(res.stdout)


def metrics(image: Path, reference: str) -> dict:
    res = subprocess.run([engine_binary(), "metrics", str(image), "--reference", reference],
                         capture_output=True, text=True, check=True)
    return json.loads(res.stdout)


def run_oidn(noisy: str, out: Path, quality: str = "high") -> float:
    import pyoidn

    ch = read_exr(noisy)
    rgb = lambda base: np.stack([ch[f"{base}.{c}"] for c in "RGB"], -1).astype(np.float32)
    color = rgb("diffuse") + rgb("specular")
    albedo = np.clip(rgb("albedo"), 0, None)
    normal = np.stack([ch.get(f"normal.{a}", ch.get(f"normal.{b}")) for a, b in zip("RGB", "XYZ")], -1).astype(np.float32)
    t = time.perf_counter()
    den = pyoidn.denoise(np.ascontiguousarray(color), np.ascontiguousarray(albedo), np.ascontiguousarray(normal),
                         hdr=True, quality=quality)
    seconds = time.perf_counter() - t
    write_exr(out, {c: den[..., i] for i, c in enumerate("RGB")})
    return seconds


def summarize(rows: list[dict]) -> str:
    methods = list(dict.fromkeys(r["method"] for r in rows))
    lines = ["## Mean over all frames", "",
             "| method | frames | RelMSE | DSSIM | PSNR (dB) | SMAPE |", "|---|---|---|---|---|---|"]
    for m in methods:
        sel = [r for r in rows if r["method"] == m]
        means = [np.mean([r[k] for r in sel]) for k in METRICS]
        lines.append(f"| {m} | {len(sel)} | {means[0]:.4g} | {means[1]:.4g} | {means[2]:.2f} | {means[3]:.4g} |")
    for key, title in (("spp", "sample count"), ("scene", "scene")):
        groups = sorted({r[key] for r in rows}, key=lambda v: (isinstance(v, str), v))
        lines += ["", f"## Per {title}: RelMSE / DSSIM / PSNR (dB) / SMAPE", "",
                  f"| {title} | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
        for g in groups:
            cells = []
            for m in methods:
                sel = [r for r in rows if r["method"] == m and r[key] == g]
                mean = lambda k: np.mean([r[k] for r in sel])
                cells.append(f"{mean('relmse'):.4g} / {mean('dssim'):.3f} / {mean('psnr'):.1f} / {mean('smape'):.3g}"
                             if sel else "–")
            lines.append(f"| {g} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path) -> None:
    """RelMSE, DSSIM and PSNR against the sample count, one line per method (means over
    the frames of each sample count)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = list(dict.fromkeys(r["method"] for r in rows))
    spps = sorted({r["spp"] for r in rows})
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, (k, label, log) in zip(axes, (("relmse", "RelMSE", True), ("dssim", "DSSIM", True), ("psnr", "PSNR (dB)", False))):
        for m in methods:
            ys = [np.mean([r[k] for r in rows if r["method"] == m and r["spp"] == s] or [np.nan]) for s in spps]
            ax.plot(spps, ys, marker="o", label=m)
        ax.set_xscale("log", base=2)
        if log:
            ax.set_yscale("log")
        ax.set_xlabel("samples per pixel")
        ax.set_title(label)
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def tonemap(rgb: np.ndarray) -> np.ndarray:
    """HDR to 8-bit sRGB for viewing: clamp to [0, 1], then the sRGB curve."""
    x = np.clip(rgb, 0.0, 1.0)
    x = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (x * 255 + 0.5).astype(np.uint8)


def rgb_of(path: Path | str) -> np.ndarray:
    ch = read_exr(path)
    return np.stack([ch[c] for c in "RGB"], -1)


def save_crops(images: dict[str, np.ndarray], path: Path, size: int = 96) -> None:
    """Side-by-side crops (same window of every image, labelled), the window centred on the
    reference's largest local contrast so that it shows detail rather than a flat wall."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ref = images["reference"]
    h, w = ref.shape[:2]
    size = min(size, h, w)
    lum = ref.mean(-1)
    grad = np.abs(np.diff(lum, axis=0))[:, :-1] + np.abs(np.diff(lum, axis=1))[:-1, :]
    best, y0, x0 = -1.0, 0, 0
    for y in range(0, h - size + 1, max(1, size // 4)):
        for x in range(0, w - size + 1, max(1, size // 4)):
            v = float(grad[y:y + size - 1, x:x + size - 1].mean())
            if v > best:
                best, y0, x0 = v, y, x
    fig, axes = plt.subplots(1, len(images), figsize=(2.2 * len(images), 2.5))
    for ax, (name, img) in zip(axes, images.items()):
        ax.imshow(tonemap(img[y0:y0 + size, x0:x0 + size]), interpolation="nearest")
        ax.set_title(name, fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True)
    p.add_argument("--split", default="val")
    p.add_argument("--method", action="append", default=[], metavar="NAME=DIR[:VARIANT]")
    p.add_argument("--oidn", action="store_true", help="also evaluate Intel Open Image Denoise")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--limit", type=int, default=None, help="at most this many frames")
    p.add_argument("--crops", type=int, default=0, metavar="N",
                   help="write side-by-side crops (input, each method, reference) of the lowest sample count "
                        "of N scenes as OUT/crops/*.png")
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    records = [r for r in read_manifest(a.data) if r.get("split") == a.split][: a.limit]
    if not records:
        raise SystemExit(f"{a.data}: no frames in split {a.split!r}")
    rows = []
    crop_scenes = list(dict.fromkeys(r.get("scene", "") for r in records))[: a.crops]
    lowest = {sc: min(r["spp"] for r in records if r.get("scene", "") == sc) for sc in crop_scenes}
    with tempfile.TemporaryDirectory() as tmp:
        for r in records:
            base = {"scene": r.get("scene", ""), "spp": r.get("spp", 0), "frame": Path(r["noisy"]).name}
            rows.append({**base, "method": "input", **metrics(Path(r["noisy"]), r["reference"])})
            for spec in a.method:
                name, _, rest = spec.partition("=")
                models, _, variant = rest.partition(":")
                rep = run_engine(r["noisy"], r["reference"], models, variant or None, Path(tmp) / f"{name}.exr", a.threads)
                rows.append({**base, "method": name, **rep["metrics"]["output"],
                             "seconds": rep["timings_ms"]["total"] / 1e3})
            if a.oidn:
                secs = run_oidn(r["noisy"], Path(tmp) / "oidn.exr")
                rows.append({**base, "method": "oidn", **metrics(Path(tmp) / "oidn.exr", r["reference"]), "seconds": secs})
            if lowest.get(base["scene"]) == base["spp"]:
                (out / "crops").mkdir(exist_ok=True)
                ch = read_exr(r["noisy"])
                images = {f"input ({base['spp']} spp)": sum(np.stack([ch[f"{p}.{c}"] for c in "RGB"], -1) for p in ("diffuse", "specular"))}
                for spec in a.method:
                    name = spec.partition("=")[0]
                    images[name] = rgb_of(Path(tmp) / f"{name}.exr")
                if a.oidn:
                    images["OIDN"] = rgb_of(Path(tmp) / "oidn.exr")
                images["reference"] = rgb_of(r["reference"])
                save_crops(images, out / "crops" / f"{base['scene']}.png")
            print(f"{base['frame']}: " + ", ".join(f"{x['method']} {x['relmse']:.4g}" for x in rows if x["frame"] == base["frame"]), flush=True)
    with open(out / "results.jsonl", "w") as f:
        for row in rows:
            f.write(json.dumps(row) + "\n")
    (out / "results.md").write_text(summarize(rows))
    plot(rows, out / "quality.png")
    print(summarize(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

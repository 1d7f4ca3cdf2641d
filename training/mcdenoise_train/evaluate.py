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
        lines += ["", f"## RelMSE / DSSIM per {title}", "",
                  f"| {title} | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
        for g in groups:
            cells = []
            for m in methods:
                sel = [r for r in rows if r["method"] == m and r[key] == g]
                cells.append(f"{np.mean([r['relmse'] for r in sel]):.4g} / {np.mean([r['dssim'] for r in sel]):.4g}" if sel else "–")
            lines.append(f"| {g} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True)
    p.add_argument("--split", default="val")
    p.add_argument("--method", action="append", default=[], metavar="NAME=DIR[:VARIANT]")
    p.add_argument("--oidn", action="store_true", help="also evaluate Intel Open Image Denoise")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--limit", type=int, default=None, help="at most this many frames")
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    records = [r for r in read_manifest(a.data) if r.get("split") == a.split][: a.limit]
    if not records:
        raise SystemExit(f"{a.data}: no frames in split {a.split!r}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in records:
            base = {"scene": r.get("scene", ""), "spp": r.get("spp", 0), "frame": Path(r["noisy"]).name}
            rows.append({**base, "method": "input", **metrics(Path(r["noisy"]), r["reference"])})
            for spec in a.method:
                name, _, rest = spec.partition("=")
                models, _, variant = rest.partition(":")
                rep = run_engine(r["noisy"], r["reference"], models, variant or None, Path(tmp) / "o.exr", a.threads)
                rows.append({**base, "method": name, **rep["metrics"]["output"],
                             "seconds": rep["timings_ms"]["total"] / 1e3})
            if a.oidn:
                secs = run_oidn(r["noisy"], Path(tmp) / "oidn.exr")
                rows.append({**base, "method": "oidn", **metrics(Path(tmp) / "oidn.exr", r["reference"]), "seconds": secs})
            print(f"{base['frame']}: " + ", ".join(f"{x['method']} {x['relmse']:.4g}" for x in rows if x["frame"] == base["frame"]), flush=True)
    with open(out / "results.jsonl", "w") as f:
        for row in rows:
            f.write(json.dumps(row) + "\n")
    (out / "results.md").write_text(summarize(rows))
    print(summarize(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

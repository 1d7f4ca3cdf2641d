"""Quality against time: each variant's and each OIDN quality's mean error on the test
scenes against its seconds per 1280x720 frame on this machine's cores.

    python benches/quality_time.py --frame target/bench/frame-1280x720.exr --models models \\
        --results docs/results/test-both/results.jsonl --out docs/results/quality-time.json

Time: `mcdenoise run` as a whole process (EXR decode, model load, denoise, EXR encode) for
each variant, and `pyoidn.denoise` (HDR, albedo and normal, the call alone, its device
made before the timing) at each quality; the median of --runs runs after one warm-up.
`mcdenoise` runs with --threads threads; OIDN's CPU device takes every core of the
machine (pyoidn has no thread setting), so compare on a machine with --threads cores. Quality: the means of `make eval`'s rows (RelMSE, DSSIM)
over the frames on which every plotted method ran (`lin2020` needs covariance, so with it
the Mitsuba frames only). Writes the JSON and a plot beside it (.png).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "training"))

from mcdenoise_train.data import engine_binary  # noqa: E402
from mcdenoise_train.evaluate import oidn_inputs, oidn_method  # noqa: E402
from mcdenoise_train.exr import read_exr  # noqa: E402

VARIANTS = {"default": "full", "nocov": "nocov", "beauty": "beauty", "lin2020": "lin2020", "lin2020-narrow": "lin2020-narrow"}
QUALITIES = ("high", "balanced", "fast")


def time_engine(frame: str, models: str, variant: str, threads: int, runs: int) -> float:
    times = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(runs + 1):
            t = time.perf_counter()
            subprocess.run([engine_binary(), "run", frame, "-o", str(Path(tmp) / "out.exr"), "--models", models,
                            "--variant", variant, "--threads", str(threads)], check=True, capture_output=True)
            if k:  # the first run warms the page cache
                times.append(time.perf_counter() - t)
    return statistics.median(times)


def time_oidn(frame: str, quality: str, threads: int, runs: int) -> float:
    import pyoidn

    color, albedo, normal = oidn_inputs(read_exr(frame))
    times = []
    for k in range(runs + 1):
        t = time.perf_counter()
        pyoidn.denoise(color, albedo, normal, hdr=True, quality=quality)
        if k:  # the first call makes the device and the filter
            times.append(time.perf_counter() - t)
    return statistics.median(times)


def quality(results: Path, methods: list[str]) -> tuple[dict[str, dict[str, float]], int]:
    rows = [json.loads(line) for line in open(results)]
    by_frame: dict[str, dict[str, dict]] = {}
    for r in rows:
        by_frame.setdefault(r["frame"], {})[r["method"]] = r
    frames = [f for f, m in by_frame.items() if all(x in m for x in methods)]
    if not frames:
        raise SystemExit(f"{results}: no frame has rows of every method ({', '.join(methods)})")
    means = {m: {k: float(np.mean([by_frame[f][m][k] for f in frames])) for k in ("relmse", "dssim")} for m in methods}
    return means, len(frames)


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for ax, key, label in zip(axes, ("relmse", "dssim"), ("RelMSE", "DSSIM")):
        for p in report["points"]:
            ours = not p["method"].startswith("oidn")
            ax.scatter(p["seconds"], p[key], marker="o" if ours else "s", color="C0" if ours else "C3")
            ax.annotate(p["method"], (p["seconds"], p[key]), textcoords="offset points", xytext=(5, 4), fontsize=8)
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel(f"seconds per {report['width']}x{report['height']} frame, {report['threads']} threads")
        ax.set_ylabel(f"mean {label}, {report['frames']} test frames")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frame", default=str(ROOT / "target/bench/frame-1280x720.exr"))
    p.add_argument("--models", default=str(ROOT / "models"))
    p.add_argument("--results", default=str(ROOT / "docs/results/test-both/results.jsonl"))
    p.add_argument("--variants", default="default,beauty,lin2020,lin2020-narrow", help=f"of {', '.join(VARIANTS)}")
    p.add_argument("--qualities", default=",".join(QUALITIES), help="OIDN's")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--out", default=str(ROOT / "docs/results/quality-time.json"))
    p.add_argument("--plot-only", action="store_true", help="redraw the plot of an existing --out")
    a = p.parse_args(argv)
    if a.plot_only:
        plot(json.loads(Path(a.out).read_text()), Path(a.out).with_suffix(".png"))
        return 0
    if not Path(a.frame).exists():
        raise SystemExit(f"{a.frame}: no such frame (`make bench` writes it)")
    variants = [v for v in a.variants.split(",") if v]
    qualities = [q for q in a.qualities.split(",") if q]
    for v in variants:
        if v not in VARIANTS:
            raise SystemExit(f"--variants: unknown {v!r} (known: {', '.join(VARIANTS)})")
    methods = variants + [oidn_method(q) for q in qualities]
    means, frames = quality(Path(a.results), methods)
    ch = read_exr(a.frame)
    h, w = next(iter(ch.values())).shape
    points = []
    for v in variants:
        points.append({"method": v, "seconds": time_engine(a.frame, a.models, VARIANTS[v], a.threads, a.runs),
                       **means[v]})
    for q in qualities:
        points.append({"method": oidn_method(q), "seconds": time_oidn(a.frame, q, a.threads, a.runs),
                       **means[oidn_method(q)]})
    report = {"width": w, "height": h, "threads": a.threads, "runs": a.runs, "frames": frames,
              "results": os.path.relpath(a.results, ROOT), "points": points}
    Path(a.out).write_text(json.dumps(report, indent=2) + "\n")
    plot(report, Path(a.out).with_suffix(".png"))
    for pt in points:
        print(f"{pt['method']:14s} {pt['seconds']:7.2f} s  RelMSE {pt['relmse']:.4g}  DSSIM {pt['dssim']:.4g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

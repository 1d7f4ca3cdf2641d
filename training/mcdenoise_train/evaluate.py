"""Quality evaluation on held-out frames: the noisy input, our models and Intel Open Image
Denoise, with the engine's own metrics.

    python -m mcdenoise_train.evaluate --data DATA --split val \\
        --method full=models:full --method nocov=models:nocov --oidn --out eval/

Each `--method NAME=MODELS_DIR[:VARIANT]` denoises every frame with `mcdenoise run`
(tiled, as served). `--oidn` runs OIDN (pyoidn, HDR, with albedo and normal, quality
high, or the qualities `--oidn-quality` names) on the same frames' color (diffuse + specular). All metrics (RelMSE, DSSIM, PSNR,
SMAPE) come from the engine (`mcdenoise run --reference` / `mcdenoise metrics`), so every
method is measured by the same code. Writes `results.jsonl` (one row per frame and
method) and `results.md` (what frames were judged, then means per method, per scene and per
sample count).

`--outliers N` adds the firefly check (docs/fireflies.md): N isolated outliers of 10-1000x
the local level are injected into each frame (variance raised to match, as a renderer's
would be), and every method runs on the injected copy too: our models with the firefly
handling `auto` and `off`, OIDN as it is. `outliers.jsonl` and a section of `results.md`
give the RelMSE ratio injected / clean per method, scene and sample count.
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

from .data import REPOSITORY, engine_binary, manifest_frames
from .exr import exr_size, read_exr, write_exr
from .files import write_jsonl

METRICS = ("relmse", "dssim", "psnr", "smape")


class NotApplicable(Exception):
    """The frame lacks a channel the chosen model needs (the engine's message)."""


def run_engine(noisy: str, reference: str, models: str, variant: str | None, out: Path, threads: int,
               fireflies: str | None = None) -> dict:
    cmd = [engine_binary(), "run", str(noisy), "-o", str(out), "--reference", reference, "--models", models,
           "--threads", str(threads)]
    if variant:
        cmd += ["--variant", variant]
    if fireflies:
        cmd += ["--fireflies", fireflies]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        err = res.stderr.strip()
        if "model needs a `" in err:  # e.g. `full` or `lin2020` on a frame without covariance
            raise NotApplicable(err.removeprefix("error: "))
        raise RuntimeError(f"mcdenoise run {noisy}: {err}")
    return json.loads(res.stdout)


def metrics(image: Path, reference: str) -> dict:
    res = subprocess.run([engine_binary(), "metrics", str(image), "--reference", reference],
                         capture_output=True, text=True, check=True)
    return json.loads(res.stdout)


def oidn_inputs(ch: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OIDN's color (diffuse + specular), albedo and normal of a frame's channels, [H, W, 3]
    contiguous float32."""
    rgb = lambda base: np.stack([ch[f"{base}.{c}"] for c in "RGB"], -1).astype(np.float32)
    color = rgb("diffuse") + rgb("specular")
    albedo = np.clip(rgb("albedo"), 0, None)
    normal = np.stack([ch.get(f"normal.{a}", ch.get(f"normal.{b}")) for a, b in zip("RGB", "XYZ")], -1).astype(np.float32)
    return np.ascontiguousarray(color), np.ascontiguousarray(albedo), np.ascontiguousarray(normal)


def run_oidn(noisy: str, out: Path, quality: str = "high") -> float:
    import pyoidn

    color, albedo, normal = oidn_inputs(read_exr(noisy))
    t = time.perf_counter()
    den = pyoidn.denoise(color, albedo, normal, hdr=True, quality=quality)
    seconds = time.perf_counter() - t
    write_exr(out, {c: den[..., i] for i, c in enumerate("RGB")})
    return seconds


def oidn_method(quality: str) -> str:
    """The method name of OIDN at `quality` in the results (`oidn` is quality high)."""
    return "oidn" if quality == "high" else f"oidn-{quality}"


LUMINANCE = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)


def luminance(ch: dict[str, np.ndarray]) -> np.ndarray:
    """Luminance of diffuse + specular."""
    return sum(w * (ch[f"diffuse.{c}"] + ch[f"specular.{c}"]) for w, c in zip(LUMINANCE, "RGB"))


def inject_outliers(ch: dict[str, np.ndarray], count: int, seed: int) -> tuple[dict[str, np.ndarray], list]:
    """`count` isolated outliers (at least 6 pixels apart, 2 from the border) of 10-1000x
    (log-uniform) the local level, the mean luminance of diffuse + specular over the pixel's
    5x5 neighbourhood, put into the diffuse or the specular buffer (alternately) as a white
    `delta` that makes the pixel's luminance that multiple; the component's variance gains
    `delta**2`, as a renderer's variance of the pixel mean would with one sample carrying
    the outlier. Pixels darker than a tenth of the frame's median are skipped. The same
    injection as tests/fireflies.rs. Returns the new channels and the (y, x) chosen."""
    out = {k: v.copy() for k, v in ch.items()}
    lum = luminance(ch)
    h, w = lum.shape
    median = float(np.median(lum))
    rng = np.random.default_rng(seed)
    chosen: list[tuple[int, int]] = []
    for _ in range(100_000):
        if len(chosen) == count:
            break
        y, x = int(rng.integers(2, h - 2)), int(rng.integers(2, w - 2))
        if any(max(abs(y - cy), abs(x - cx)) < 6 for cy, cx in chosen):
            continue
        level = float(lum[y - 2:y + 3, x - 2:x + 3].mean())
        if level < 0.1 * median:
            continue
        factor = 10.0 ** (1.0 + 2.0 * rng.random())
        delta = factor * level - float(lum[y, x])
        comp = "diffuse" if len(chosen) % 2 == 0 else "specular"
        for c in "RGB":
            out[f"{comp}.{c}"][y, x] += delta
        for name in out:
            if name.startswith(f"{comp}Variance."):
                out[name][y, x] += delta * delta
        chosen.append((y, x))
    if len(chosen) < count:
        raise ValueError(f"cannot place {count} outliers in a {w}x{h} frame")
    return out, chosen


def summarize_outliers(rows: list[dict]) -> str:
    """RelMSE injected / clean per method (and firefly handling), overall and per scene and
    sample count."""
    keys = list(dict.fromkeys(r["label"] for r in rows))
    lines = ["", f"## Outlier injection ({rows[0]['outliers']} isolated outliers of 10-1000x the local level, "
             "variance raised to match): RelMSE injected / clean", "",
             "| method | frames | mean ratio | worst ratio |", "|---|---|---|---|"]
    for k in keys:
        sel = [r["ratio"] for r in rows if r["label"] == k]
        lines.append(f"| {k} | {len(sel)} | {np.mean(sel):.3g} | {np.max(sel):.3g} |")
    lines += ["", "| scene | spp | " + " | ".join(keys) + " |", "|---" * (len(keys) + 2) + "|"]
    for scene, spp in sorted({(r["scene"], r["spp"]) for r in rows}, key=lambda t: (str(t[0]), t[1])):
        cells = []
        for k in keys:
            sel = [r["ratio"] for r in rows if r["label"] == k and r["scene"] == scene and r["spp"] == spp]
            cells.append(f"{np.mean(sel):.3g}" if sel else "–")
        lines.append(f"| {scene} | {spp} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def outlier_check(r: dict, base: dict, a, tmp: Path, clean: dict[str, float], seed: int,
                  oidn_quality: str = "high") -> list[dict]:
    """The firefly check of one frame: every method on an injected copy (OIDN at
    `oidn_quality`, labelled `oidn`); `clean` holds the RelMSE of the methods on the frame
    itself (keys as the rows' labels)."""
    injected, _ = inject_outliers(read_exr(r["noisy"]), a.outliers, seed)
    path = tmp / "injected.exr"
    write_exr(path, injected)
    rows = []

    def row(label: str, relmse: float) -> None:
        rows.append({**base, "label": label, "outliers": a.outliers, "clean": clean[label], "injected": relmse,
                     "ratio": relmse / clean[label]})

    for spec in a.method:
        name, _, rest = spec.partition("=")
        models, _, variant = rest.partition(":")
        if f"{name} (fireflies auto)" not in clean:
            continue  # the method cannot take this frame
        for mode in ("auto", "off"):
            label = f"{name} (fireflies {mode})"
            if label not in clean:
                rep = run_engine(r["noisy"], r["reference"], models, variant or None, tmp / "c.exr", a.threads, mode)
                clean[label] = rep["metrics"]["output"]["relmse"]
            rep = run_engine(path, r["reference"], models, variant or None, tmp / "i.exr", a.threads, mode)
            row(label, rep["metrics"]["output"]["relmse"])
    if a.oidn:
        run_oidn(path, tmp / "oidn-injected.exr", oidn_quality)
        row("oidn", metrics(tmp / "oidn-injected.exr", r["reference"])["relmse"])
    return rows


def describe(records: list[dict], data: str, split: str) -> str:
    """The line results.md opens with: how many frames of how many scenes, from where, at what
    size, sample counts and renderers (those the manifest names), so that a table is never
    read as another set's."""
    scenes = list(dict.fromkeys(r.get("scene", "") for r in records))
    sizes = sorted({exr_size(r["noisy"]) for r in records})
    spp = sorted({int(r.get("spp", 0)) for r in records})
    renderers = sorted({r["renderer"] for r in records if r.get("renderer")})
    where = Path(data).resolve()
    if where.is_relative_to(REPOSITORY):
        where = where.relative_to(REPOSITORY)

    def count(n: int, what: str) -> str:
        return f"{n} {what}" + ("" if n == 1 else "s")

    return (f"{count(len(records), 'frame')} of {count(len(scenes), 'scene')} from `{where}` (split `{split}`), "
            + ", ".join(f"{w}×{h}" for w, h in sizes)
            + f", {', '.join(map(str, spp))} spp"
            + (f", rendered by {' and '.join(renderers)}" if renderers else "") + ".\n\n")


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
    p.add_argument("--oidn-quality", default="high",
                   help="OIDN's qualities, comma-separated (high, balanced, fast): methods `oidn` (high) and "
                        "`oidn-<quality>`; the crops and the outlier check use the first")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--limit", type=int, default=None, help="at most this many frames")
    p.add_argument("--crops", type=int, default=0, metavar="N",
                   help="write side-by-side crops (input, each method, reference) of the lowest sample count "
                        "of N scenes as OUT/crops/*.png")
    p.add_argument("--outliers", type=int, default=0, metavar="N",
                   help="also inject N isolated outliers into each frame and report RelMSE injected / clean per "
                        "method, with and without the firefly handling (docs/fireflies.md)")
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    records = [r for r in manifest_frames(a.data) if r.get("split") == a.split][: a.limit]
    if not records:
        raise SystemExit(f"{a.data}: no frames in split {a.split!r}")
    qualities = [q.strip() for q in a.oidn_quality.split(",") if q.strip()]
    if not qualities or any(q not in ("high", "balanced", "fast") for q in qualities):
        raise SystemExit(f"--oidn-quality {a.oidn_quality!r}: name one or more of high, balanced, fast")
    rows = []
    outlier_rows = []
    skipped: dict[str, list[str]] = {}  # method -> frames it cannot take
    crop_scenes = list(dict.fromkeys(r.get("scene", "") for r in records))[: a.crops]
    lowest = {sc: min(r["spp"] for r in records if r.get("scene", "") == sc) for sc in crop_scenes}
    # The crops of an earlier run into OUT (other scenes, other models) would be shown beside these.
    for old in (out / "crops").glob("*.png"):
        old.unlink()
    with tempfile.TemporaryDirectory() as tmp:
        for r in records:
            base = {"scene": r.get("scene", ""), "spp": r.get("spp", 0), "frame": Path(r["noisy"]).name}
            rows.append({**base, "method": "input", **metrics(Path(r["noisy"]), r["reference"])})
            ran = set()
            for spec in a.method:
                name, _, rest = spec.partition("=")
                models, _, variant = rest.partition(":")
                try:
                    rep = run_engine(r["noisy"], r["reference"], models, variant or None, Path(tmp) / f"{name}.exr",
                                     a.threads)
                except NotApplicable as e:
                    skipped.setdefault(name, []).append(f"{base['frame']}: {e}")
                    continue
                ran.add(name)
                rows.append({**base, "method": name, **rep["metrics"]["output"],
                             "seconds": rep["timings_ms"]["total"] / 1e3, "device": rep.get("device")})
            if a.oidn:
                for k, quality in enumerate(qualities):
                    name = oidn_method(quality)
                    secs = run_oidn(r["noisy"], Path(tmp) / f"{name}.exr", quality)
                    rows.append({**base, "method": name, **metrics(Path(tmp) / f"{name}.exr", r["reference"]),
                                 "seconds": secs})
            if a.outliers:
                frame_rows = [x for x in rows if x["frame"] == base["frame"]]
                clean = {f"{x['method']} (fireflies auto)": x["relmse"] for x in frame_rows
                         if x["method"] != "input" and not x["method"].startswith("oidn")}
                clean.update({"oidn": x["relmse"] for x in frame_rows if x["method"] == oidn_method(qualities[0])})
                outlier_rows += outlier_check(r, base, a, Path(tmp), clean, seed=len(outlier_rows) + 22,
                                              oidn_quality=qualities[0])
            if lowest.get(base["scene"]) == base["spp"]:
                (out / "crops").mkdir(exist_ok=True)
                ch = read_exr(r["noisy"])
                images = {f"input ({base['spp']} spp)": sum(np.stack([ch[f"{p}.{c}"] for c in "RGB"], -1) for p in ("diffuse", "specular"))}
                for spec in a.method:
                    name = spec.partition("=")[0]
                    if name in ran:
                        images[name] = rgb_of(Path(tmp) / f"{name}.exr")
                if a.oidn:
                    images["OIDN"] = rgb_of(Path(tmp) / f"{oidn_method(qualities[0])}.exr")
                images["reference"] = rgb_of(r["reference"])
                save_crops(images, out / "crops" / f"{base['scene']}.png")
            print(f"{base['frame']}: " + ", ".join(f"{x['method']} {x['relmse']:.4g}" for x in rows if x["frame"] == base["frame"]), flush=True)
    write_jsonl(out / "results.jsonl", rows)
    summary = describe(records, a.data, a.split) + summarize(rows)
    if skipped:
        summary += "\n## Frames a method cannot take (not in its means)\n\n" + "".join(
            f"- {name}: {len(v)} frames, e.g. {v[0]}\n" for name, v in skipped.items())
    if outlier_rows:
        write_jsonl(out / "outliers.jsonl", outlier_rows)
        summary += summarize_outliers(outlier_rows)
    (out / "results.md").write_text(summary)
    plot(rows, out / "quality.png")
    print(summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Render a training/validation data set of N procedural scenes.

    python -m mcdenoise_train.datagen.dataset --out data/ --scenes N --size 256 \\
        --spp 4,8,16,32,64,128 --ref-spp 4096 --val-fraction 0.1

Output (under --out):

    train/<scene>/<scene>-spp0004.exr ... <scene>-spp0128.exr, <scene>-ref.exr
    val/<scene>/...                      (validation scenes, chosen by scene index)
    specs/<scene>.json                   the scene spec (regenerable from the seed)
    manifest.jsonl                       one JSON record per completed scene
    summary.json                         totals and throughput of the last run

Scene i has seed `--seed-base + i`; its kind (cornell/room/open) is drawn from the seed.
Scene i is a validation scene when floor((i + 1) f) > floor(i f), f = --val-fraction, which
puts round(N f) validation scenes evenly through the index range and does not depend on N
(growing a data set keeps the split of the scenes it has).

Resuming: every frame is written atomically (temporary file + rename); a scene whose
frames all exist and are readable with every channel is skipped, so an interrupted run
continues where it stopped. Frames are deterministic functions of (seed, spp, size), so a
scene interrupted half-way is simply rendered again.

`--frames noisy|ref|all` renders a subset, e.g. the noisy frames on the CPU and the
references in a second run with `--variant cuda_ad_rgb` on a GPU.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from .backend import set_variant


def is_validation(i: int, fraction: float) -> bool:
    return math.floor((i + 1) * fraction + 1e-9) > math.floor(i * fraction + 1e-9)


def frame_paths(out: Path, name: str, split: str, spps, with_ref=True):
    d = out / split / name
    paths = {int(s): d / f"{name}-spp{int(s):04d}.exr" for s in spps}
    if with_ref:
        paths["ref"] = d / f"{name}-ref.exr"
    return paths


def _noisy_seed(scene_seed: int) -> int:
    return (scene_seed * 7919 + 1) << 12


def _ref_seed(scene_seed: int) -> int:
    return ((scene_seed * 7919 + 1) << 12) + 2048


def error_ratios(ref_ch: dict, noisy: dict) -> dict:
    """How far the reference's own error is below each noisy frame's, by spp:
    `mean`: mean colour variance of the reference over that of the noisy frame (expected
    spp / ref_spp; dominated by the brightest, firefly-prone pixels), and `rel`: the same
    for the relative variance Var / (L_ref^2 + 0.01), L_ref the reference's luminance (the
    relMSE weighting, robust to fireflies)."""
    lum = 0.2126 * ref_ch["R"] + 0.7152 * ref_ch["G"] + 0.0722 * ref_ch["B"]
    wgt = 1.0 / (lum.astype(np.float64) ** 2 + 0.01)
    rv = float(np.mean(ref_ch["colorVariance.Z"]))
    rr = float(np.mean(ref_ch["colorVariance.Z"] * wgt))
    out = {}
    for s, ch in noisy.items():
        out[str(s)] = {"mean": round(rv / max(float(np.mean(ch["colorVariance.Z"])), 1e-30), 6),
                       "rel": round(rr / max(float(np.mean(ch["colorVariance.Z"] * wgt)), 1e-30), 6)}
    return out


def render_scene(spec, width, height, spps, ref_spp, out_paths, opts, frames="all", max_lanes=None,
                 progress=None, covariance=True, root=None):
    """Render the frames of one scene that are missing; returns the manifest record, whose
    paths are relative to `root` (the data set directory) when given."""
    from . import exr_io, render, scenes

    def rel(p):
        return os.path.relpath(p, root) if root is not None else str(p)

    expect = exr_io.CHANNELS if covariance else exr_io.CHANNELS_NOCOV
    t0 = time.perf_counter()
    scene = scenes.build(spec, width, height)
    t_build = time.perf_counter() - t0
    cam = scenes.camera_params(spec, width)
    kw = {"max_lanes": max_lanes} if max_lanes else {}
    rec = {"scene": spec["name"], "seed": spec["seed"], "kind": spec["kind"], "width": width, "height": height,
           "spp": sorted(int(s) for s in spps), "ref_spp": ref_spp, "build_seconds": round(t_build, 3),
           "frames": {}}
    base = {"scene": spec["name"], "seed": spec["seed"], "kind": spec["kind"], "width": width, "height": height,
            "max_depth": opts.max_depth, "renderer": "mcdenoise datagen (Mitsuba 3 " + _mi_version() + ")"}
    noisy_ch = {}

    if frames in ("all", "noisy"):
        def on_frame(spp, m, seconds):
            ch, meta = render.frame_channels(m, covariance)
            meta.update(base, seconds=round(seconds, 3), seed_first_pass=_noisy_seed(spec["seed"]))
            exr_io.write_frame(out_paths[spp], ch, meta)
            noisy_ch[spp] = {"colorVariance.Z": ch["colorVariance.Z"]}
            rec["frames"][str(spp)] = {"path": rel(out_paths[spp]), "seconds": round(seconds, 3)}

        if all(exr_io.is_complete(out_paths[s], expect) for s in spps):
            for s in spps:
                ch, meta = exr_io.read_frame(out_paths[s])
                noisy_ch[s] = {"colorVariance.Z": ch["colorVariance.Z"]}
                rec["frames"][str(s)] = {"path": rel(out_paths[s]), "seconds": meta.get("seconds")}
            if progress:
                progress(max(spps))
        else:
            render.render_ladder(scene, width, height, spps, _noisy_seed(spec["seed"]), cam["pixel_angle"], opts,
                                 progress=progress, on_frame=on_frame, **kw)
    else:  # reference-only run: describe the noisy frames already on disk
        for s in spps:
            if exr_io.is_complete(out_paths[s], expect):
                ch, meta = exr_io.read_frame(out_paths[s])
                noisy_ch[s] = {"colorVariance.Z": ch["colorVariance.Z"]}
                rec["frames"][str(s)] = {"path": rel(out_paths[s]), "seconds": meta.get("seconds")}
    if frames in ("all", "ref") and ref_spp > 0:
        p = out_paths["ref"]
        if exr_io.is_complete(p, expect):
            ch, meta = exr_io.read_frame(p)
            secs = meta.get("seconds")
            if progress:
                progress(ref_spp)
        else:
            t1 = time.perf_counter()
            m = render.render(scene, width, height, ref_spp, _ref_seed(spec["seed"]), cam["pixel_angle"], opts,
                              progress=progress, **kw)
            secs = time.perf_counter() - t1
            ch, meta = render.frame_channels(m, covariance)
            meta.update(base, seconds=round(secs, 3), seed_first_pass=_ref_seed(spec["seed"]), reference=True)
            exr_io.write_frame(p, ch, meta)
        rec["frames"]["ref"] = {"path": rel(p), "seconds": round(float(secs), 3) if secs is not None else None}
    elif ref_spp > 0 and exr_io.is_complete(out_paths["ref"], expect):  # noisy-only run
        ch, meta = exr_io.read_frame(out_paths["ref"])
        rec["frames"]["ref"] = {"path": rel(out_paths["ref"]), "seconds": meta.get("seconds")}
    if "ref" in rec["frames"]:
        if noisy_ch:
            rec["ref_variance_ratio"] = error_ratios(ch, noisy_ch)
    rec["seconds"] = round(time.perf_counter() - t0, 3)
    return rec


def _mi_version():
    import mitsuba

    return mitsuba.__version__


def read_manifest(path: Path) -> list[dict]:
    out = []
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue  # a line cut short by an interruption
    return out


def append_manifest(path: Path, record: dict) -> None:
    with open(path, "a") as f:
        f.write(json.dumps(record, sort_keys=True) + "\n")
        f.flush()
        os.fsync(f.fileno())


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python -m mcdenoise_train.datagen.dataset", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("data"))
    p.add_argument("--scenes", type=int, default=10, help="number of scenes N")
    p.add_argument("--size", type=int, default=256, help="frame width in pixels")
    p.add_argument("--height", type=int, default=None, help="frame height (default: --size)")
    p.add_argument("--spp", default="4,8,16,32,64,128", help="comma-separated noisy sample counts")
    p.add_argument("--ref-spp", type=int, default=4096, help="samples per pixel of the references")
    p.add_argument("--val-fraction", type=float, default=0.1)
    p.add_argument("--seed-base", type=int, default=0)
    p.add_argument("--kinds", default=None, help="restrict to kinds, e.g. cornell,open")
    p.add_argument("--frames", choices=("all", "noisy", "ref"), default="all")
    p.add_argument("--variant", default=None, help="Mitsuba variant (llvm_ad_rgb; cuda_ad_rgb on a GPU)")
    p.add_argument("--no-covariance", action="store_true", help="skip covariance tracing and its channels")
    p.add_argument("--max-depth", type=int, default=6)
    p.add_argument("--max-lanes", type=int, default=None, help="samples per kernel launch (memory bound)")
    p.add_argument("--no-progress", action="store_true")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    set_variant(args.variant)
    import mitsuba as mi
    from tqdm import tqdm

    from . import exr_io, scenes
    from .integrator import Options

    spps = sorted({int(s) for s in args.spp.split(",") if s.strip()})
    width, height = args.size, args.height or args.size
    kinds = args.kinds.split(",") if args.kinds else None
    covariance = not args.no_covariance
    opts = Options(max_depth=args.max_depth, covariance=covariance)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    (out / "specs").mkdir(exist_ok=True)
    manifest = out / "manifest.jsonl"
    for stale in out.glob("*/*/.*.exr.*.tmp"):  # left by a killed run (one writer per --out)
        stale.unlink(missing_ok=True)
    done = {(r["scene"], r["width"], r["height"], tuple(r["spp"]), r["ref_spp"]) for r in read_manifest(manifest)
            if r.get("complete")}
    expect = exr_io.CHANNELS if covariance else exr_io.CHANNELS_NOCOV

    per_scene = (max(spps) if args.frames != "ref" else 0) + (args.ref_spp if args.frames != "noisy" else 0)
    bar = tqdm(total=args.scenes * per_scene, unit="spp", unit_scale=True, disable=args.no_progress,
               dynamic_ncols=True, desc="dataset")
    t_start = time.perf_counter()
    n_rendered = n_skipped = 0
    secs_noisy = {s: [] for s in spps}
    secs_ref = []
    for i in range(args.scenes):
        seed = args.seed_base + i
        kind = None
        if kinds:
            kind = kinds[int(np.random.default_rng([seed, 7]).integers(len(kinds)))]
        spec = scenes.generate(seed, kind)
        split = "val" if is_validation(i, args.val_fraction) else "train"
        paths = frame_paths(out, spec["name"], split, spps, args.ref_spp > 0)
        key = (spec["name"], width, height, tuple(spps), args.ref_spp)
        wanted = [paths[s] for s in spps] if args.frames != "ref" else []
        if args.frames != "noisy" and args.ref_spp > 0:
            wanted.append(paths["ref"])
        if key in done and all(exr_io.is_complete(p, expect) for p in wanted):
            n_skipped += 1
            bar.update(per_scene)
            continue
        bar.set_postfix_str(f"{spec['name']} ({split})")
        spec_path = out / "specs" / f"{spec['name']}.json"
        spec_path.write_text(json.dumps(spec, indent=1, sort_keys=True))
        rec = render_scene(spec, width, height, spps, args.ref_spp, paths, opts, args.frames, args.max_lanes,
                           progress=bar.update, covariance=covariance, root=out)
        rec.update(split=split, index=i, spec=os.path.relpath(spec_path, out), variant=mi.variant(),
                   frames_rendered=args.frames,
                   complete=all(exr_io.is_complete(p_, expect) for p_ in paths.values()))
        append_manifest(manifest, rec)
        n_rendered += 1
        for s in spps:
            f = rec["frames"].get(str(s))
            if f and f.get("seconds") is not None:
                secs_noisy[s].append(f["seconds"])
        if "ref" in rec["frames"] and rec["frames"]["ref"]["seconds"] is not None:
            secs_ref.append(rec["frames"]["ref"]["seconds"])
    bar.close()
    wall = time.perf_counter() - t_start
    summary = {
        "scenes": args.scenes, "rendered": n_rendered, "skipped": n_skipped, "width": width, "height": height,
        "spp": spps, "ref_spp": args.ref_spp, "variant": mi.variant(), "covariance": covariance,
        "wall_seconds": round(wall, 2), "machine": f"{platform.machine()} {os.cpu_count()} cpus",
        "mean_seconds_per_noisy_ladder_level": {str(s): round(float(np.mean(v)), 3) for s, v in secs_noisy.items() if v},
        "mean_seconds_per_reference": round(float(np.mean(secs_ref)), 3) if secs_ref else None,
    }
    if n_rendered:
        summary["scenes_per_hour"] = round(3600.0 * n_rendered / wall, 2)
        summary["frames_per_hour"] = round(3600.0 * n_rendered * (len(spps) + (args.ref_spp > 0)) / wall, 2)
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1), file=sys.stderr)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:
        print("\ninterrupted: run the same command again to resume", file=sys.stderr)
        sys.exit(130)

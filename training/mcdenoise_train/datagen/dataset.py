"""Render a training/validation data set of N procedural scenes, and a fixed test set.

    python -m mcdenoise_train.datagen.dataset --out data/ --scenes N --size 256 \\
        --spp 1,2,4,8,16,32,64,128 --ref-spp 4096 --val-fraction 0.1 --test-scenes M

Output (under --out):

    train/<scene>/<scene>-spp0004.exr ... <scene>-spp0128.exr, <scene>-ref.exr
    val/<scene>/...                      (validation scenes, chosen by scene index)
    specs/<scene>.json                   the scene spec (regenerable from the seed)
    manifest.jsonl                       one JSON record per completed scene
    summary.json                         totals, throughput and timings of the last run

and, with --test-scenes M, a separate data set directory (--test-out, default
`<out>-test`) with the same layout under `test/`: M scenes whose seeds lie in a range that
training and validation scenes never use (TEST_SEED_BASE and up), so training and
checkpoint selection, which read --out, never see them.

Scene i has seed `--seed-base + i` (test scene i: TEST_SEED_BASE + --test-seed-base + i);
its family is drawn from the seed among --families (default: all). Scene i is a
validation scene when floor((i + 1) f) > floor(i f), f = --val-fraction, which puts
round(N f) validation scenes evenly through the index range and does not depend on N
(growing a data set keeps the split of the scenes it has).

Speed: every noisy sample count of a scene is rendered in one kernel launch (nested
segments of each pixel's samples), the reference in a second launch without covariance
tracing (references only provide the training targets); kernels read per-scene values as
opaque variables, so seeds and sample counts never recompile them. `--workers K` runs K
processes (scene i on worker i mod K), e.g. several processes feeding one GPU: while one
traces and compiles a scene's kernel on the CPU, the others' kernels run.

Resuming: every frame is written atomically (temporary file + rename) and a scene whose
frames all exist with every channel (and that has a manifest record) is skipped, so an
interrupted run continues where it stopped; frames are deterministic functions of
(seed, spp, size). Records are appended to the manifest under an exclusive lock, one line
per write, so workers share it safely (`files.append_manifest`; a line cut short by an
interruption is dropped before the next append). `--max-minutes T` stops starting new scenes after
T minutes (test scenes go first), for runs on a machine lent for a fixed time.
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

from ..files import append_manifest, read_manifest
from .backend import set_variant

#: Test scenes take seeds from here on; training/validation seeds must stay below.
TEST_SEED_BASE = 1_000_000_000
#: A reference is "clean" when its noise floor is at most this fraction of every input's
#: observed error (expected: spp / ref_spp, 1/32 for 128 against 4096 spp).
CLEAN_REF_RATIO = 0.25


def _sizes(rec: dict, root) -> None:
    for f in rec["frames"].values():
        p = Path(root) / f["path"] if root is not None else Path(f["path"])
        if p.is_file():
            f["bytes"] = p.stat().st_size


def mark_clean(rec: dict) -> None:
    """Set `ref_clean` from the frames' noise_floor_ratio (see CLEAN_REF_RATIO)."""
    ratios = [f["noise_floor_ratio"] for k, f in rec["frames"].items() if k != "ref" and "noise_floor_ratio" in f]
    if ratios:
        rec["ref_clean"] = bool(max(ratios) <= CLEAN_REF_RATIO)


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


def _rel_weight(ch: dict) -> np.ndarray:
    lum = 0.2126 * ch["R"] + 0.7152 * ch["G"] + 0.0722 * ch["B"]
    return 1.0 / (lum.astype(np.float64) ** 2 + 0.01)


def error_ratios(ref_ch: dict, noisy: dict) -> dict:
    """How far the reference's own error is below each noisy frame's, by spp:
    `mean`: mean colour variance of the reference over that of the noisy frame (expected
    spp / ref_spp; dominated by the brightest, firefly-prone pixels), and `rel`: the same
    for the relative variance Var / (L_ref^2 + 0.01), L_ref the reference's luminance (the
    relMSE weighting, robust to fireflies)."""
    wgt = _rel_weight(ref_ch)
    rv = float(np.mean(ref_ch["colorVariance.Z"]))
    rr = float(np.mean(ref_ch["colorVariance.Z"] * wgt))
    out = {}
    for s, ch in noisy.items():
        out[str(s)] = {"mean": round(rv / max(float(np.mean(ch["colorVariance.Z"])), 1e-30), 6),
                       "rel": round(rr / max(float(np.mean(ch["colorVariance.Z"] * wgt)), 1e-30), 6)}
    return out


def noise_floor(ref_ch: dict, noisy: dict) -> tuple[float, dict]:
    """The reference's own relative noise floor, mean(Var_ref / (L_ref^2 + 0.01)), and the
    observed relative error of each noisy frame against the reference,
    mean((L - L_ref)^2 / (L_ref^2 + 0.01)) on luminance (relMSE's weighting)."""
    wgt = _rel_weight(ref_ch)
    lum = lambda c: 0.2126 * c["R"] + 0.7152 * c["G"] + 0.0722 * c["B"]  # noqa: E731
    floor = float(np.mean(ref_ch["colorVariance.Z"] * wgt))
    ref_l = lum(ref_ch).astype(np.float64)
    errs = {str(s): float(np.mean((lum(ch).astype(np.float64) - ref_l) ** 2 * wgt)) for s, ch in noisy.items()}
    return floor, errs


def _stats_dict(st) -> dict:
    return st.as_dict() if st is not None else None


def render_scene(spec, width, height, spps, ref_spp, out_paths, opts, frames="all", max_lanes=None,
                 progress=None, covariance=True, root=None, precision="half"):
    """Render the frames of one scene that are missing; returns the manifest record, whose
    paths are relative to `root` (the data set directory) when given."""
    from .. import exr
    from . import render, scenes
    from .integrator import Options

    def rel(p):
        return os.path.relpath(p, root) if root is not None else str(p)

    expect = exr.CHANNELS if covariance else exr.CHANNELS_NOCOV
    expect_ref = exr.CHANNELS_NOCOV
    t0 = time.perf_counter()
    scene = scenes.build(spec, width, height)
    t_build = time.perf_counter() - t0
    cam = scenes.camera_params(spec, width)
    kw = {"max_lanes": max_lanes} if max_lanes else {}
    rec = {"scene": spec["name"], "seed": spec["seed"], "kind": spec["kind"], "family": spec["kind"],
           "renderer": "mitsuba", "width": width, "height": height,
           "spp": sorted(int(s) for s in spps), "ref_spp": ref_spp, "build_seconds": round(t_build, 3),
           "frames": {}, "timings": {"build": round(t_build, 3)}}
    base = {"scene": spec["name"], "seed": spec["seed"], "kind": spec["kind"], "family": spec["kind"],
            "width": width, "height": height, "max_depth": opts.max_depth,
            "renderer": "mcdenoise datagen (Mitsuba 3 " + _mi_version() + ")"}
    noisy_ch = {}
    t_write = 0.0

    def noisy_entry(spp, path, seconds):
        return {"path": rel(path), "seconds": seconds, "renderer": "mitsuba", "family": spec["kind"],
                "seed": spec["seed"], "spp": int(spp)}

    if frames in ("all", "noisy"):
        if all(exr.is_complete(out_paths[s], expect) for s in spps):
            for s in spps:
                ch, meta = exr.read_frame(out_paths[s])
                noisy_ch[s] = {k: ch[k] for k in ("R", "G", "B", "colorVariance.Z")}
                rec["frames"][str(s)] = noisy_entry(s, out_paths[s], meta.get("seconds"))
            if progress:
                progress(max(spps))
        else:
            def on_frame(spp, m, seconds):
                nonlocal t_write
                tw = time.perf_counter()
                ch, meta = render.frame_channels(m, covariance)
                meta.update(base, seconds=round(seconds, 3), seed_first_pass=_noisy_seed(spec["seed"]),
                            launch="ladder")
                exr.write_frame(out_paths[spp], ch, meta, precision=precision)
                noisy_ch[spp] = {k: ch[k] for k in ("R", "G", "B", "colorVariance.Z")}
                rec["frames"][str(spp)] = noisy_entry(spp, out_paths[spp], round(seconds, 3))
                t_write += time.perf_counter() - tw

            _, st = render.render_ladder(scene, width, height, spps, _noisy_seed(spec["seed"]), cam["pixel_angle"],
                                         opts, progress=progress, on_frame=on_frame, **kw)
            rec["timings"]["noisy"] = _stats_dict(st)
    else:  # reference-only run: describe the noisy frames already on disk
        for s in spps:
            if exr.is_complete(out_paths[s], expect):
                ch, meta = exr.read_frame(out_paths[s])
                noisy_ch[s] = {k: ch[k] for k in ("R", "G", "B", "colorVariance.Z")}
                rec["frames"][str(s)] = noisy_entry(s, out_paths[s], meta.get("seconds"))
    ref_ch = None
    if frames in ("all", "ref") and ref_spp > 0:
        p = out_paths["ref"]
        if exr.is_complete(p, expect_ref):
            ref_ch, meta = exr.read_frame(p)
            secs = meta.get("seconds")
            if progress:
                progress(ref_spp)
        else:
            ref_opts = Options(**{**opts.__dict__, "covariance": False})
            m, st = render.render(scene, width, height, ref_spp, _ref_seed(spec["seed"]), cam["pixel_angle"],
                                  ref_opts, progress=progress, with_stats=True, **kw)
            secs = st.seconds
            rec["timings"]["ref"] = _stats_dict(st)
            tw = time.perf_counter()
            ref_ch, meta = render.frame_channels(m, False)
            meta.update(base, seconds=round(secs, 3), seed_first_pass=_ref_seed(spec["seed"]), reference=True)
            exr.write_frame(p, ref_ch, meta, precision=precision)
            t_write += time.perf_counter() - tw
        rec["frames"]["ref"] = {"path": rel(p), "seconds": round(float(secs), 3) if secs is not None else None,
                                "renderer": "mitsuba", "family": spec["kind"], "seed": spec["seed"], "spp": ref_spp}
    elif ref_spp > 0 and exr.is_complete(out_paths["ref"], expect_ref):  # noisy-only run
        ref_ch, meta = exr.read_frame(out_paths["ref"])
        rec["frames"]["ref"] = {"path": rel(out_paths["ref"]), "seconds": meta.get("seconds"),
                                "renderer": "mitsuba", "family": spec["kind"], "seed": spec["seed"], "spp": ref_spp}
    if ref_ch is not None and noisy_ch:
        rec["ref_variance_ratio"] = error_ratios(ref_ch, noisy_ch)
        floor, errs = noise_floor(ref_ch, noisy_ch)
        rec["frames"]["ref"]["noise_floor"] = round(floor, 9)
        for s, e in errs.items():
            rec["frames"][s]["rel_error"] = round(e, 9)
            rec["frames"][s]["noise_floor_ratio"] = round(floor / max(e, 1e-30), 6)
    rec["timings"]["write"] = round(t_write, 3)
    rec["seconds"] = round(time.perf_counter() - t0, 3)
    mark_clean(rec)
    _sizes(rec, root)
    return rec


def render_scene_cycles(spec, width, height, spps, ref_spp, out_paths, max_depth=6, progress=None, root=None,
                        precision="half", streams=None):
    """Render a scene's frames with Blender Cycles (all of them: Cycles frames are made in
    one Blender session); returns the manifest record (see cycles.py)."""
    from .. import exr
    from . import cycles

    def rel(p):
        return os.path.relpath(p, root) if root is not None else str(p)

    t0 = time.perf_counter()
    res, secs = cycles.render_frames(spec, width, height, spps, ref_spp, spec["seed"], max_depth,
                                     streams or cycles.STREAMS)
    if progress:
        progress(max(spps) + ref_spp)
    base = {"scene": spec["name"], "seed": spec["seed"], "kind": spec["kind"], "family": spec["kind"],
            "width": width, "height": height, "max_depth": max_depth, "renderer": "Blender Cycles (bpy)"}
    rec = {"scene": spec["name"], "seed": spec["seed"], "kind": spec["kind"], "family": spec["kind"],
           "renderer": "cycles", "width": width, "height": height, "spp": sorted(int(s) for s in spps),
           "ref_spp": ref_spp, "frames": {}, "timings": {"render": round(secs, 3)}}
    tw = time.perf_counter()
    for key, (ch, meta) in res.items():
        meta.update(base, seconds=round(secs, 3), reference=key == "ref")
        exr.write_frame(out_paths[key], ch, meta, precision=precision)
        rec["frames"][str(key)] = {"path": rel(out_paths[key]), "seconds": round(secs, 3), "renderer": "cycles",
                                   "family": spec["kind"], "seed": spec["seed"],
                                   "spp": ref_spp if key == "ref" else int(key), "renders": meta["renders"]}
    if "ref" in res:
        ref_ch = res["ref"][0]
        noisy = {s: res[s][0] for s in spps}
        rec["ref_variance_ratio"] = error_ratios(ref_ch, noisy)
        floor, errs = noise_floor(ref_ch, noisy)
        rec["frames"]["ref"]["noise_floor"] = round(floor, 9)
        for s_, e in errs.items():
            rec["frames"][s_]["rel_error"] = round(e, 9)
            rec["frames"][s_]["noise_floor_ratio"] = round(floor / max(e, 1e-30), 6)
    rec["timings"]["write"] = round(time.perf_counter() - tw, 3)
    rec["seconds"] = round(time.perf_counter() - t0, 3)
    mark_clean(rec)
    _sizes(rec, root)
    return rec


def _mi_version():
    import mitsuba

    return mitsuba.__version__


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python -m mcdenoise_train.datagen.dataset", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("data"))
    p.add_argument("--scenes", type=int, default=10, help="number of training/validation scenes N")
    p.add_argument("--size", type=int, default=256, help="frame width in pixels")
    p.add_argument("--height", type=int, default=None, help="frame height (default: --size)")
    p.add_argument("--spp", default="4,8,16,32,64,128", help="comma-separated noisy sample counts")
    p.add_argument("--ref-spp", type=int, default=4096, help="samples per pixel of the references")
    p.add_argument("--val-fraction", type=float, default=0.1)
    p.add_argument("--seed-base", type=int, default=0)
    p.add_argument("--families", "--kinds", dest="families", default=None,
                   help="restrict to scene families, comma-separated (default: all)")
    p.add_argument("--test-scenes", type=int, default=0,
                   help="also render M test scenes (disjoint seeds) into --test-out")
    p.add_argument("--test-out", type=Path, default=None, help="test set directory (default: <out>-test)")
    p.add_argument("--test-seed-base", type=int, default=0, help="offset of the test seeds within their range")
    p.add_argument("--renderer", choices=("mitsuba", "cycles", "both"), default="mitsuba",
                   help="Mitsuba (our integrator, with covariance), Blender Cycles (no covariance) or both "
                        "(every scene twice, the Cycles one named <scene>-cycles, in the same split)")
    p.add_argument("--frames", choices=("all", "noisy", "ref"), default="all")
    p.add_argument("--variant", default=None, help="Mitsuba variant (llvm_ad_rgb; cuda_ad_rgb on a GPU)")
    p.add_argument("--workers", type=int, default=1, help="rendering processes (scene i on worker i mod K)")
    p.add_argument("--max-minutes", type=float, default=None, help="start no new scene after this many minutes")
    p.add_argument("--no-covariance", action="store_true", help="skip covariance tracing and its channels")
    p.add_argument("--precision", choices=("half", "float"), default="half",
                   help="image channels in half (variances stay float32) or float32")
    p.add_argument("--max-depth", type=int, default=6)
    p.add_argument("--max-lanes", type=int, default=None, help="lanes per kernel launch (memory bound)")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    if args.workers < 1:
        p.error("--workers must be at least 1")
    if args.seed_base < 0 or args.seed_base + args.scenes > TEST_SEED_BASE:
        p.error(f"training/validation seeds must lie in [0, {TEST_SEED_BASE}) (the test seeds start there)")
    if args.test_seed_base < 0:
        p.error("--test-seed-base must be >= 0")
    if args.families:
        from .scenes import KINDS

        unknown = [f for f in args.families.split(",") if f not in KINDS]
        if unknown:
            p.error(f"unknown scene families {', '.join(unknown)}; families: {', '.join(KINDS)}")
    args.spps = sorted({int(s) for s in args.spp.split(",") if s.strip()})
    if not args.spps or args.spps[0] < 1:
        p.error("--spp needs positive sample counts")
    if args.renderer != "mitsuba" and args.frames != "all":
        p.error("--frames applies to Mitsuba only (Cycles renders all frames of a scene in one session)")
    if args.test_scenes and args.test_out is None:
        args.test_out = args.out.parent / (args.out.name + "-test")
    if args.test_out is not None and args.test_out.resolve() == args.out.resolve():
        p.error("--test-out must differ from --out: the test set is its own data set directory")
    return args


def _jobs(args):
    """All scenes of the run as (data set dir, split, index, seed, renderer): test scenes
    first (a fixed set, done even when --max-minutes cuts the run short), then the rest."""
    renderers = ("mitsuba", "cycles") if args.renderer == "both" else (args.renderer,)
    jobs = []
    for i in range(args.test_scenes):
        for r in renderers:
            jobs.append((args.test_out, "test", i, TEST_SEED_BASE + args.test_seed_base + i, r))
    for i in range(args.scenes):
        split = "val" if is_validation(i, args.val_fraction) else "train"
        for r in renderers:
            jobs.append((args.out, split, i, args.seed_base + i, r))
    return jobs


def _spec_of(seed: int, families):
    from . import scenes

    family = None
    if families:
        family = families[int(np.random.default_rng([seed, 7]).integers(len(families)))]
    return scenes.generate(seed, family)


def _check_dir(out: Path, test: bool) -> None:
    """A data set directory holds either the test split or train/val, never both."""
    recs = read_manifest(out / "manifest.jsonl", missing_ok=True)
    bad = [r["scene"] for r in recs if (r.get("split") == "test") != test]
    if bad:
        raise SystemExit(f"{out}: holds {'training/validation' if test else 'test'} scenes ({bad[0]}, ...); "
                         f"the test set must be a data set directory of its own")


def _work(worker: int, args, progress_q=None) -> dict:
    """Render the scenes of one worker (job j when j mod K == worker); returns its totals."""
    set_variant(args.variant)
    import drjit as dr
    import mitsuba as mi

    from .. import exr
    from .integrator import Options

    if args.workers > 1 and mi.variant().startswith("llvm"):
        dr.set_thread_count(max(1, (os.cpu_count() or 1) // args.workers))
    width, height = args.size, args.height or args.size
    families = args.families.split(",") if args.families else None
    covariance = not args.no_covariance
    opts = Options(max_depth=args.max_depth, covariance=covariance)
    expect = exr.CHANNELS if covariance else exr.CHANNELS_NOCOV
    deadline = args.deadline
    done = {}
    for d in {args.out, args.test_out} - {None}:
        done[d] = {(r["scene"], r["width"], r["height"], tuple(r["spp"]), r["ref_spp"])
                   for r in read_manifest(d / "manifest.jsonl", missing_ok=True) if r.get("complete")}
    per_scene = (max(args.spps) if args.frames != "ref" else 0) + (args.ref_spp if args.frames != "noisy" else 0)
    tot = {"rendered": 0, "skipped": 0, "not_started": 0, "frames": 0, "records": []}
    for j, (out, split, i, seed, renderer) in enumerate(_jobs(args)):
        if j % args.workers != worker:
            continue
        if deadline is not None and time.time() > deadline:
            tot["not_started"] += 1
            continue
        spec = _spec_of(seed, families)
        if renderer == "cycles":
            spec["name"] += "-cycles"
        expect = exr.CHANNELS if covariance and renderer == "mitsuba" else exr.CHANNELS_NOCOV
        paths = frame_paths(out, spec["name"], split, args.spps, args.ref_spp > 0)
        key = (spec["name"], width, height, tuple(args.spps), args.ref_spp)
        wanted = [(paths[s], expect) for s in args.spps] if args.frames != "ref" else []
        if args.frames != "noisy" and args.ref_spp > 0:
            wanted.append((paths["ref"], exr.CHANNELS_NOCOV))
        if key in done[out] and all(exr.is_complete(p, e) for p, e in wanted):
            tot["skipped"] += 1
            if progress_q is not None:
                progress_q.put(("spp", per_scene, None))
            continue
        if progress_q is not None:
            progress_q.put(("scene", 0, f"{spec['name']} ({split})"))
        spec_path = out / "specs" / f"{spec['name']}.json"
        spec_path.write_text(json.dumps(spec, indent=1, sort_keys=True))
        step = (lambda k: progress_q.put(("spp", k, None))) if progress_q is not None else None
        if renderer == "cycles":
            rec = render_scene_cycles(spec, width, height, args.spps, args.ref_spp, paths, args.max_depth,
                                      progress=step, root=out, precision=args.precision)
        else:
            rec = render_scene(spec, width, height, args.spps, args.ref_spp, paths, opts, args.frames,
                               args.max_lanes, progress=step, covariance=covariance, root=out,
                               precision=args.precision)
        complete = all(exr.is_complete(p_, expect if k != "ref" else exr.CHANNELS_NOCOV)
                       for k, p_ in paths.items())
        rec.update(split=split, index=i, spec=os.path.relpath(spec_path, out), variant=mi.variant(),
                   frames_rendered=args.frames, precision=args.precision, worker=worker, complete=complete)
        append_manifest(out / "manifest.jsonl", rec)
        tot["rendered"] += 1
        tot["frames"] += len(rec["frames"])
        tot["records"].append({k: rec.get(k) for k in ("scene", "timings", "frames", "seconds", "ref_clean")})
    return tot


def _worker_main(worker, args, progress_q, result_q):
    try:
        result_q.put((worker, _work(worker, args, progress_q), None))
    except BaseException as e:  # reported by the parent
        import traceback

        result_q.put((worker, None, f"{type(e).__name__}: {e}\n{traceback.format_exc()}"))


def _mean(v):
    v = [x for x in v if x is not None]
    return round(float(np.mean(v)), 3) if v else None


def summarize(args, results: list[dict], wall: float, variant: str) -> dict:
    recs = [r for t in results for r in t["records"]]
    timing = {}
    for launch in ("noisy", "ref"):
        st = [r["timings"].get(launch) for r in recs if r["timings"].get(launch)]
        if st:
            timing[launch] = {k: _mean([s[k] for s in st]) for k in
                              ("seconds", "trace_seconds", "compile_seconds", "execute_seconds")}
            timing[launch]["kernel_cache_hits"] = sum(bool(s["kernel_cache_hit"]) for s in st)
            timing[launch]["launches"] = len(st)
    cyc = [r["timings"]["render"] for r in recs if "render" in r["timings"]]
    if cyc:
        timing["cycles_render"] = _mean(cyc)
    timing["build"] = _mean([r["timings"].get("build") for r in recs])
    timing["write"] = _mean([r["timings"].get("write") for r in recs])
    timing["scene"] = _mean([r["seconds"] for r in recs])
    n_rendered = sum(t["rendered"] for t in results)
    n_frames = sum(t["frames"] for t in results)
    summary = {
        "scenes": args.scenes, "test_scenes": args.test_scenes, "rendered": n_rendered,
        "skipped": sum(t["skipped"] for t in results), "not_started": sum(t["not_started"] for t in results),
        "frames": n_frames, "width": args.size, "height": args.height or args.size, "spp": args.spps,
        "ref_spp": args.ref_spp, "renderer": args.renderer, "variant": variant, "covariance": not args.no_covariance,
        "precision": args.precision, "workers": args.workers, "wall_seconds": round(wall, 2),
        "machine": f"{platform.machine()} {os.cpu_count()} cpus",
        "mean_seconds_per_scene": timing,
        "references_not_clean": sorted(r["scene"] for r in recs if r.get("ref_clean") is False),
    }
    sizes = [f["bytes"] for r in recs for f in r["frames"].values() if "bytes" in f]
    if sizes:
        summary["mean_frame_megabytes"] = round(float(np.mean(sizes)) / 1e6, 3)
        summary["gigabytes_per_2000_frames"] = round(2000 * float(np.mean(sizes)) / 1e9, 2)
    if n_rendered:
        summary["scenes_per_hour"] = round(3600.0 * n_rendered / wall, 2)
        summary["frames_per_hour"] = round(3600.0 * n_frames / wall, 2)
    return summary


def main(argv=None) -> int:
    args = parse_args(argv)
    # the time limit counts from the command's start, for every worker
    args.deadline = time.time() + 60.0 * args.max_minutes if args.max_minutes is not None else None
    from tqdm import tqdm

    for d, test in ((args.out, False), (args.test_out, True)):
        if d is None:
            continue
        d.mkdir(parents=True, exist_ok=True)
        (d / "specs").mkdir(exist_ok=True)
        _check_dir(d, test)
        for stale in d.glob("*/*/.*.exr.*.tmp"):  # left by a killed run (one run per --out)
            stale.unlink(missing_ok=True)
    per_scene = (max(args.spps) if args.frames != "ref" else 0) + (args.ref_spp if args.frames != "noisy" else 0)
    n_jobs = args.scenes + args.test_scenes
    bar = tqdm(total=n_jobs * per_scene, unit="spp", unit_scale=True, disable=args.no_progress,
               dynamic_ncols=True, desc="dataset")
    t_start = time.perf_counter()
    if args.workers == 1:
        class _Q:  # progress straight into the bar
            def put(self, item):
                kind, k, text = item
                bar.update(k) if kind == "spp" else bar.set_postfix_str(text)

        results = [_work(0, args, _Q())]
        variant = set_variant(args.variant).variant()
    else:
        import multiprocessing as mp

        ctx = mp.get_context("spawn")  # Dr.Jit state does not survive fork
        progress_q, result_q = ctx.Queue(), ctx.Queue()
        procs = [ctx.Process(target=_worker_main, args=(k, args, progress_q, result_q), daemon=True)
                 for k in range(args.workers)]
        for pr in procs:
            pr.start()
        results, errors = [], []
        while len(results) + len(errors) < args.workers:
            while not progress_q.empty():
                kind, k, text = progress_q.get()
                bar.update(k) if kind == "spp" else bar.set_postfix_str(text)
            while not result_q.empty():
                w, res, err = result_q.get()
                (results.append(res) if err is None else errors.append(f"worker {w}: {err}"))
            if all(not pr.is_alive() for pr in procs) and result_q.empty():
                if len(results) + len(errors) < args.workers:
                    errors.append("a worker exited without a result")
                break
            time.sleep(0.2)
        for pr in procs:
            pr.join()
        if errors:
            bar.close()
            print("\n".join(errors), file=sys.stderr)
            return 1
        variant = args.variant or os.environ.get("MCDENOISE_MI_VARIANT") or "llvm_ad_rgb"
    bar.close()
    summary = summarize(args, results, time.perf_counter() - t_start, variant)
    for d in {args.out, args.test_out} - {None}:
        (d / "summary.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1), file=sys.stderr)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:
        print("\ninterrupted: run the same command again to resume", file=sys.stderr)
        sys.exit(130)

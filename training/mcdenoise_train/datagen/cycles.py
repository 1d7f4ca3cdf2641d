"""Blender Cycles as a second renderer: frames of the same scene specs, with variances.

`bpy==5.0.1` (Blender as a Python module, Python 3.11 only) pins numpy 1.26 while the
training environment uses numpy 2, so bpy lives in its own environment and runs as a
subprocess (`cycles_worker.py`); this module prepares its job, reads the multi-layer EXRs
it writes and assembles frames in the engine's layout (docs/frame-layout.md):

- colour = Combined; diffuse = (Diffuse Direct + Diffuse Indirect) x Diffuse Color
  (Cycles' exact split); specular = Combined - diffuse (glossy, transmission, emission,
  environment) -- the same recipe as the engine's reader for Cycles files (renderers.rs);
- albedo, normal, depth = Denoising Albedo, Denoising Normal, Denoising Depth (no hit -> 0),
  as the engine maps them for Cycles frames;
- no covariance (Cycles frames train the no-covariance variant);
- variances: Cycles writes none, so every frame is the mean of K independent renders
  (different seeds, each skipping sample 0 -- see cycles_worker.py) of n/K samples, and
  Var[mean] = s_K^2 / K, s_K^2 the sample variance of the K render means (K = min(8, n); a
  1-spp frame is the first of two 1-spp renders, its variance from both).

Set `MCDENOISE_BPY_PYTHON` to the interpreter that has bpy (default
`$MCDENOISE_HOME/bpy-venv/bin/python`, which `scripts/setup-bpy` creates).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np

LUM = (0.2126, 0.7152, 0.0722)
#: Independent renders per frame (the variance estimate has K - 1 degrees of freedom).
STREAMS = 8


def bpy_python() -> str:
    """The Python interpreter with bpy, or a clear error."""
    home = os.environ.get("MCDENOISE_HOME", str(Path.home() / ".cache" / "mcdenoise"))
    path = os.environ.get("MCDENOISE_BPY_PYTHON") or str(Path(home) / "bpy-venv" / "bin" / "python")
    if not Path(path).is_file():
        raise FileNotFoundError(f"no Python with bpy at {path}: run scripts/setup-bpy or set MCDENOISE_BPY_PYTHON")
    return path


def available() -> bool:
    try:
        bpy_python()
        return True
    except FileNotFoundError:
        return False


def _split(n: int, parts: int) -> list[int]:
    return [n // parts + (1 if j < n % parts else 0) for j in range(parts)]


def plan(spps, ref_spp, seed: int, streams: int = STREAMS) -> tuple[list[dict], dict]:
    """The renders of a scene: for each frame (spp or "ref") K renders of about spp/K
    samples with distinct seeds. Returns the render list and frame -> render names."""
    renders, frames = [], {}
    for key, n in [(int(s), int(s)) for s in spps] + ([("ref", int(ref_spp))] if ref_spp else []):
        k = 2 if n == 1 else min(streams, n)
        counts = [1, 1] if n == 1 else _split(n, k)
        names = []
        for j, c in enumerate(counts):
            name = f"f{key}-{j}"
            renders.append({"name": name, "spp": c,
                            "seed": zlib.crc32(f"{seed}/{key}/{j}".encode()) & 0x7FFFFFFF})
            names.append(name)
        frames[key] = names
    return renders, frames


def read_passes(path) -> dict:
    """Channels of a Cycles multi-layer EXR by `<pass>.<channel>` (view layer dropped)."""
    from ..exr import read_parts  # OpenEXR only where frames are read, not to import this module

    out = {}
    for part in read_parts(path):
        for name, pixels in part.items():
            bits = name.rsplit(".", 2)
            key = ".".join(bits[-2:]) if len(bits) >= 2 else name
            out.setdefault(key, pixels)
    return out


def buffers(p: dict) -> dict:
    """Engine buffers (H, W, C) of one render's passes."""
    rgb = lambda name: np.stack([p[f"{name}.{c}"] for c in "RGB"], -1)  # noqa: E731
    color = rgb("Combined")
    diffuse = (rgb("Diffuse Direct") + rgb("Diffuse Indirect")) * rgb("Diffuse Color")
    # everything else, from its own passes (so that diffuse + specular = Combined is a check
    # of the pass setup, not an identity; the engine's reader takes Combined - diffuse)
    specular = ((rgb("Glossy Direct") + rgb("Glossy Indirect")) * rgb("Glossy Color")
                + (rgb("Transmission Direct") + rgb("Transmission Indirect")) * rgb("Transmission Color")
                + rgb("Emission") + rgb("Environment"))
    depth = p["Denoising Depth.Z"] if "Denoising Depth.Z" in p else p["Depth.Z"]
    depth = np.where(depth >= 1e9, 0.0, depth)
    return {"color": color, "diffuse": diffuse, "specular": specular, "albedo": rgb("Denoising Albedo"),
            "normal": np.stack([p[f"Denoising Normal.{c}"] for c in "XYZ"], -1), "depth": depth[..., None]}


def combine(parts: list[dict], counts: list[int], spp: int) -> tuple[dict, dict]:
    """Frame channels (engine layout, no covariance) and metadata of a frame of `spp`
    samples from its K renders (`counts` samples each)."""
    n = np.asarray(counts, np.float64)
    if spp == 1:  # the first of two 1-spp renders, the variance from both
        mean = {k: parts[0][k].astype(np.float64) for k in parts[0]}
        var = {k: (parts[0][k].astype(np.float64) - parts[1][k]) ** 2 / 2.0 for k in parts[0]}
        spp = 1
    else:
        w = n / n.sum()
        mean = {k: sum(wj * p[k].astype(np.float64) for wj, p in zip(w, parts)) for k in parts[0]}
        # per-sample variance from the render means (Var[mean_j] = sigma^2 / n_j), then / N
        K = len(parts)
        s2 = {k: sum(nj * (p[k] - mean[k]) ** 2 for nj, p in zip(n, parts)) / (K - 1) for k in parts[0]}
        var = {k: s2[k] / n.sum() for k in parts[0]}
        spp = int(n.sum())
    ch = {}
    names = {"color": ("R", "G", "B"), "diffuse": ("diffuse.R", "diffuse.G", "diffuse.B"),
             "specular": ("specular.R", "specular.G", "specular.B"), "albedo": ("albedo.R", "albedo.G", "albedo.B"),
             "normal": ("normal.R", "normal.G", "normal.B")}
    for k, cn in names.items():
        for i, c in enumerate(cn):
            ch[c] = mean[k][..., i]
        ch[f"{k}Variance.Z"] = sum(LUM[i] * var[k][..., i] for i in range(3))
    ch["depth.Z"] = mean["depth"][..., 0]
    ch["depthVariance.Z"] = var["depth"][..., 0]
    return {k: np.ascontiguousarray(v, np.float32) for k, v in ch.items()}, {"spp": spp, "renders": len(parts)}


def render_frames(spec, width, height, spps, ref_spp, seed, max_depth=6, streams=STREAMS, workdir=None,
                  log=None) -> tuple[dict, float]:
    """Render a scene's frames with Cycles: {spp or "ref": (channels, meta)} and the seconds."""
    renders, frames = plan(spps, ref_spp, seed, streams)
    with tempfile.TemporaryDirectory(dir=workdir, prefix="mcdenoise-cycles-") as tmp:
        job = {"spec": spec, "width": width, "height": height, "max_depth": max_depth, "out": tmp, "renders": renders}
        jp = Path(tmp) / "job.json"
        jp.write_text(json.dumps(job))
        t0 = time.perf_counter()
        pkg_root = str(Path(__file__).resolve().parents[2])
        env = {**os.environ, "PYTHONPATH": pkg_root + os.pathsep + os.environ.get("PYTHONPATH", "")}
        r = subprocess.run([bpy_python(), "-m", "mcdenoise_train.datagen.cycles_worker", str(jp)], cwd=pkg_root,
                           env=env, capture_output=True, text=True)
        secs = time.perf_counter() - t0
        if r.returncode != 0:
            raise RuntimeError(f"Cycles render of {spec['name']} failed ({r.returncode}):\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
        counts = {x["name"]: x["spp"] for x in renders}
        out = {}
        for key, names in frames.items():
            parts = [buffers(read_passes(Path(tmp) / f"{nm}.exr")) for nm in names]
            out[key] = combine(parts, [counts[nm] for nm in names], ref_spp if key == "ref" else key)
    return out, secs


if __name__ == "__main__":  # a quick look: python -m mcdenoise_train.datagen.cycles FAMILY SEED SIZE SPP
    from . import scenes

    fam, sd, size, spp = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
    res, s = render_frames(scenes.generate(sd, fam), size, size, [spp], 0, sd)
    ch, meta = res[spp]
    print(meta, f"{s:.1f}s", {k: float(v.mean()) for k, v in ch.items()})

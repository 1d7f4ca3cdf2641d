"""Training data: frames preprocessed by the Rust engine, and patch sampling.

A data set directory holds `manifest.jsonl` as written by `datagen.dataset` (one record
per scene, read by `files.read_manifest`; `manifest_frames` lists its frames). Every
frame is turned into network inputs and training targets by `mcdenoise preprocess
--reference` (the engine's implementation, so training and serving see the same tensors), cached as
`<data>/preprocessed/<name>.npz` next to the frames and redone when a source is newer.

Patches are drawn as in KPCN (Bako et al. 2017): most of them by importance, favouring
regions where the noisy color and the features vary (edges, texture, noise), the rest
uniformly, so flat regions are still seen.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .contract import select_nocov
from .files import atomic_path, read_manifest

ARRAYS = ("diffuse_color", "specular_color", "features", "albedo", "noisy",
          "diffuse_target", "specular_target", "reference")


#: The repository this package lies in (training/mcdenoise_train/ below it).
REPOSITORY = Path(__file__).resolve().parents[2]


def engine_binary() -> str:
    """The `mcdenoise` binary: $MCDENOISE_BIN, else target/release/mcdenoise of the repository."""
    path = os.environ.get("MCDENOISE_BIN") or str(REPOSITORY / "target/release/mcdenoise")
    if not Path(path).is_file():
        raise FileNotFoundError(f"mcdenoise binary not found at {path}: run `make build` or set MCDENOISE_BIN")
    return path


def manifest_frames(data_dir: str | os.PathLike) -> list[dict]:
    """One record per noisy frame, with absolute `noisy` and `reference` paths.

    Accepts the data generator's per-scene records (`frames` maps each sample count and
    `ref` to a path; only `complete` scenes) and flat per-frame records (`noisy`,
    `reference`). Relative paths are relative to `data_dir`.
    """
    data_dir = Path(data_dir)
    records = []
    lines = read_manifest(data_dir / "manifest.jsonl")
    # A scene rendered again appends a new record: the last one wins.
    last = {r["scene"]: i for i, r in enumerate(lines) if "frames" in r}
    for i, r in enumerate(lines):
        if "frames" not in r:
            records.append({**r, "noisy": str(data_dir / r["noisy"]), "reference": str(data_dir / r["reference"])})
            continue
        if last[r["scene"]] != i or not r.get("complete", True) or "ref" not in r["frames"]:
            continue
        ref = r["frames"]["ref"]["path"]
        for spp, frame in r["frames"].items():
            if spp != "ref":
                records.append({"scene": r["scene"], "seed": r.get("seed"), "split": r.get("split", "train"),
                                "spp": int(spp), "noisy": str(data_dir / frame["path"]),
                                "reference": str(data_dir / ref),
                                **({"renderer": frame["renderer"]} if "renderer" in frame else {})})
    return records


def preprocessed(record: dict, data_dir: str | os.PathLike) -> Path:
    """Preprocess one record's frame with the engine (cached); the .npz path."""
    out_dir = Path(data_dir) / "preprocessed"
    out_dir.mkdir(exist_ok=True)
    out = out_dir / (Path(record["noisy"]).stem + ".npz")
    newest = max(os.path.getmtime(record["noisy"]), os.path.getmtime(record["reference"]))
    if not out.exists() or out.stat().st_mtime < newest:
        subprocess.run(
            [engine_binary(), "preprocess", record["noisy"], "--reference", record["reference"],
             "--variant", "full", "-o", str(out)],
            check=True, capture_output=True, text=True,
        )
    return out


@dataclass
class Frame:
    """The arrays of one preprocessed frame, float32 `[C, H, W]`."""

    name: str
    scene: str
    spp: int
    arrays: dict[str, np.ndarray]

    @property
    def shape(self) -> tuple[int, int]:
        return self.arrays["noisy"].shape[1:]


def load_frames(data_dir: str | os.PathLike, split: str, variant: str, limit: int | None = None) -> list[Frame]:
    """The frames of one split, preprocessed, with the variant's features."""
    frames = []
    for r in [r for r in manifest_frames(data_dir) if r.get("split", "train") == split][:limit]:
        with np.load(preprocessed(r, data_dir)) as z:
            arrays = {k: z[k].astype(np.float32) for k in ARRAYS}
        if variant == "nocov":
            arrays["features"] = np.ascontiguousarray(select_nocov(arrays["features"]))
        frames.append(Frame(Path(r["noisy"]).stem, str(r.get("scene", "")), int(r.get("spp", 0)), arrays))
    return frames


def importance_map(frame: Frame) -> np.ndarray:
    """Per-pixel importance: gradient magnitude of the log noisy color and of the
    normals and albedo, plus the relative color variance."""
    a = frame.arrays
    log_color = np.log1p(np.maximum(a["noisy"], 0)).mean(0)
    grad = lambda x: np.abs(np.diff(x, axis=-1, append=x[..., -1:])) + np.abs(np.diff(x, axis=-2, append=x[..., -1:, :]))
    imp = grad(log_color)
    imp = imp + grad(a["features"][0:6]).mean(0)  # normal and albedo
    imp = imp + a["diffuse_color"][3] / (1.0 + a["diffuse_color"][0:3].mean(0) ** 2)
    return imp.astype(np.float64)


class PatchSampler:
    """Draws `[N, ...]` batches of square patches from frames.

    A fraction `uniform` of the patches is placed uniformly; the rest with probability
    proportional to the mean importance inside the patch (on a grid of stride patch/4).
    """

    def __init__(self, frames: list[Frame], patch: int, uniform: float = 0.3):
        self.frames, self.patch, self.uniform = frames, patch, uniform
        self.candidates = []
        for i, f in enumerate(frames):
            h, w = f.shape
            if h < patch or w < patch:
                raise ValueError(f"frame {f.name} ({w}x{h}) is smaller than the patch size {patch}")
            imp = importance_map(f)
            integral = np.pad(imp.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
            stride = max(1, patch // 4)
            for y in range(0, h - patch + 1, stride):
                for x in range(0, w - patch + 1, stride):
                    s = integral[y + patch, x + patch] - integral[y, x + patch] - integral[y + patch, x] + integral[y, x]
                    self.candidates.append((i, y, x, s))
        weights = np.array([c[3] for c in self.candidates]) + 1e-12
        self.p = weights / weights.sum()

    def sample(self, n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
        picks = []
        for _ in range(n):
            if rng.random() < self.uniform:
                i = int(rng.integers(len(self.frames)))
                h, w = self.frames[i].shape
                picks.append((i, int(rng.integers(h - self.patch + 1)), int(rng.integers(w - self.patch + 1))))
            else:
                i, y, x, _ = self.candidates[int(rng.choice(len(self.candidates), p=self.p))]
                picks.append((i, y, x))
        p = self.patch
        return {
            k: np.stack([self.frames[i].arrays[k][:, y:y + p, x:x + p] for i, y, x in picks])
            for k in ARRAYS
        }


def split_scenes(dirs: list[str | os.PathLike], chosen: set[str], chosen_dir: str | os.PathLike,
                 rest_dir: str | os.PathLike) -> tuple[int, int]:
    """The complete scenes of the data sets `dirs` as two data sets of flat per-frame records
    (absolute paths, no copies): the scenes named in `chosen` with split `val` into
    `chosen_dir` (validation only: what a fine-tune selects on), every other with split
    `test` into `rest_dir` (judging only). Returns the frame counts; a name in `chosen` that
    no data set has complete is an error naming it."""
    frames = [r for d in dirs for r in manifest_frames(d)]
    missing = chosen - {r["scene"] for r in frames}
    if missing:
        raise ValueError(f"no complete scene {', '.join(sorted(missing))} in {', '.join(map(str, dirs))}")
    counts = []
    for out, split, keep in ((chosen_dir, "val", True), (rest_dir, "test", False)):
        rows = [{**{k: r[k] for k in ("scene", "seed", "spp", "noisy", "reference", "renderer") if k in r},
                 "split": split}
                for r in frames if (r["scene"] in chosen) == keep]
        Path(out).mkdir(parents=True, exist_ok=True)
        with atomic_path(Path(out) / "manifest.jsonl") as tmp:
            Path(tmp).write_text("".join(json.dumps(row) + "\n" for row in rows))
        counts.append(len(rows))
    return counts[0], counts[1]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="Data set tools: `split-scenes` (scripts/cpu-pipeline split).")
    sub = p.add_subparsers(dest="command", required=True)
    sp = sub.add_parser("split-scenes", help="named scenes into a validation set, the rest into a judging set")
    sp.add_argument("--data", action="append", required=True, help="data set directory (repeatable)")
    sp.add_argument("--scenes", required=True, help="comma-separated scene names: the validation set")
    sp.add_argument("--chosen", required=True, help="directory of the validation set (split `val`)")
    sp.add_argument("--rest", required=True, help="directory of the other scenes (split `test`)")
    a = p.parse_args(argv)
    try:
        n_val, n_rest = split_scenes(a.data, {s for s in a.scenes.split(",") if s}, a.chosen, a.rest)
    except ValueError as e:
        raise SystemExit(str(e))
    print(f"{n_val} validation frames in {a.chosen}, {n_rest} judging frames in {a.rest}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

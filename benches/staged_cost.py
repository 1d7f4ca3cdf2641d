"""What running the default network in three stages saves ONNX Runtime: the shipped
contract-v2 graph cut at its level-1 boundary and timed against the whole graph over the
regions the engine cuts a frame into (the measurement behind the engine's stages,
`src/engine/stages.rs`; the engine runs the stage files `mcdenoise_train.stages` writes).

    python benches/staged_cost.py --models models --sizes 1280x720,1920x1080 --rounds 5

Without stages every region is the whole network over a core and a halo of the receptive radius
(128 px for the shipped `full`), so a 1280×720 frame runs the network over 1.11 M pixels
for its 0.92 M. Most of that radius comes from the coarse levels, whose pixels are cheap;
the full-resolution convolutions (the paper's two extractors, decoder level 0, the level-0
heads) reach only a few pixels. Cut there, the network is three graphs:

- `front`: the frame's inputs → the level-0 features (the extractors' concatenation) and
  their 2×2 max-pool, run per core with a small margin;
- `middle`: the pooled features of the whole frame → decoder level 1's output and the
  heads of levels 1 … L−1, run once at half resolution;
- `back`: decoder level 1's output and the level-0 features → the level-0 heads, per core
  with the same margin.

The cut graphs are checked against the whole one on a small frame (outputs equal), then
timed on random inputs with the engine's session settings (--threads intra-op threads,
memory patterns off, no spinning): the regions as `Tiling::cores` and `expand` cut the
frame without stages (a balanced grid of cores of at most 768 px a side, the halo, sides multiples
of 16), against `front` and `back` over each core and a margin of --margin px and `middle`
over the whole frame. ONNX Runtime alone: no preprocessing, reconstruction or tiling of
the engine; medians of the rounds, the two layouts in turns. Take it with background work
paused.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import onnx
import onnx.utils
import onnxruntime as ort

ROOT = Path(__file__).resolve().parents[1]
# The engine's default region bound (`DEFAULT_REGION_PIXELS`): frames whose regions exceed it
# (above 1920×1080) are cut further than `cores` cuts them.
REGION_PIXELS = 896 * 768
# The cut, by the tensors' names in the exported graph (`export_ms`).
SKIP = "/Relu_output_0"
POOLED = "/MaxPool_output_0"
DECODER1 = "/decoder.1/decoder.1.3/Relu_output_0"


def session(path: str, threads: int) -> ort.InferenceSession:
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.enable_mem_pattern = False
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])


def cut(model: str, out: Path) -> dict[str, str]:
    """The three stage graphs of `model` in `out`; their paths by stage."""
    m = onnx.load(model)
    inputs = [i.name for i in m.graph.input]
    outputs = [o.name for o in m.graph.output]
    level0 = [o for o in outputs if o.endswith("_0")]
    paths = {s: str(out / f"{s}.onnx") for s in ("front", "middle", "back")}
    onnx.utils.extract_model(model, paths["front"], inputs, [SKIP, POOLED])
    onnx.utils.extract_model(model, paths["middle"], [POOLED], [DECODER1] + [o for o in outputs if o not in level0])
    onnx.utils.extract_model(model, paths["back"], [DECODER1, SKIP], level0)
    return paths


def inputs_of(sess: ort.InferenceSession, h: int, w: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {i.name: rng.random((1, i.shape[1], h, w), np.float32) for i in sess.get_inputs()}


def check(whole: ort.InferenceSession, stages: dict[str, ort.InferenceSession], rng) -> float:
    """Largest difference between the whole graph's outputs and the stages' on a 128×192 frame."""
    feeds = inputs_of(whole, 128, 192, rng)
    ref = dict(zip([o.name for o in whole.get_outputs()], whole.run(None, feeds)))
    skip, pooled = stages["front"].run(None, feeds)
    middle = stages["middle"]
    got = dict(zip([o.name for o in middle.get_outputs()], middle.run(None, {POOLED: pooled})))
    back = stages["back"]
    got.update(zip([o.name for o in back.get_outputs()], back.run(None, {DECODER1: got[DECODER1], SKIP: skip})))
    return max(float(np.abs(ref[k] - got[k]).max()) for k in ref)


def cores(w: int, h: int, tile: int, halo: int, m: int) -> list[tuple[int, int, int, int]]:
    """`Tiling::cores` for frames whose regions stay under the default region bound."""
    up = lambda n: -(-n // m) * m  # noqa: E731
    side = lambda n, k: min(up(-(-n // k)), up(n))  # noqa: E731
    nx, ny = -(-w // tile), -(-h // tile)
    cw, ch = side(w, nx), side(h, ny)
    return [(x, y, min(cw, w - x), min(ch, h - y)) for y in range(0, h, ch) for x in range(0, w, cw)]


def grow(core, by: int, w: int, h: int, m: int) -> tuple[int, int]:
    """The side lengths of `core` grown by `by` inside the frame, padded to multiples of `m`."""
    x, y, cw, ch = core
    x0, y0 = max(x - by, 0), max(y - by, 0)
    x1, y1 = min(x + cw + by, w), min(y + ch + by, h)
    return -(-(x1 - x0) // m) * m, -(-(y1 - y0) // m) * m


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", default=str(ROOT / "models"))
    p.add_argument("--variant", default="full")
    p.add_argument("--sizes", default="1280x720")
    p.add_argument("--tile", type=int, default=768, help="the engine's --tile-v2")
    p.add_argument("--margin", type=int, default=16, help="px around a core for `front` and `back`")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args(argv)
    model = str(Path(a.models) / a.variant / "model.onnx")
    meta = {x.key: x.value for x in onnx.load(model, load_external_data=False).metadata_props}
    levels = int(meta["mcdenoise.levels"])
    m = 1 << (levels - 1)
    halo = -(-int(meta["mcdenoise.receptive_radius"]) // m) * m
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        paths = cut(model, Path(tmp))
        whole = session(model, a.threads)
        stages = {s: session(path, a.threads) for s, path in paths.items()}
        diff = check(whole, stages, rng)
        for size in a.sizes.split(","):
            w, h = (int(v) for v in size.split("x"))
            now = [grow(c, halo, w, h, m) for c in cores(w, h, a.tile, halo, m)]
            if max(rw * rh for rw, rh in now) > REGION_PIXELS:
                raise SystemExit(f"{size}: the engine cuts this frame further for its region bound "
                                 f"({REGION_PIXELS} pixels), which this bench does not follow; up to 1920x1080")
            staged = [grow(c, a.margin, w, h, m) for c in cores(w, h, a.tile, halo, m)]
            now_feeds = {r: inputs_of(whole, r[1], r[0], rng) for r in set(now)}
            front_feeds = {r: inputs_of(whole, r[1], r[0], rng) for r in set(staged)}
            back_feeds = {
                r: {DECODER1: rng.random((1, 32, r[1] // 2, r[0] // 2), np.float32),
                    SKIP: rng.random((1, 32, r[1], r[0]), np.float32)}
                for r in set(staged)
            }
            pw, ph = -(-w // m) * m // 2, -(-h // m) * m // 2
            middle_feed = {POOLED: rng.random((1, 32, ph, pw), np.float32)}

            def run_now() -> float:
                t = time.perf_counter()
                for r in now:
                    whole.run(None, now_feeds[r])
                return time.perf_counter() - t

            def run_staged() -> tuple[float, float, float]:
                t = time.perf_counter()
                for r in staged:
                    stages["front"].run(None, front_feeds[r])
                t_front = time.perf_counter() - t
                t = time.perf_counter()
                stages["middle"].run(None, middle_feed)
                t_middle = time.perf_counter() - t
                t = time.perf_counter()
                for r in staged:
                    stages["back"].run(None, back_feeds[r])
                return t_front, t_middle, time.perf_counter() - t

            run_now(), run_staged()
            rounds = []
            for k in range(a.rounds):
                if k % 2 == 0:
                    n, s = run_now(), run_staged()
                else:
                    s, n = run_staged(), run_now()
                rounds.append({"now_s": n, "front_s": s[0], "middle_s": s[1], "back_s": s[2], "ratio": sum(s) / n})
            med = lambda key: statistics.median(r[key] for r in rounds)  # noqa: E731
            print(json.dumps({
                "size": size, "variant": a.variant, "threads": a.threads, "max_abs_diff": diff,
                "now_regions": [f"{rw}x{rh}" for rw, rh in now],
                "now_pixels": sum(rw * rh for rw, rh in now),
                "staged_regions": [f"{rw}x{rh}" for rw, rh in staged], "middle": f"{pw}x{ph}",
                "now_s": med("now_s"), "front_s": med("front_s"), "middle_s": med("middle_s"),
                "back_s": med("back_s"), "ratio_median": med("ratio"),
                "ratio_range": [min(r["ratio"] for r in rounds), max(r["ratio"] for r in rounds)],
            }))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

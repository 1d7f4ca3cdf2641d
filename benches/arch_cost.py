"""What a shape of the production network (`msnet`) would cost the engine on this CPU,
before any training: the shape exported untrained as the engine runs it (inputs already
compressed, `export_ms --compression engine`) and timed in ONNX Runtime on one region.

    python benches/arch_cost.py                                # the shipped shape and the candidates below
    python benches/arch_cost.py --shape '{"dec": [16, 32, 48, 64]}' --size 1280x720

One JSON line per shape: its FLOP per pixel (`flops_per_pixel`), receptive radius,
parameters and the median of --runs timed runs after a warm-up, with --threads intra-op
threads and the engine's session settings (memory patterns off). The weights do not change
the time; the time is the network alone, without the engine's preprocessing,
reconstruction or tiling. Take it with background work paused.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "training"))

from mcdenoise_train.export_ms import export_onnx  # noqa: E402
from mcdenoise_train.msnet import DEFAULT, MSNet  # noqa: E402

# The shipped shape first, then cheaper ones at full resolution, where most of the time goes
# (docs/results/speed-work.md). ONNX Runtime's CPU convolutions work on blocks of 16
# channels (AVX-512), so widths stay multiples of 16.
CANDIDATES = {
    "shipped": {},
    "dec0-16": {"dec": [16, 32, 48, 64]},
    "ext-blocks-0": {"ext_blocks": 0},
    "dec0-16-ext-blocks-0": {"dec": [16, 32, 48, 64], "ext_blocks": 0},
    # Decoder level 0 as 1x1 convs of level 1 and of the skip, then one 3x3 (msnet.Lean0).
    "lean0-16-ext-blocks-0": {"dec": [16, 32, 48, 64], "ext_blocks": 0, "lean0": True},
}


def measure(name: str, shape: dict, h: int, w: int, threads: int, runs: int, tmp: Path) -> dict:
    import numpy as np
    import onnxruntime as ort

    cfg = {**DEFAULT, **shape}
    net = MSNet(in_features=28, **cfg).eval()
    path = tmp / f"{name}.onnx"
    export_onnx(net, path, "full", verify=False)
    so = ort.SessionOptions()
    so.intra_op_num_threads, so.inter_op_num_threads, so.enable_mem_pattern = threads, 1, False
    session = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    m = net.size_multiple
    hp, wp = -(-h // m) * m, -(-w // m) * m
    rng = np.random.default_rng(0)
    feeds = {i.name: rng.random((1, i.shape[1], hp, wp), dtype=np.float32) for i in session.get_inputs()}
    session.run(None, feeds)
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        session.run(None, feeds)
        times.append(time.perf_counter() - t)
    keys = ("ext_width", "ext_blocks", "enc", "dec", "kernel_size", "levels", "lean0")
    return {"name": name, "shape": {k: cfg[k] for k in keys if k in cfg},
            "mflop_per_px": round(net.flops_per_pixel() / 1e6, 4), "receptive_radius": net.receptive_radius(),
            "params": net.param_count(), "size": f"{wp}x{hp}", "threads": threads,
            "seconds": round(sorted(times)[len(times) // 2], 4)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--shape", action="append", default=[],
                   help="a shape as JSON (msnet arguments: ext_width, ext_blocks, enc, dec, kernel_size, levels, lean0); "
                        "repeatable; default: the shipped shape and the built-in candidates")
    p.add_argument("--size", default="1280x720", help="region WxH (padded to the network's size multiple)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--runs", type=int, default=3)
    a = p.parse_args(argv)
    w, h = (int(v) for v in a.size.lower().split("x"))
    shapes = {f"shape{i}": json.loads(s) for i, s in enumerate(a.shape)} if a.shape else CANDIDATES
    with tempfile.TemporaryDirectory() as tmp:
        for name, shape in shapes.items():
            print(json.dumps(measure(name, shape, h, w, a.threads, a.runs, Path(tmp))), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Training steps per second of `train_ms` on synthetic frames, on a given device.

    python benches/train_step.py --device cuda --batch 32 --patch 112 --steps 400

Writes a data set of synthetic frames (every channel of the frame layout; the step's cost
does not depend on the content), trains the production shape for --steps steps without
validation, and reports the rate over the steps after the first 20 (warm-up: cuDNN's
algorithm search, allocations), read from the run's own log. One JSON line per setting.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "training"))

from mcdenoise_train import train_ms  # noqa: E402
from mcdenoise_train.exr import write_exr  # noqa: E402
from mcdenoise_train.frames import synthetic_frame  # noqa: E402


def make_frames(root: Path, n: int, size: int) -> None:
    root.mkdir(parents=True, exist_ok=True)
    with open(root / "manifest.jsonl", "w") as m:
        for i in range(n):
            ch = synthetic_frame(size, size, seed=i)
            write_exr(root / f"s{i}-spp8.exr", ch)
            write_exr(root / f"s{i}-ref.exr", ch)
            split = "val" if i == n - 1 else "train"
            m.write(json.dumps({"scene": f"s{i}", "spp": 8, "split": split,
                                "noisy": f"s{i}-spp8.exr", "reference": f"s{i}-ref.exr"}) + "\n")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda")
    p.add_argument("--batch", type=int, action="append", default=None, help="repeatable (default 32)")
    p.add_argument("--patch", type=int, default=112)
    p.add_argument("--steps", type=int, default=400)
    p.add_argument("--frames", type=int, default=9)
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--threads", type=int, default=4)
    p.add_argument("--ssim", type=float, default=0.2)
    p.add_argument("--shape", default="", help="extra train_ms shape options, e.g. '--ext-width 4 --enc 4,4,4,4'")
    a = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "data"
        make_frames(data, a.frames, a.size)
        for batch in a.batch or [32]:
            out = Path(tmp) / f"run-{batch}"
            t = time.time()
            train_ms.main(["--data", str(data), "--out", str(out), "--device", a.device, "--steps", str(a.steps),
                           "--batch", str(batch), "--patch", str(a.patch), "--threads", str(a.threads),
                           "--ssim", str(a.ssim), "--val-every", str(10 * a.steps), *a.shape.split()])
            rows = [json.loads(line) for line in open(out / "log.jsonl")]
            first = next(r for r in rows if r["step"] >= 20)
            last = rows[-1]
            rate = (last["step"] - first["step"]) / (last["time"] - first["time"])
            print(json.dumps({"device": a.device, "batch": batch, "patch": a.patch, "steps_per_s": round(rate, 2),
                              "patches_per_s": round(rate * batch, 1), "steps": last["step"],
                              "wall_s": round(time.time() - t, 1)}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

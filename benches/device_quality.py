"""The same frames denoised on two devices, `cpu` (ONNX Runtime's CPU provider, float32) and
`openvino` (OpenVINO: bfloat16 on a CPU with AMX or AVX512-BF16), and their metrics side by side:
what computing the networks in bfloat16 costs in quality.

    python benches/device_quality.py --data runs/res-384a --data data-test --models models \\
        --out docs/results/device-quality.json

Every complete scene's noisy frames of each `--data` set (a data generator's manifest) run
through `mcdenoise run --reference` once per device, with the same options; the engine's own
metrics (RelMSE, DSSIM, PSNR, SMAPE) are compared per frame and in the mean. Prints one line
per frame and the means; `--out` writes every row and the means as JSON.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "training"))

from mcdenoise_train.data import engine_binary, manifest_frames  # noqa: E402

METRICS = ("relmse", "dssim", "psnr", "smape")


def denoise(frame: dict, device: str, models: str, threads: int, out: Path) -> dict:
    cmd = [engine_binary(), "run", frame["noisy"], "-o", str(out), "--reference", frame["reference"],
           "--models", models, "--threads", str(threads), "--device", device]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)}: {res.stderr.strip()}")
    report = json.loads(res.stdout)
    if report["device"] != device:
        raise SystemExit(f"asked for {device}, ran on {report['device']}")
    return report["metrics"]["output"]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", action="append", required=True, help="a data set with a manifest.jsonl (repeatable)")
    p.add_argument("--models", default=str(ROOT / "models"))
    p.add_argument("--devices", default="cpu,openvino", help="two devices: the reference one first")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out")
    a = p.parse_args(argv)
    devices = a.devices.split(",")
    if len(devices) != 2:
        raise SystemExit("--devices: two devices, the reference one first")
    frames = [f for d in a.data for f in manifest_frames(d)]
    if not frames:
        raise SystemExit(f"no complete scene in {', '.join(a.data)}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for f in frames:
            got = {d: denoise(f, d, a.models, a.threads, Path(tmp) / "out.exr") for d in devices}
            rows.append({"scene": f["scene"], "spp": f["spp"], **got})
            base, other = (got[d] for d in devices)
            print(f"{f['scene']} {f['spp']:>3} spp: " + ", ".join(
                f"{m} {base[m]:.5g} -> {other[m]:.5g}" for m in ("relmse", "dssim")), flush=True)
    means = {d: {m: statistics.fmean(r[d][m] for r in rows) for m in METRICS} for d in devices}
    ratios = {m: means[devices[1]][m] / means[devices[0]][m] for m in ("relmse", "dssim", "smape")}
    worst = {m: max(r[devices[1]][m] / r[devices[0]][m] for r in rows) for m in ("relmse", "dssim")}
    print(f"{len(rows)} frames, means: " + "; ".join(
        f"{m} {means[devices[0]][m]:.5g} -> {means[devices[1]][m]:.5g} ({ratios[m]:.4f}x)" for m in ratios))
    print("largest per-frame ratio: " + ", ".join(f"{m} {v:.4f}x" for m, v in worst.items()))
    if a.out:
        Path(a.out).write_text(json.dumps({"devices": devices, "data": a.data, "frames": len(rows), "means": means,
                                           "ratios": ratios, "largest_frame_ratio": worst, "rows": rows},
                                          indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

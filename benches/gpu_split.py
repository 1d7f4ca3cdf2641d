"""Where the GPU frame time goes: the shipped network with its reconstruction on the device
alone, against the copies of its inputs and outputs across PCIe (docs/results.md, "GPU").

    python benches/gpu_split.py --out gpu-split.json

PyTorch (eager, and replayed as a CUDA graph) runs `export_ms.WithReconstruction`, the
module the engine's `model-recon.onnx` and `model-recon-fp16.onnx` are exported from,
loaded from `training/checkpoints/msnet.pt`, on inputs already on the device; then the
inputs' copy to the device (from pageable and from page-locked memory) and the outputs'
copy back are timed on their own. Times are medians of CUDA-event timings after warm-up.
With `--device cpu` it runs the same on the CPU (wall clock), which is how CI checks it.
"""

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "training"))

from mcdenoise_train.checkpoint import load_msnet  # noqa: E402
from mcdenoise_train.export_ms import WithReconstruction  # noqa: E402
from mcdenoise_train.contract import COLOR_CHANNELS  # noqa: E402


def median_ms(fn, device: str, repeats: int) -> float:
    """The median time of `fn()` in milliseconds, after two warm-up calls."""
    for _ in range(2):
        fn()
    times = []
    for _ in range(repeats):
        if device == "cuda":
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            fn()
            end.record()
            end.synchronize()
            times.append(start.elapsed_time(end))
        else:
            t = time.perf_counter()
            fn()
            times.append((time.perf_counter() - t) * 1000)
    return statistics.median(times)


def measure(net, w: int, h: int, device: str, repeats: int) -> dict:
    # The engine pads a region to a multiple of the pyramid's coarsest step; so does this.
    step = 2 ** (net.levels - 1)
    w, h = -(-w // step) * step, -(-h // step) * step
    gen = torch.Generator().manual_seed(0)
    host = [torch.rand(1, c, h, w, generator=gen) for c in (COLOR_CHANNELS, COLOR_CHANNELS, net.in_features)]
    row = {"frame": f"{w}x{h}", "input_mb": sum(x.numel() * 4 for x in host) / 1e6}
    dev = [x.to(device) for x in host]
    for name, half in (("fp32", False), ("fp16", True)):
        m = WithReconstruction(net, half).to(device).eval()
        with torch.inference_mode():
            outs = m(*dev)
            row[f"network_and_reconstruction_{name}_ms"] = median_ms(lambda: m(*dev), device, repeats)
            if device == "cuda":
                # Replayed as one CUDA graph: without the launch gaps of eager execution.
                try:
                    g = torch.cuda.CUDAGraph()
                    s = torch.cuda.Stream()
                    s.wait_stream(torch.cuda.current_stream())
                    with torch.cuda.stream(s):
                        m(*dev)
                    torch.cuda.current_stream().wait_stream(s)
                    with torch.cuda.graph(g):
                        m(*dev)
                    row[f"network_and_reconstruction_{name}_graph_ms"] = median_ms(g.replay, device, repeats)
                except RuntimeError as e:
                    row[f"network_and_reconstruction_{name}_graph_error"] = str(e)[:500]
    row["output_mb"] = sum(o.numel() * 4 for o in outs) / 1e6
    if device == "cuda":
        pinned = [x.pin_memory() for x in host]
        row["inputs_to_device_pageable_ms"] = median_ms(lambda: [x.to(device) for x in host], device, repeats)
        row["inputs_to_device_pinned_ms"] = median_ms(
            lambda: [x.to(device, non_blocking=True) for x in pinned], device, repeats)
        row["outputs_to_host_ms"] = median_ms(lambda: [o.cpu() for o in outs], device, repeats)
    return row


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda")
    p.add_argument("--sizes", default="1920x1080,3840x2160")
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--checkpoint", default=str(ROOT / "training" / "checkpoints" / "msnet.pt"))
    p.add_argument("--out", required=True)
    a = p.parse_args()
    net, _ = load_msnet(a.checkpoint)
    net = net.to(a.device).eval()
    rows = []
    for size in a.sizes.split(","):
        w, h = map(int, size.split("x"))
        rows.append(measure(net, w, h, a.device, a.repeats))
        print(json.dumps(rows[-1]), file=sys.stderr)
    report = {"command": " ".join(sys.argv), "device": a.device, "torch": torch.__version__,
              "gpu": torch.cuda.get_device_name() if a.device == "cuda" else "", "rows": rows}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

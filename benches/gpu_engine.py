"""The engine on a GPU against OIDN's CUDA device, on the same frames (docs/results.md, "GPU").

    python benches/gpu_engine.py --device cuda --oidn-benchmark PATH/oidnBenchmark \\
        --out docs/results/gpu.json

Synthetic frames with every channel (`mcdenoise_train.frames.synthetic_frame`) at each
`--sizes`; then:

- parity: `mcdenoise run` on `--device` (reconstruction in the graph where the variant has
  `model-recon.onnx`; on the CPU, asked for) against the CPU with the engine's own
  reconstruction, on a small frame: the largest difference relative to the largest value,
  for each of `--precisions` (`fp16`: the network in half precision, `model-recon-fp16.onnx`);
- the daemon (`serve --device --precision --io-binding`, `--workers` workers, whole frames:
  `--tile-v2 0`), for each precision and each of `--io-bindings` (ONNX Runtime's I/O binding,
  page-locked tensors on a GPU, against tensors over the engine's buffers): `--jobs`
  copies of each frame submitted by each of `--clients` concurrent clients in turn; frames per
  second, latency, and the jobs' own stage timings (median), whose `inference` is the time
  on the device once sessions are warm (the first job of each size is left out: it includes
  cuDNN's algorithm search);
- OIDN (`oidnBenchmark -d cuda -r RT.hdr_alb_nrm.WxH`, HDR color with albedo and normal,
  quality high), when `--oidn-benchmark` is given.

With `--device cpu` the same runs on the CPU build (CI runs it on a tiny frame).
"""

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benches"))
sys.path.insert(0, str(ROOT / "training"))

from scale_out import Daemon, request, wait_job  # noqa: E402


def write_frame(path: Path, w: int, h: int) -> None:
    from mcdenoise_train.exr import write_exr
    from mcdenoise_train.frames import synthetic_frame

    write_exr(path, synthetic_frame(h, w, seed=3, covariance=True))


def run_json(a, *args: str) -> dict:
    out = subprocess.run([a.bin, "run", *args, "--models", a.models], check=True, capture_output=True, text=True)
    return json.loads(out.stdout)


def parity(a, work: Path, precision: str) -> dict:
    from mcdenoise_train.exr import read_exr

    frame = work / "parity.exr"
    write_frame(frame, 320, 192)
    reports, colors = {}, {}
    # On the CPU, `auto` would be the engine's reconstruction again: ask for the graph's.
    where = "graph" if a.device == "cpu" else "auto"
    for name, device, where, p in (("device", a.device, where, precision), ("cpu", "cpu", "engine", "fp32")):
        out = work / f"parity-{name}.exr"
        reports[name] = run_json(a, str(frame), "-o", str(out), "--device", device, "--reconstruction", where,
                                 "--precision", p)
        c = read_exr(out)
        colors[name] = [c[k] for k in ("R", "G", "B")]
    scale = max(float(np.abs(x).max()) for x in colors["cpu"])
    worst = max(float(np.abs(x - y).max()) for x, y in zip(colors["device"], colors["cpu"]))
    return {"frame": "320x192", "device": reports["device"]["device"], "precision": reports["device"]["precision"],
            "reconstruction": reports["device"]["reconstruction"], "max_abs_diff": worst,
            "relative_to_max": worst / max(scale, 1e-12)}


def daemon_runs(a, work: Path, frames: dict[str, Path], precision: str, io_binding: str) -> list[dict]:
    rows = []
    d = Daemon(a, work, "serve", None, ("--device", a.device, "--tile-v2", "0", "--precision", precision,
                                        "--io-binding", io_binding))
    try:
        d.wait_ready()
        for size, path in frames.items():
            data = path.read_bytes()
            # Warm-up (cuDNN's algorithm search for this shape), finished before the clock starts.
            wait_job(d.base, request(d.base + "/v1/jobs", data, "POST")["id"])
            for clients in a.clients:
                jobs: list[dict] = []
                lock = threading.Lock()

                def client() -> None:
                    for _ in range(a.jobs):
                        t = time.monotonic()
                        j = wait_job(d.base, request(d.base + "/v1/jobs", data, "POST")["id"], poll=0.005)
                        with lock:
                            jobs.append({**j, "latency_s": time.monotonic() - t})

                t0 = time.monotonic()
                threads = [threading.Thread(target=client) for _ in range(clients)]
                for t in threads:
                    t.start()
                for t in threads:
                    t.join()
                wall = time.monotonic() - t0
                if len(jobs) != clients * a.jobs:
                    raise RuntimeError(f"{size}, {clients} clients: {len(jobs)} of {clients * a.jobs} jobs succeeded")
                stages = {k: statistics.median(j["timings_ms"][k] for j in jobs)
                          for k in jobs[0]["timings_ms"] if isinstance(jobs[0]["timings_ms"][k], (int, float))}
                rows.append({"frame": size, "precision": precision, "io_binding": io_binding,
                             "clients": clients, "jobs": len(jobs),
                             "frames_per_s": len(jobs) / wall,
                             "latency_p50_s": statistics.median(j["latency_s"] for j in jobs),
                             "job_stages_ms_median": stages})
                print(f"{size} {precision}, I/O binding {io_binding}, {clients} clients: {len(jobs) / wall:.2f} frames/s, "
                      f"inference {stages.get('inference', 0):.1f} ms", file=sys.stderr)
    finally:
        d.stop()
    return rows


def oidn(a, sizes: list[str]) -> list[dict]:
    rows = []
    for size in sizes:
        out = subprocess.run([a.oidn_benchmark, "-d", a.device.split(":")[0], "-r", f"RT.hdr_alb_nrm.{size}"],
                             capture_output=True, text=True, timeout=600)
        m = re.search(r"([0-9.]+) msec/image", out.stdout + out.stderr)
        if not m:
            raise RuntimeError(f"oidnBenchmark {size}: no timing in its output:\n{out.stdout[-2000:]}{out.stderr[-2000:]}")
        rows.append({"frame": size, "quality": "high", "ms_per_frame": float(m.group(1))})
        print(f"OIDN {size}: {m.group(1)} ms", file=sys.stderr)
    return rows


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda")
    p.add_argument("--sizes", default="1920x1080,3840x2160")
    p.add_argument("--jobs", type=int, default=8, help="jobs per client and configuration")
    p.add_argument("--clients", default="1,4")
    p.add_argument("--precisions", default="fp32,fp16", help="the networks' precisions to run (`--precision`)")
    p.add_argument("--io-bindings", default="on,off", help="ONNX Runtime's I/O binding settings to run (`--io-binding`)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--threads", type=int, default=4, help="threads per worker (pre- and post-processing)")
    p.add_argument("--models", default=str(ROOT / "models"))
    p.add_argument("--bin", default=os.environ.get("MCDENOISE_BIN", str(ROOT / "target/release/mcdenoise")))
    p.add_argument("--oidn-benchmark", help="oidnBenchmark (pyoidn's, with its CUDA device beside it)")
    p.add_argument("--out", required=True)
    a = p.parse_args()
    a.clients = [int(c) for c in a.clients.split(",")]
    precisions = [p for p in a.precisions.split(",") if p]
    sizes = [s for s in a.sizes.split(",") if s]
    work = Path(tempfile.mkdtemp(prefix="mcdenoise-gpu-"))
    frames = {}
    for size in sizes:
        w, h = map(int, size.split("x"))
        frames[size] = work / f"frame-{size}.exr"
        write_frame(frames[size], w, h)
    report = {
        "command": " ".join(sys.argv),
        "device": a.device,
        "workers": a.workers,
        "threads_per_worker": a.threads,
        "parity": [parity(a, work, p) for p in precisions],
        "daemon": [row for p in precisions for io in a.io_bindings.split(",") if io
                   for row in daemon_runs(a, work, frames, p, io)],
        "oidn": oidn(a, sizes) if a.oidn_benchmark else None,
    }
    gpu = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True).stdout.strip() if a.device != "cpu" else ""
    report["machine"] = {"gpu": gpu, "cpu_threads": os.cpu_count()}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {a.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

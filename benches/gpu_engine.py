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
  quality high), when `--oidn-benchmark` is given;
- `--variant-runs` (e.g. `lin2020`): each variant through the daemon on the first size, one
  client (`variants`).

The parts run in the order OIDN, the daemon with the first `--io-bindings` setting for each
precision, parity, the variants, the other settings; the report is written after each. A
part that fails is named under `errors` (the exit status is then 1) and the others still
run; with `--deadline S`, the parts not begun S seconds after the start are listed under
`skipped`. Larger frames than 1080p get proportionally fewer `--jobs`.

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


def jobs_for(a, size: str) -> int:
    """`--jobs` at 1080p and below; fewer on larger frames, in proportion to their pixels."""
    w, h = map(int, size.split("x"))
    return max(1, round(a.jobs * min(1.0, 1920 * 1080 / (w * h))))


def daemon_runs(a, work: Path, frames: dict[str, Path], precision: str, io_binding: str,
                variant: str | None = None, clients_list: list[int] | None = None) -> list[dict]:
    rows = []
    d = Daemon(a, work, "serve", None, ("--device", a.device, "--tile-v2", "0", "--precision", precision,
                                        "--io-binding", io_binding))
    url = d.base + "/v1/jobs" + (f"?variant={variant}" if variant else "")
    try:
        d.wait_ready()
        for size, path in frames.items():
            if a.past_deadline():
                a.skipped.append(f"daemon {variant or 'default'} {precision} I/O binding {io_binding} {size}")
                continue
            data = path.read_bytes()
            n = jobs_for(a, size)
            # Warm-up (cuDNN's algorithm search for this shape), finished before the clock starts.
            wait_job(d.base, request(url, data, "POST")["id"])
            for clients in clients_list or a.clients:
                jobs: list[dict] = []
                failures: list[str] = []
                lock = threading.Lock()

                def client() -> None:
                    try:
                        for _ in range(n):
                            t = time.monotonic()
                            j = wait_job(d.base, request(url, data, "POST")["id"], poll=0.005)
                            with lock:
                                jobs.append({**j, "latency_s": time.monotonic() - t})
                    except Exception as e:  # noqa: BLE001 - reported below, with the part
                        with lock:
                            failures.append(f"{type(e).__name__}: {e}")

                t0 = time.monotonic()
                threads = [threading.Thread(target=client) for _ in range(clients)]
                for t in threads:
                    t.start()
                for t in threads:
                    t.join()
                wall = time.monotonic() - t0
                if len(jobs) != clients * n:
                    raise RuntimeError(f"{size}, {clients} clients: {len(jobs)} of {clients * n} jobs succeeded; "
                                       f"first failure: {failures[0] if failures else 'none reported'}")
                stages = {k: statistics.median(j["timings_ms"][k] for j in jobs)
                          for k in jobs[0]["timings_ms"] if isinstance(jobs[0]["timings_ms"][k], (int, float))}
                rows.append({"frame": size, **({"variant": variant} if variant else {}),
                             "precision": precision, "io_binding": io_binding,
                             "clients": clients, "jobs": len(jobs),
                             "frames_per_s": len(jobs) / wall,
                             "latency_p50_s": statistics.median(j["latency_s"] for j in jobs),
                             "job_stages_ms_median": stages})
                print(f"{size} {variant or 'default'} {precision}, I/O binding {io_binding}, {clients} clients: {len(jobs) / wall:.2f} frames/s, "
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
    p.add_argument("--variant-runs", default="",
                   help="more variants to time (e.g. lin2020), each on the first size with one client: `variants`")
    p.add_argument("--deadline", type=float, default=0,
                   help="seconds after which the parts not yet started are skipped (listed under `skipped`); 0: none")
    p.add_argument("--out", required=True)
    a = p.parse_args()
    a.clients = [int(c) for c in a.clients.split(",")]
    precisions = [p for p in a.precisions.split(",") if p]
    sizes = [s for s in a.sizes.split(",") if s]
    a.skipped = []
    start = time.monotonic()
    a.past_deadline = lambda: a.deadline > 0 and time.monotonic() - start > a.deadline
    work = Path(tempfile.mkdtemp(prefix="mcdenoise-gpu-"))
    frames = {}
    for size in sizes:
        w, h = map(int, size.split("x"))
        frames[size] = work / f"frame-{size}.exr"
        write_frame(frames[size], w, h)
    gpu = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True).stdout.strip() if a.device != "cpu" else ""
    report = {
        "command": " ".join(sys.argv),
        "device": a.device,
        "machine": {"gpu": gpu, "cpu_threads": os.cpu_count()},
        "workers": a.workers,
        "threads_per_worker": a.threads,
        "jobs_per_client": {size: jobs_for(a, size) for size in sizes},
        "parity": [],
        "daemon": [],
        "variants": [],
        "oidn": None,
        "errors": [],
        "skipped": a.skipped,
    }
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)

    def section(name: str, run) -> None:
        """Runs one part of the benchmark and writes the report so far: a part that fails is
        recorded under `errors` and the rest still runs; past `--deadline`, under `skipped`."""
        if a.past_deadline():
            a.skipped.append(name)
        else:
            try:
                run()
            except Exception as e:  # noqa: BLE001 - the report names it, the other parts go on
                report["errors"].append({"part": name, "error": f"{type(e).__name__}: {e}"[-4000:]})
                print(f"{name}: {type(e).__name__}: {e}", file=sys.stderr)
        report["elapsed_s"] = round(time.monotonic() - start, 1)
        out.write_text(json.dumps(report, indent=1) + "\n")

    def daemon(p: str, io: str) -> None:
        section(f"daemon {p} I/O binding {io}", lambda: report["daemon"].extend(daemon_runs(a, work, frames, p, io)))

    # The most telling parts first, in case the deadline cuts the rest: OIDN, every precision
    # with the first I/O binding setting, parity, the other variants, the other settings.
    io_bindings = [io for io in a.io_bindings.split(",") if io]
    if a.oidn_benchmark:
        section("oidn", lambda: report.__setitem__("oidn", oidn(a, sizes)))
    for p in precisions:
        daemon(p, io_bindings[0])
    for p in precisions:
        section(f"parity {p}", lambda p=p: report["parity"].append(parity(a, work, p)))
    for v in [v for v in a.variant_runs.split(",") if v]:
        section(f"variant {v}", lambda v=v: report["variants"].extend(
            daemon_runs(a, work, {sizes[0]: frames[sizes[0]]}, "auto", "auto", variant=v, clients_list=[1])))
    for io in io_bindings[1:]:
        for p in precisions:
            daemon(p, io)
    print(f"wrote {a.out}", file=sys.stderr)
    return 1 if report["errors"] else 0


if __name__ == "__main__":
    raise SystemExit(main())

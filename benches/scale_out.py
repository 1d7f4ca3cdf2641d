"""Throughput of the shared mode (NATS JetStream) with 1, 2 and 3 replicas against one
daemon in the embedded mode, on this machine (`make bench-scale-out`).

    python benches/scale_out.py --frame target/bench/frame-320x180.exr --jobs 24 \\
        --out docs/results/scale-out.json

Each configuration starts fresh: its daemons (one worker of `--threads` threads each, the
given models), and for the shared ones a nats-server with JetStream on a loopback port and
an empty store. `--jobs` copies of the frame are submitted round-robin over the replicas
(all at once, so the queue is never empty), and the wall time runs from the first
submission to the last success. Reported per configuration: jobs per second, per-replica
efficiency (throughput / (replicas x the one-replica shared throughput)), and the queue's
own overhead per job: (wall of shared with 1 replica - wall of embedded) / jobs, the cost
of storing the frame and result in JetStream and passing the job through the stream and
key-value bucket. The machine's cores cap the gain of more replicas: each replica's worker
uses `--threads` threads.
"""

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(port: int, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return
        except OSError:
            time.sleep(0.05)
    raise RuntimeError(f"nothing listens on port {port}")


def request(url: str, data: bytes | None = None, method: str = "GET") -> dict:
    headers = {"content-type": "image/x-exr"} if data is not None else {}
    req = urllib.request.Request(url, data=data, method=method, headers=headers)
    with urllib.request.urlopen(req, timeout=60) as r:
        return json.loads(r.read() or b"{}")


def wait_job(base: str, job_id: str, poll: float = 0.02) -> dict:
    """Polls job `job_id` on the daemon at `base` until it ends; its record if it succeeded."""
    while True:
        j = request(f"{base}/v1/jobs/{job_id}")
        if j["state"] in ("succeeded", "failed", "cancelled"):
            break
        time.sleep(poll)
    if j["state"] != "succeeded":
        raise RuntimeError(f"job {job_id} {j['state']}: {j.get('error')}")
    return j


class Daemon:
    """`mcdenoise serve` on loopback ports with its data under `work/name`: `a.workers`
    workers (1 without it) of `a.threads` threads; `extra` are more arguments."""

    def __init__(self, a, work: Path, name: str, store: str | None, extra: tuple[str, ...] = ()):
        self.http = free_port()
        self.log = open(work / f"{name}.log", "w")
        cmd = [
            a.bin, "serve", "--http", f"127.0.0.1:{self.http}", "--grpc", f"127.0.0.1:{free_port()}",
            "--workers", str(getattr(a, "workers", 1)), "--threads-per-worker", str(a.threads), "--models", a.models,
            "--data-dir", str(work / name), "--queue-capacity", str(max(64, a.jobs)), "--log", "warn", *extra,
        ]
        if store:
            cmd += ["--store", store]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=self.log)
        self.base = f"http://127.0.0.1:{self.http}"

    def wait_ready(self, timeout: float = 120.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                self.log.flush()
                tail = Path(self.log.name).read_text()[-2000:]
                raise RuntimeError(f"the daemon exited ({self.proc.returncode}):\n{tail}")
            try:
                if request(self.base + "/readyz").get("ready"):
                    return
            except OSError:
                pass
            time.sleep(0.1)
        raise RuntimeError("the daemon is not ready")

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        self.log.close()


def run_config(a, frame: bytes, replicas: int, shared: bool) -> dict:
    work = Path(tempfile.mkdtemp(prefix="mcdenoise-bench-"))
    nats = None
    daemons: list[Daemon] = []
    try:
        store = None
        if shared:
            port = free_port()
            nats = subprocess.Popen(
                [a.nats, "-js", "-a", "127.0.0.1", "-p", str(port), "-sd", str(work / "js")],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            )
            wait_port(port)
            store = f"nats://127.0.0.1:{port}"
        daemons = [Daemon(a, work, f"replica-{i}", store) for i in range(replicas)]
        for d in daemons:
            d.wait_ready()
        t0 = time.monotonic()
        ids = [request(daemons[i % replicas].base + "/v1/jobs", frame, "POST")["id"] for i in range(a.jobs)]
        submitted = time.monotonic() - t0
        jobs = [wait_job(daemons[(i + 1) % replicas].base, job_id) for i, job_id in enumerate(ids)]
        wall = time.monotonic() - t0
        runs = [j["timings_ms"]["total"] for j in jobs]
        return {
            "mode": "shared" if shared else "embedded",
            "replicas": replicas,
            "jobs": a.jobs,
            "wall_s": round(wall, 3),
            "submit_s": round(submitted, 3),
            "jobs_per_s": round(a.jobs / wall, 4),
            "mean_run_ms": round(sum(runs) / len(runs), 1),
            "attempts": sum(j["attempts"] for j in jobs),
        }
    finally:
        for d in daemons:
            d.stop()
        if nats:
            nats.terminate()
            nats.wait()
        shutil.rmtree(work, ignore_errors=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frame", required=True, help="EXR frame every job denoises")
    p.add_argument("--jobs", type=int, default=24)
    p.add_argument("--replicas", default="1,2,3", help="replica counts of the shared mode")
    p.add_argument("--threads", type=int, default=1, help="threads of each replica's worker")
    p.add_argument("--models", default=str(ROOT / "models"))
    p.add_argument("--bin", default=os.environ.get("MCDENOISE_BIN", str(ROOT / "target/release/mcdenoise")))
    p.add_argument("--nats", default=shutil.which("nats-server") or "/usr/sbin/nats-server")
    p.add_argument("--out", required=True)
    a = p.parse_args()
    frame = Path(a.frame).read_bytes()
    counts = [int(n) for n in a.replicas.split(",")]
    results = [run_config(a, frame, 1, shared=False)]
    for n in counts:
        results.append(run_config(a, frame, n, shared=True))
    one = next((r for r in results if r["mode"] == "shared" and r["replicas"] == 1), None)
    for r in results:
        if r["mode"] == "shared" and one:
            r["efficiency"] = round(r["jobs_per_s"] / (r["replicas"] * one["jobs_per_s"]), 3)
    embedded = results[0]
    report = {
        "frame": str(a.frame),
        "frame_bytes": len(frame),
        "models": a.models,
        "threads_per_replica": a.threads,
        "cores": os.cpu_count(),
        "results": results,
        "queue_overhead_ms_per_job": round((one["wall_s"] - embedded["wall_s"]) * 1e3 / a.jobs, 1) if one else None,
    }
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(report, indent=1) + "\n")
    print(f"{'mode':9} {'replicas':>8} {'jobs/s':>8} {'wall s':>8} {'efficiency':>10}")
    for r in results:
        print(f"{r['mode']:9} {r['replicas']:>8} {r['jobs_per_s']:>8.3f} {r['wall_s']:>8.2f} {r.get('efficiency', ''):>10}")
    print(f"queue overhead per job: {report['queue_overhead_ms_per_job']} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())

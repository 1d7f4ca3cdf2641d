"""benches/gpu_engine.py, the GPU benchmark against OIDN's CUDA device, run end to end on the
CPU build with the tiny models: parity of the reconstruction in the graph (float32 and half
precision) with the engine's,
the daemon's throughput rows (with and without ONNX Runtime's I/O binding) and the report's fields (the figures come from a GPU machine)."""

import json
import os
import subprocess
import sys
from pathlib import Path

from test_train import BIN, needs_engine

ROOT = Path(__file__).resolve().parents[2]


@needs_engine
def test_gpu_engine_bench_runs_on_the_cpu(tmp_path):
    out = tmp_path / "gpu.json"
    subprocess.run([sys.executable, str(ROOT / "benches" / "gpu_engine.py"), "--device", "cpu", "--sizes", "96x64",
                    "--jobs", "2", "--clients", "1,2", "--workers", "1", "--threads", "1", "--bin", BIN,
                    "--models", str(ROOT / "tests" / "fixtures" / "models" / "tiny-v2"), "--out", str(out)],
                   check=True, capture_output=True, env={**os.environ})
    r = json.loads(out.read_text())
    fp32, fp16 = r["parity"]
    assert (fp32["reconstruction"], fp32["precision"]) == ("graph", "fp32") and fp32["relative_to_max"] <= 1e-4
    # The network in half precision: near the engine's float32 output, not equal to it.
    assert (fp16["reconstruction"], fp16["precision"]) == ("graph", "fp16") and 0 < fp16["relative_to_max"] <= 2e-2
    assert [(row["frame"], row["precision"], row["io_binding"], row["clients"], row["jobs"]) for row in r["daemon"]] == [
        ("96x64", p, io, c, j) for io in ("on", "off") for p in ("fp32", "fp16") for c, j in ((1, 2), (2, 4))]
    assert all(row["frames_per_s"] > 0 and row["job_stages_ms_median"]["inference"] > 0 for row in r["daemon"])
    assert r["oidn"] is None


@needs_engine
def test_gpu_engine_bench_reports_what_failed_and_what_the_deadline_skipped(tmp_path):
    out = tmp_path / "gpu.json"
    common = [sys.executable, str(ROOT / "benches" / "gpu_engine.py"), "--device", "cpu", "--sizes", "96x64",
              "--jobs", "1", "--clients", "1", "--workers", "1", "--threads", "1", "--bin", BIN,
              "--models", str(ROOT / "tests" / "fixtures" / "models" / "tiny-v2"), "--out", str(out)]
    # A variant that is not loaded fails its part, named in `errors`; the others still ran.
    run = subprocess.run([*common, "--precisions", "fp32", "--io-bindings", "off", "--variant-runs", "nosuch"],
                         capture_output=True, env={**os.environ})
    r = json.loads(out.read_text())
    assert run.returncode == 1 and [e["part"] for e in r["errors"]] == ["variant nosuch"]
    assert len(r["daemon"]) == 1 and len(r["parity"]) == 1 and r["variants"] == [] and r["skipped"] == []
    # Past the deadline, every part is skipped and listed.
    subprocess.run([*common, "--deadline", "1e-9"], check=True, capture_output=True, env={**os.environ})
    r = json.loads(out.read_text())
    assert r["daemon"] == [] and r["parity"] == [] and r["errors"] == []
    assert r["skipped"] == ["daemon fp32 I/O binding on", "daemon fp16 I/O binding on", "parity fp32", "parity fp16",
                            "daemon fp32 I/O binding off", "daemon fp16 I/O binding off"]


def test_gpu_split_times_the_network_alone_on_the_cpu(tmp_path):
    # benches/gpu_split.py on the CPU (wall clock): the shipped network and its reconstruction,
    # float32 and half, on a frame padded to the network's multiple of 16.
    out = tmp_path / "split.json"
    subprocess.run([sys.executable, str(ROOT / "benches" / "gpu_split.py"), "--device", "cpu", "--sizes", "40x20",
                    "--repeats", "1", "--out", str(out)], check=True, capture_output=True)
    r = json.loads(out.read_text())
    [row] = r["rows"]
    assert row["frame"] == "48x32" and row["input_mb"] == 48 * 32 * 48 * 4 / 1e6
    assert row["network_and_reconstruction_fp32_ms"] > 0 and row["network_and_reconstruction_fp16_ms"] > 0
    assert row["output_mb"] == 2 * 3 * 48 * 32 * 4 / 1e6

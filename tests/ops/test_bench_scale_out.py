"""benches/scale_out.py on tiny inputs: the scale-out benchmark (make bench-scale-out) keeps
working. Two jobs of a 64x64 frame with the tiny models, embedded and shared with 1 and 2
replicas on a nats-server started by the benchmark."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT, mcdenoise_bin


def test_the_scale_out_benchmark_runs_every_configuration(tmp_path):
    nats = shutil.which("nats-server") or "/usr/sbin/nats-server"
    if not Path(nats).is_file():
        pytest.fail("nats-server is missing: bash scripts/setup test installs it")
    out = tmp_path / "scale-out.json"
    r = subprocess.run(
        [sys.executable, str(ROOT / "benches" / "scale_out.py"), "--frame",
         str(ROOT / "tests/fixtures/frames/cornell-spp8.exr"), "--jobs", "2", "--replicas", "1,2",
         "--models", str(ROOT / "tests/fixtures/models/tiny"), "--bin", str(mcdenoise_bin()), "--nats", nats,
         "--out", str(out)],
        capture_output=True, text=True, timeout=300,
    )
    assert r.returncode == 0, r.stderr
    report = json.loads(out.read_text())
    configs = [(x["mode"], x["replicas"]) for x in report["results"]]
    assert configs == [("embedded", 1), ("shared", 1), ("shared", 2)]
    for x in report["results"]:
        assert x["jobs"] == 2 and x["attempts"] == 2 and x["jobs_per_s"] > 0, x
    assert report["results"][1]["efficiency"] == 1.0
    assert isinstance(report["queue_overhead_ms_per_job"], float)

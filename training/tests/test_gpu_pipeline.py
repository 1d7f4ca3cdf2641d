"""scripts/gpu-pipeline end to end on tiny inputs, on the CPU (DEVICE=cpu): render (training,
validation and test workers), train two runs side by side against a deadline, pack the
results, pack the test set and unpack it here as one data set."""

import json
import os
import subprocess
import tarfile
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "gpu-pipeline"
TINY = "--ext-width 4 --enc 4,4,4,4 --dec 4,4,4,4 --threads 2"


def _run(env, *args, timeout=300):
    res = subprocess.run([str(SCRIPT), *args], env=env, capture_output=True, text=True, timeout=timeout)
    assert res.returncode == 0, f"gpu-pipeline {' '.join(args)}:\n{res.stdout}\n{res.stderr}"
    return res


@pytest.mark.skipif(not SCRIPT.exists(), reason="scripts/gpu-pipeline missing")
def test_render_train_pack_and_unpack_on_the_cpu(tmp_path):
    import sys

    home = tmp_path / "home"
    env = {**os.environ, "GPU_HOME": str(home), "DEVICE": "cpu", "PY": sys.executable, "WORKERS": "2",
           "VAL_WORKERS": "1", "TEST_WORKERS": "1", "SIZE": "32", "SPP": "2,8", "TEST_SPP": "2,8",
           "REF_SPP": "16", "PATCH": "16", "BATCH": "2", "VAL_FRAMES": "2",
           "RUNS": f"a=--l1 1 {TINY};b=--l1 1 --ssim 0.2 {TINY}"}
    _run(env, "render", "40")
    splits = {}
    for m in home.glob("*/*/manifest.jsonl"):
        for line in m.read_text().splitlines():
            r = json.loads(line)
            splits.setdefault(m.parent.name, set()).add(r["split"])
    assert splits.get("w0") == {"val"} and splits.get("w1") == {"train"} and splits.get("t0") == {"test"}

    _run(env, "train", "45")
    for run in ("a", "b"):
        assert (home / "runs" / run / "best.pt").is_file()
        for variant in ("full", "nocov"):
            assert (home / "models" / run / variant / "model.onnx").is_file()

    out = tmp_path / "out"
    _run(env, "pack", str(out))
    with tarfile.open(out / "models-runs.tar.gz") as t:
        names = t.getnames()
    assert "models/a/full/model.onnx" in names and "runs/b/val.jsonl" in names

    _run(env, "pack-test", str(out))
    assert all(p.stat().st_size <= 15_000_000 for p in out.glob("test-data.tar.part-*"))
    dest = tmp_path / "data-test"
    _run(env, "unpack-test", str(out), str(dest))
    from mcdenoise_train.data import manifest_frames

    records = manifest_frames(dest)
    assert records and all(r["split"] == "test" and Path(r["noisy"]).is_file() for r in records)

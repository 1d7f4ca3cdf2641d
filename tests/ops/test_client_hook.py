"""The Python client (clients/python) and the farm hook (examples/farm) against a real
daemon with the shipped models."""

from __future__ import annotations

import shutil
import subprocess
import sys
import threading
import time

import numpy as np
import OpenEXR
import pytest

import denoise_hook
import mcdenoise_client as mc
from conftest import FRAMES, ROOT, TOKEN


def read_rgb(path):
    f = OpenEXR.File(str(path), separate_channels=True)
    ch = f.channels()
    return np.stack([np.asarray(ch[c].pixels, dtype=np.float32) for c in "RGB"])


def copy_frame(tmp_path, name="cornell-spp8.exr", as_name="beauty.0001.exr"):
    d = tmp_path / "sh010"
    d.mkdir(exist_ok=True)
    shutil.copy(FRAMES / name, d / as_name)
    return d / as_name


def without_channel(src, dst, drop):
    f = OpenEXR.File(str(src), separate_channels=True)
    chans = {n: np.asarray(c.pixels) for n, c in f.channels().items() if n != drop}
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, chans).write(str(dst))


def test_hook_writes_the_denoised_frame_next_to_the_rendered_one(daemon, tmp_path):
    frame = copy_frame(tmp_path)
    client = mc.Client(daemon.url, token=TOKEN)
    job = denoise_hook.denoise_frame(frame, client, label="sh010", log=lambda m: None)
    out = frame.parent / "beauty.0001.denoised.exr"
    assert job["state"] == "succeeded" and job["variant"] == "full" and job["label"] == "sh010"
    assert out.is_file() and not list(frame.parent.glob("*.part*"))
    denoised, noisy, ref = read_rgb(out), read_rgb(frame), read_rgb(FRAMES / "cornell-ref.exr")
    assert denoised.shape == (3, 64, 64) and np.isfinite(denoised).all()
    # The shipped model lowers the error of the 8-spp input against the reference.
    rel = lambda x: float(np.mean((x - ref) ** 2 / (ref ** 2 + 0.01)))  # noqa: E731
    assert rel(denoised) < 0.5 * rel(noisy), (rel(denoised), rel(noisy))
    # Running the hook again on the unchanged file finds the same job.
    again = denoise_hook.denoise_frame(frame, client, log=lambda m: None)
    assert again["id"] == job["id"]


def test_frame_without_covariance_uses_the_nocov_model(daemon, tmp_path):
    frame = copy_frame(tmp_path, "cornell-nocov-spp8.exr")
    job = mc.Client(daemon.url, token=TOKEN).denoise(frame, tmp_path / "out.exr")
    assert job["variant"] == "nocov"
    assert read_rgb(tmp_path / "out.exr").shape == (3, 64, 64)


def test_missing_channel_is_named_and_not_retried(daemon, tmp_path):
    bad = tmp_path / "no-depth.exr"
    without_channel(FRAMES / "cornell-spp8.exr", bad, "depth.Z")
    retries = []
    client = mc.Client(daemon.url, token=TOKEN, on_retry=lambda r, w: retries.append(r))
    with pytest.raises(mc.DaemonError) as e:
        denoise_hook.denoise_frame(bad, client, log=lambda m: None)
    assert e.value.status == 422 and e.value.code == "invalid_frame"
    assert "depth.Z" in e.value.message
    assert retries == []
    assert not (tmp_path / "no-depth.denoised.exr").exists()


def test_wrong_token_is_refused(daemon, tmp_path):
    with pytest.raises(mc.DaemonError) as e:
        mc.Client(daemon.url, token="wrong").submit(FRAMES / "cornell-spp8.exr")
    assert (e.value.status, e.value.code) == (401, "unauthenticated")


def test_queue_full_is_retried_after_retry_after(make_daemon, tmp_path):
    d = make_daemon("--queue-capacity", "1", "--debug-tile-delay", "250ms")
    frame = FRAMES / "cornell-spp8.exr"
    # One job first, so the daemon's Retry-After is based on a measured run time.
    mc.Client(d.url, token=TOKEN).denoise(frame, tmp_path / "warm.exr")
    retries, errors, jobs = [], [], []

    def one(i):
        try:
            c = mc.Client(d.url, token=TOKEN, retry_timeout=120, on_retry=lambda r, w: retries.append((r, w)))
            jobs.append(c.denoise(frame, tmp_path / f"out{i}.exr", idempotency_key=f"q-{i}"))
        except Exception as e:  # collected for the assertion below
            errors.append(e)

    threads = [threading.Thread(target=one, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(180)
    assert errors == [] and len(jobs) == 4
    assert any(r.startswith("429 queue_full") for r, _ in retries), retries
    assert all(w >= 1 for r, w in retries if r.startswith("429")), retries
    status, metrics = d.get("/metrics")
    assert status == 200
    line = next(ln for ln in metrics.splitlines() if ln.startswith('mcdenoise_jobs_rejected_total{reason="queue_full"}'))
    assert float(line.split()[-1]) >= 1


def test_submission_while_loading_is_retried(make_daemon, tmp_path):
    d = make_daemon("--debug-startup-delay", "3s", wait=False)
    retries = []
    client = mc.Client(d.url, token=TOKEN, retry_timeout=60, on_retry=lambda r, w: retries.append(r))
    # Submit once the HTTP server answers (the client would also retry a refused
    # connection, but its backoff could step over the whole loading window).
    for _ in range(200):
        try:
            if d.get("/livez")[0] == 200:
                break
        except OSError:
            time.sleep(0.02)
    job = client.denoise(FRAMES / "cornell-spp8.exr", tmp_path / "out.exr")
    assert job["state"] == "succeeded"
    assert any(r.startswith("503 unavailable") for r in retries), retries


def test_hook_resubmits_a_job_that_disappeared(make_daemon, tmp_path):
    d = make_daemon("--debug-tile-delay", "300ms")
    frame = copy_frame(tmp_path)
    client = mc.Client(d.url, token=TOKEN)
    logs, result = [], {}
    t = threading.Thread(target=lambda: result.update(job=denoise_hook.denoise_frame(frame, client, log=logs.append)))
    t.start()
    for _ in range(200):
        if logs:
            break
        time.sleep(0.05)
    first = logs[0].split()[2]
    client.delete(first)  # as if the replica holding it had gone
    t.join(120)
    assert result["job"]["state"] == "succeeded" and result["job"]["id"] != first
    assert any("submitting again" in m for m in logs), logs
    assert (frame.parent / "beauty.0001.denoised.exr").is_file()


def test_hook_command_line_over_a_frame_range(daemon, tmp_path):
    d = tmp_path / "sh020"
    d.mkdir()
    shutil.copy(FRAMES / "cornell-spp8.exr", d / "beauty.0001.exr")
    shutil.copy(FRAMES / "shadow-spp8.exr", d / "beauty.0002.exr")
    without_channel(FRAMES / "caustic-spp8.exr", d / "beauty.0003.exr", "depth.Z")
    cmd = [sys.executable, str(ROOT / "examples" / "farm" / "denoise_hook.py"), "--server", daemon.url,
           "--pattern", str(d / "beauty.####.exr")]
    ok = subprocess.run(cmd + ["--frames", "1-2"], capture_output=True, text=True,
                        env={"MCDENOISE_TOKEN": TOKEN, "PATH": "/usr/bin:/bin"}, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert (d / "beauty.0001.denoised.exr").is_file() and (d / "beauty.0002.denoised.exr").is_file()
    assert "denoised 2 of 2 frames" in ok.stderr
    bad = subprocess.run(cmd + ["--frames", "3"], capture_output=True, text=True,
                         env={"MCDENOISE_TOKEN": TOKEN, "PATH": "/usr/bin:/bin"}, timeout=120)
    assert bad.returncode == 1
    assert "depth.Z" in bad.stderr and "denoised 0 of 1 frames" in bad.stderr


def test_frame_pattern_expansion():
    assert denoise_hook.expand_pattern("a/b.###.exr", "1-3,10") == [
        "a/b.001.exr", "a/b.002.exr", "a/b.003.exr", "a/b.010.exr"]
    assert str(denoise_hook.output_path("x/beauty.0001.exr")) == "x/beauty.0001.denoised.exr"
    with pytest.raises(ValueError):
        denoise_hook.output_path("x/beauty.png")

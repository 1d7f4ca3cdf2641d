"""The Python client (clients/python) and the farm hook (examples/farm) against a real
daemon with the shipped models."""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from types import ModuleType, SimpleNamespace

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
    out = frame.parent / "beauty.denoised.0001.exr"
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
    assert not list(tmp_path.glob("*denoised*"))


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
    assert (frame.parent / "beauty.denoised.0001.exr").is_file()


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
    assert (d / "beauty.denoised.0001.exr").is_file() and (d / "beauty.denoised.0002.exr").is_file()
    assert "denoised 2 of 2 frames" in ok.stderr
    bad = subprocess.run(cmd + ["--frames", "1-3"], capture_output=True, text=True,
                         env={"MCDENOISE_TOKEN": TOKEN, "PATH": "/usr/bin:/bin"}, timeout=120)
    assert bad.returncode == 1
    assert "depth.Z" in bad.stderr and "denoised 2 of 3 frames" in bad.stderr
    # The failed frames are named again at the end.
    failed = bad.stderr.split("1 failed:\n", 1)[1].splitlines()
    assert len(failed) == 1 and failed[0].strip().startswith(str(d / "beauty.0003.exr") + ": 422 invalid_frame")


def test_frame_pattern_expansion():
    assert denoise_hook.expand_pattern("a/b.###.exr", "1-3,10") == [
        "a/b.001.exr", "a/b.002.exr", "a/b.003.exr", "a/b.010.exr"]
    with pytest.raises(ValueError):
        denoise_hook.output_path("x/beauty.png")


@pytest.mark.parametrize("frame, pattern, out", [
    ("x/beauty.0001.exr", None, "x/beauty.denoised.0001.exr"),
    ("x/shot_0001.exr", None, "x/shot_denoised_0001.exr"),
    ("x/sh010.v003.0010.exr", None, "x/sh010.v003.denoised.0010.exr"),
    ("x/beauty.exr", None, "x/beauty.denoised.exr"),
    ("x/0001.exr", None, "x/denoised.0001.exr"),
    ("x/beauty.0001.exr", "{name}.denoised.{ext}", "x/beauty.0001.denoised.exr"),
    ("x/beauty.0001.exr", "denoised/{stem}.{frame}.{ext}", "x/denoised/beauty.0001.exr"),
    ("x/beauty.exr", "denoised/{stem}.{frame}.{ext}", "x/denoised/beauty.exr"),
    ("x/beauty.0001.exr", "/comp/sh010/{stem}_dn.{frame}.{ext}", "/comp/sh010/beauty_dn.0001.exr"),
])
def test_output_pattern(frame, pattern, out):
    args = (pattern,) if pattern else ()
    assert str(denoise_hook.output_path(frame, *args)) == out


@pytest.mark.parametrize("pattern", ["{name}.{ext}", "{stem}.{frame}.{ext}", "{shot}.exr", "{stem", "sub/"])
def test_output_pattern_refused(pattern, tmp_path):
    with pytest.raises(ValueError):
        denoise_hook.output_path("x/beauty.0001.exr", pattern)
    r = subprocess.run([sys.executable, str(ROOT / "examples" / "farm" / "denoise_hook.py"), "--output-pattern", pattern,
                        str(tmp_path / "beauty.0001.exr")], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "output pattern" in r.stderr


def test_frames_writing_the_same_output_fail_before_submission(tmp_path):
    frames = [copy_frame(tmp_path, as_name=f"beauty.000{i}.exr") for i in (1, 2)]
    client = mc.Client("http://127.0.0.1:9", retry_timeout=0)  # never reached
    logs = []
    errors = denoise_hook.denoise_frames(frames, client, output_pattern="out.{ext}", log=logs.append)
    assert len(errors) == 2 and all("is also the output of" in e for e in errors), errors


def hook_cli(*args, token=TOKEN, timeout=180):
    env = {"PATH": "/usr/bin:/bin"}
    if token:
        env["MCDENOISE_TOKEN"] = token
    return subprocess.run([sys.executable, str(ROOT / "examples" / "farm" / "denoise_hook.py"), *map(str, args)],
                          capture_output=True, text=True, env=env, timeout=timeout)


def request_count(d, route):
    status, text = d.get("/metrics")
    assert status == 200
    prefix = f'mcdenoise_http_requests_total{{route="{route}",'
    return sum(float(ln.split()[-1]) for ln in text.splitlines() if ln.startswith(prefix))


def log_order(stderr):
    """(kind, frame name) per line of the hook's log: kind `job` (submitted) or `wrote`."""
    out = []
    for ln in stderr.splitlines():
        m = re.match(r"(\S+\.exr): (job|wrote) ", ln)
        if m:
            out.append((m.group(2), m.group(1)))
    return out


def test_hook_submits_the_range_before_waiting_and_writes_each_as_it_finishes(make_daemon, tmp_path):
    d = make_daemon("--debug-tile-delay", "1s")
    shot = tmp_path / "sh030"
    shot.mkdir()
    for i in range(1, 6):
        shutil.copy(FRAMES / "cornell-spp8.exr", shot / f"beauty.{i:04d}.exr")
    r = hook_cli("--server", d.url, "--pattern", shot / "beauty.####.exr", "--frames", "1-5")
    assert r.returncode == 0, r.stderr
    order = log_order(r.stderr)
    first_written = [k for k, _ in order].index("wrote")
    assert sorted(f for k, f in order[:first_written] if k == "job") == [f"beauty.{i:04d}.exr" for i in range(1, 6)]
    assert sorted(p.name for p in shot.glob("*denoised*")) == [f"beauty.denoised.{i:04d}.exr" for i in range(1, 6)]
    assert "denoised 5 of 5 frames" in r.stderr
    # Waiting went through each job's events, not by polling it.
    assert request_count(d, "/v1/jobs/{id}/events") == 5
    assert request_count(d, "/v1/jobs/{id}") == 0
    # Another pattern: the same jobs (found by their keys), other names.
    r = hook_cli("--server", d.url, "--pattern", shot / "beauty.####.exr", "--frames", "1-5",
                 "--output-pattern", "denoised/{stem}_{frame}.{ext}")
    assert r.returncode == 0, r.stderr
    assert r.stderr.count(" succeeded\n") == 5
    assert sorted(p.name for p in (shot / "denoised").iterdir()) == [f"beauty_{i:04d}.exr" for i in range(1, 6)]
    # At most --concurrency frames in flight: the third is submitted once one is written.
    other = tmp_path / "sh040"
    other.mkdir()
    for i in range(1, 5):
        shutil.copy(FRAMES / "shadow-spp8.exr", other / f"beauty.{i:04d}.exr")
    r = hook_cli("--server", d.url, "--pattern", other / "beauty.####.exr", "--frames", "1-4", "--concurrency", "2")
    assert r.returncode == 0, r.stderr
    kinds = [k for k, _ in log_order(r.stderr)]
    assert kinds[:2] == ["job", "job"] and kinds.index("wrote") < [i for i, k in enumerate(kinds) if k == "job"][2]
    assert len(list(other.glob("beauty.denoised.*.exr"))) == 4


def test_hook_reports_a_refused_token_on_large_frames_at_once(daemon, tmp_path):
    shot = tmp_path / "sh050"
    shot.mkdir()
    for i in range(1, 4):
        with open(shot / f"beauty.{i:04d}.exr", "wb") as f:
            f.write((FRAMES / "cornell-spp8.exr").read_bytes())
            f.write(os.urandom(8_000_000))
    t = time.monotonic()
    r = hook_cli("--server", daemon.url, "--pattern", shot / "beauty.####.exr", "--frames", "1-3", token="wrong",
                 timeout=120)
    assert time.monotonic() - t < 20
    assert r.returncode == 1
    assert "retrying" not in r.stderr and "Broken pipe" not in r.stderr and "reset" not in r.stderr, r.stderr
    failed = r.stderr.split("3 failed:\n", 1)[1].splitlines()
    assert [ln.strip().split(": ", 1)[0] for ln in failed] == [str(shot / f"beauty.{i:04d}.exr") for i in range(1, 4)]
    assert "401 unauthenticated" in failed[0] and all("not submitted: 401" in ln for ln in failed[1:])
    assert "denoised 0 of 3 frames" in r.stderr
    assert not list(shot.glob("*denoised*"))


def test_blender_handler_with_a_stand_in_bpy(daemon, tmp_path, monkeypatch, capsys):
    # Blender is not installed: a stand-in `bpy` with what the handler uses, and the real
    # hook and daemon behind it.
    bpy = ModuleType("bpy")
    bpy.app = SimpleNamespace(handlers=SimpleNamespace(render_write=[], render_complete=[], render_cancel=[]))
    bpy.path = SimpleNamespace(abspath=lambda p: p)
    monkeypatch.setitem(sys.modules, "bpy", bpy)
    monkeypatch.setenv("MCDENOISE_SERVER", daemon.url)
    monkeypatch.setenv("MCDENOISE_TOKEN", TOKEN)
    spec = importlib.util.spec_from_file_location("denoise_handler", ROOT / "examples" / "blender" / "denoise_handler.py")
    handler = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(handler)
    renders = tmp_path / "render"
    renders.mkdir()
    scene = SimpleNamespace(name="shot", frame_current=0,
                            render=SimpleNamespace(frame_path=lambda frame: str(renders / f"shot_{frame:04d}.exr")))
    for n, src in ((1, "cornell-spp8.exr"), (2, "shadow-spp8.exr")):
        shutil.copy(FRAMES / src, renders / f"shot_{n:04d}.exr")
        scene.frame_current = n
        for h in bpy.app.handlers.render_write:
            h(scene)
    for h in bpy.app.handlers.render_complete:
        h(scene)
    assert "2 of 2 frames denoised" in capsys.readouterr().err
    assert sorted(p.name for p in renders.glob("*denoised*")) == ["shot_denoised_0001.exr", "shot_denoised_0002.exr"]
    handler._pool.shutdown()

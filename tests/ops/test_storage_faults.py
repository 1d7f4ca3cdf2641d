"""Storage faults against a real daemon (docs/reliability.md, "Storage faults"): the job
database lost or damaged after SIGKILL, the data directory moved away while running, a
full disk during record and result writes, a file system turned read-only mid-run, and a
second daemon on the same data directory.

Each test prints one `storage-faults:` JSON line with the jobs accepted and how many reached
their expected final state (`pytest -s` shows them). The full-disk and read-only cases
mount a small tmpfs and are skipped, saying so, where the test cannot mount one (not root,
no CAP_SYS_ADMIN).
"""

from __future__ import annotations

import contextlib
import json
import signal
import socket
import subprocess
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from conftest import FRAMES, Daemon

FRAME = (FRAMES / "cornell-spp8.exr").read_bytes()
SLOW = ("--debug-tile-delay", "150ms", "--storage-check-interval", "300ms")


def report(case: str, **figures):
    print(f"storage-faults: {json.dumps({'case': case, **figures})}")


def request(d: Daemon, method: str, path: str, body: bytes | None = None):
    req = urllib.request.Request(d.url + path, data=body, method=method)
    req.add_header("Authorization", f"Bearer {d.token}")
    if body is not None:
        req.add_header("Content-Type", "image/x-exr")
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as e:
        return e.code, dict(e.headers), e.read()


def submit(d: Daemon) -> tuple[int, dict, dict]:
    status, headers, body = request(d, "POST", "/v1/jobs", FRAME)
    return status, headers, json.loads(body or b"{}")


def submit_ok(d: Daemon) -> str:
    status, _, job = submit(d)
    assert status == 202, job
    return job["id"]


def state(d: Daemon, jid: str) -> str | None:
    status, _, body = request(d, "GET", f"/v1/jobs/{jid}")
    return json.loads(body)["state"] if status == 200 else None


def wait_for(what: str, check, timeout: float = 60.0):
    t = time.monotonic()
    last = None
    while time.monotonic() - t < timeout:
        last = check()
        if last:
            return last
        time.sleep(0.1)
    raise AssertionError(f"{what}: not within {timeout} s (last: {last!r})")


def wait_states(d: Daemon, ids: list[str], states: set[str], timeout: float = 120.0) -> dict[str, str]:
    def check():
        now = {i: state(d, i) for i in ids}
        return now if all(s in states for s in now.values()) else None

    return wait_for(f"jobs reaching {states}", check, timeout)


def readiness(d: Daemon) -> tuple[int, dict]:
    try:
        with urllib.request.urlopen(d.url + "/readyz", timeout=2) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def sigkill(d: Daemon):
    d.proc.send_signal(signal.SIGKILL)
    d.proc.wait()
    d.log.close()


def files_under(root: Path) -> set[str]:
    """The files under root, less the storage health check's probe (`HEALTH_PROBE` in
    src/jobs/health.rs: written and removed every few seconds in jobs/, and left behind
    when a kill lands mid-check)."""
    return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file() and not p.name.startswith(".health-probe")}


@contextlib.contextmanager
def tmpfs(path: Path, size: str):
    path.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.decode().strip()}): needs root or CAP_SYS_ADMIN")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def fill(path: Path) -> Path:
    """Writes `path` until the file system is full."""
    chunk = b"\0" * (1 << 20)
    with open(path, "wb", buffering=0) as f:
        while True:
            try:
                f.write(chunk)
            except OSError:
                break
        for small in (1 << 16, 1 << 12, 1):
            while True:
                try:
                    f.write(b"\0" * small)
                except OSError:
                    break
    return path


@pytest.mark.parametrize("damage", ["deleted", "emptied", "truncated"])
def test_a_lost_or_damaged_database_after_sigkill_is_rebuilt_and_nothing_is_deleted(tmp_path, damage):
    d = Daemon(tmp_path / "first", *SLOW)
    finished = [submit_ok(d) for _ in range(2)]
    wait_states(d, finished, {"succeeded"})
    pending = [submit_ok(d) for _ in range(3)]  # one running, two queued when the kill lands
    wait_for("a job running", lambda: any(state(d, i) == "running" for i in pending))
    results = {i: request(d, "GET", f"/v1/jobs/{i}/result")[2] for i in finished}
    sigkill(d)
    jobs = d.data / "jobs"
    before = files_under(jobs)
    db = d.data / "jobs.redb"
    if damage == "deleted":
        db.unlink()
    elif damage == "emptied":
        db.write_bytes(b"")
    else:
        with open(db, "r+b") as f:
            f.truncate(db.stat().st_size // 2)

    d2 = Daemon(tmp_path / "second", data=d.data)
    try:
        accepted = finished + pending
        for i in accepted:
            assert state(d2, i) is not None, f"{i} forgotten after the database was {damage}"
        states = wait_states(d2, accepted, {"succeeded"})
        for i in finished:
            assert request(d2, "GET", f"/v1/jobs/{i}/result")[2] == results[i], "a finished result changed"
        # Only what a run consumes goes: the inputs of jobs that have now finished.
        gone = {f for f in before - files_under(jobs) if not f.endswith(("input.exr", ".part"))}
        assert not gone, f"files deleted: {sorted(gone)}"
        assert not (d.data / "quarantine").exists(), "nothing needed quarantine"
        report(f"database {damage} after SIGKILL", accepted=len(accepted),
               reached_expected=sum(s == "succeeded" for s in states.values()),
               kept_aside=sorted(p.name for p in d.data.glob("jobs.redb.damaged-*")))
    finally:
        d2.stop()


def test_a_moved_or_replaced_data_directory_turns_the_daemon_unready_and_refuses_jobs(tmp_path):
    d = Daemon(tmp_path / "d", "--storage-check-interval", "300ms")
    try:
        first = submit_ok(d)
        wait_states(d, [first], {"succeeded"})
        moved = d.data.with_name("data-moved")
        d.data.rename(moved)
        status, body = wait_for("not ready after the move", lambda: (r := readiness(d))[0] == 503 and r, timeout=5)
        assert body["storage"]["ok"] is False and body["storage"]["kind"] in ("unavailable", "moved"), body
        code, headers, refused = submit(d)
        assert code == 503 and refused["error"]["code"] == "storage_unavailable", refused
        assert "Retry-After" in headers or "retry-after" in headers
        # A new, empty directory in its place is not the daemon's directory either.
        d.data.mkdir()
        status, body = wait_for("moved detected", lambda: (r := readiness(d))[1]["storage"].get("kind") == "moved" and r)
        assert submit(d)[0] == 503
        assert not (d.data / "jobs").exists(), "nothing written into the impostor"
        d.data.rmdir()
        moved.rename(d.data)
        wait_for("ready again", lambda: readiness(d)[0] == 200, timeout=5)
        again = submit_ok(d)
        states = wait_states(d, [first, again], {"succeeded"})
        report("data directory moved while running", accepted=2, refused_while_moved=2,
               reached_expected=sum(s == "succeeded" for s in states.values()))
    finally:
        d.stop()


def test_a_full_disk_refuses_new_work_requeues_the_interrupted_job_and_heals_without_restart(tmp_path):
    with tmpfs(tmp_path / "fs", "48m") as fs:
        d = Daemon(tmp_path / "d", *SLOW, "--min-free-bytes", "1048576", data=fs / "data")
        try:
            running = submit_ok(d)
            queued = submit_ok(d)
            wait_for("the first job running", lambda: state(d, running) == "running")
            filler = fill(fs / "filler")
            status, body = wait_for("not ready when full", lambda: (r := readiness(d))[0] == 503 and r, timeout=5)
            assert body["storage"]["kind"] == "full", body
            code, headers, refused = submit(d)
            assert code == 503 and refused["error"]["code"] == "storage_full", refused
            # A record write on the full disk: the cancel is refused, the job stays queued.
            code, _, body = request(d, "POST", f"/v1/jobs/{queued}/cancel")
            assert code == 503 and json.loads(body)["error"]["code"] == "storage_full", body
            assert state(d, queued) == "queued"
            # The running job's result cannot be written: it goes back to the queue.
            wait_for("the interrupted job queued again", lambda: state(d, running) == "queued", timeout=30)
            filler.unlink()
            wait_for("ready again", lambda: readiness(d)[0] == 200, timeout=5)
            after = submit_ok(d)
            states = wait_states(d, [running, queued, after], {"succeeded"})
            log = d.read_log()
            report("disk full during record and result writes", accepted=3, refused_while_full=2,
                   reached_expected=sum(s == "succeeded" for s in states.values()),
                   requeued_after_storage_fault="storage fault: queued again" in log)
        finally:
            d.stop()


def remount(path: Path, mode: str):
    """Remounts `path` read-only or read-write, retrying while a write holds it busy."""
    for _ in range(50):
        if subprocess.run(["mount", "-o", f"remount,{mode}", str(path)], capture_output=True).returncode == 0:
            return
        time.sleep(0.1)
    raise AssertionError(f"cannot remount {path} {mode}")


def test_a_read_only_file_system_never_reverses_a_final_state(tmp_path):
    # The job files on their own file system, which turns read-only mid-run (the database
    # beside it keeps its file open for writing, which a read-only remount does not allow).
    data = tmp_path / "data"
    with tmpfs(data / "jobs", "48m") as jobs:
        # The running job must outlast the remount, which waits while a write holds the file
        # system busy: with SLOW's 150 ms a job could finish first (seen once in CI) and the
        # next one start, so its tile takes 2 s here.
        d = Daemon(tmp_path / "d", "--debug-tile-delay", "2s", "--storage-check-interval", "300ms", data=data)
        running, queued, cancelled = submit_ok(d), submit_ok(d), submit_ok(d)
        wait_for("the first job running", lambda: state(d, running) == "running")
        assert request(d, "POST", f"/v1/jobs/{cancelled}/cancel")[0] == 200
        remount(jobs, "ro")
        wait_for("not ready when read-only", lambda: readiness(d)[0] == 503, timeout=5)
        code, _, body = request(d, "POST", f"/v1/jobs/{queued}/cancel")
        assert code == 503 and json.loads(body)["error"]["code"] == "storage_unavailable", body
        # The running job reaches its result write and cannot make it: queued again.
        wait_for("the interrupted job queued again", lambda: state(d, running) == "queued", timeout=30)
        shown = {i: state(d, i) for i in (running, queued, cancelled)}
        assert shown == {running: "queued", queued: "queued", cancelled: "cancelled"}, shown
        sigkill(d)
        remount(jobs, "rw")
        d2 = Daemon(tmp_path / "d2", data=data)
        try:
            states = wait_states(d2, [running, queued, cancelled], {"succeeded", "cancelled"})
            assert states == {running: "succeeded", queued: "succeeded", cancelled: "cancelled"}, states
            report("read-only file system mid-run, then repaired and restarted", accepted=3,
                   reached_expected=3, terminal_states_reversed=0)
        finally:
            d2.stop()


def test_a_second_daemon_on_the_same_data_directory_binds_nothing_and_says_why(tmp_path):
    d = Daemon(tmp_path / "d")
    try:
        second = Daemon(tmp_path / "second", data=d.data, wait=False)
        # While it waits for the lock, its ports are not bound: nothing to hang on.
        time.sleep(1)
        with pytest.raises(OSError):
            socket.create_connection(("127.0.0.1", second.http_port), timeout=1).close()
        assert second.proc.wait(30) != 0
        log = second.read_log()
        assert "in use by another mcdenoise daemon" in log and str(d.data) in log, log
        assert readiness(d)[0] == 200, "the first daemon is untouched"
        second.log.close()
    finally:
        d.stop()

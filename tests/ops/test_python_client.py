"""The Python client (clients/python) as a package and its API beyond one frame: reference
uploads, listings across pages, event streams, and refused uploads reported as the daemon's
answer. All against a real daemon (conftest.py)."""

from __future__ import annotations

import json
import os
import shutil
import socket
import struct
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest

import mcdenoise_client as mc
from conftest import FRAMES, ROOT, TOKEN

FRAME, REF = FRAMES / "cornell-spp8.exr", FRAMES / "cornell-ref.exr"


def big_frame(tmp_path, mb: int = 8) -> Path:
    """A real fixture frame padded with random bytes to `mb` MB: an upload the daemon
    refuses (wrong token, over the size limit) before reading its body."""
    p = tmp_path / f"big-{mb}mb.exr"
    with open(p, "wb") as f:
        f.write(FRAME.read_bytes())
        f.write(os.urandom(mb * 1_000_000 - FRAME.stat().st_size))
    return p


def cli(*args, timeout=120, env=None):
    return subprocess.run([sys.executable, str(ROOT / "clients" / "python" / "mcdenoise_client.py"), *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, env=env)


def metric(daemon, prefix: str) -> float:
    status, text = daemon.get("/metrics")
    assert status == 200
    return sum(float(ln.split()[-1]) for ln in text.splitlines() if ln.startswith(prefix))


# --- the package -------------------------------------------------------------------------

def test_package_installs_offline_with_its_console_script(daemon, tmp_path):
    src = tmp_path / "src"
    shutil.copytree(ROOT / "clients" / "python", src,
                    ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__", "dist"))
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True, timeout=120)
    py, env = venv / "bin" / "python", dict(os.environ, PIP_NO_INDEX="1", PIP_DISABLE_PIP_VERSION_CHECK="1")
    env.pop("PYTHONPATH", None)
    # --no-build-isolation builds with the setuptools the venv sees: the base interpreter's
    # (--system-site-packages). One without bdist_wheel (setuptools < 70.1 without `wheel`)
    # cannot build a wheel; then lend it this interpreter's setuptools.
    can_build = subprocess.run([str(py), "-c", "import importlib.util as u, sys; sys.exit(not ("
                                "u.find_spec('wheel') or u.find_spec('setuptools.command.bdist_wheel')))"],
                               timeout=60).returncode == 0
    if not can_build:
        import setuptools
        env["PYTHONPATH"] = str(Path(setuptools.__file__).parents[1])
    r = subprocess.run([str(py), "-m", "pip", "install", "--no-deps", "--no-build-isolation", "--no-index", str(src)],
                       capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 0, r.stdout + r.stderr
    env.pop("PYTHONPATH", None)
    script = venv / "bin" / "mcdenoise-client"
    assert script.is_file()
    where = subprocess.run([str(py), "-c", "import mcdenoise_client as m; print(m.__file__, m.__version__)"],
                           capture_output=True, text=True, timeout=60, cwd=tmp_path, env=env)
    assert where.returncode == 0 and str(venv) in where.stdout, where.stdout + where.stderr
    assert where.stdout.split()[1] == mc.__version__
    out = tmp_path / "out.exr"
    label = f"pkg-{uuid.uuid4().hex[:8]}"
    r = subprocess.run([str(script), "--server", daemon.url, "--token", TOKEN, "denoise", str(FRAME), "-o", str(out),
                        "--reference", str(REF), "--label", label],
                       capture_output=True, text=True, timeout=120, cwd=tmp_path, env=env)
    assert r.returncode == 0, r.stderr
    job = json.loads(r.stdout)
    assert job["state"] == "succeeded" and job["has_reference"] and out.is_file()
    assert job["metrics"]["output"]["relmse"] < job["metrics"]["input"]["relmse"]
    r = subprocess.run([str(script), "--server", daemon.url, "--token", TOKEN, "jobs", "--label", label, "--json"],
                       capture_output=True, text=True, timeout=60, env=env)
    assert r.returncode == 0, r.stderr
    assert [json.loads(ln)["id"] for ln in r.stdout.splitlines()] == [job["id"]]
    # The copied file still works on its own (no package needed).
    assert cli("--server", daemon.url, "--token", TOKEN, "job", job["id"]).returncode == 0


# --- reference uploads ---------------------------------------------------------------------

def test_reference_upload_reports_metrics(daemon, tmp_path):
    client = mc.Client(daemon.url, token=TOKEN)
    job = client.submit(FRAME, reference=REF, layers=["diffuse"], label="with-ref", priority="high")
    assert job["has_reference"] and job["layers"] == ["diffuse"] and job["label"] == "with-ref"
    assert job["priority"] == "high"
    done = client.wait(job["id"], timeout=120)
    m = done["metrics"]
    for side in ("input", "output"):
        assert set(m[side]) >= {"relmse", "dssim", "psnr", "smape"}, m
    assert m["output"]["relmse"] < 0.5 * m["input"]["relmse"], m
    # Bytes work as well as paths, and denoise() passes the reference on.
    again = client.wait(client.submit(FRAME.read_bytes(), reference=REF.read_bytes())["id"], timeout=120)
    assert again["metrics"]["output"]["relmse"] == pytest.approx(m["output"]["relmse"], rel=1e-6)
    job = client.denoise(FRAME, tmp_path / "out.exr", reference=REF)
    assert job["has_reference"] and job["metrics"] and (tmp_path / "out.exr").is_file()
    # The same frame with and without the reference are different jobs for denoise().
    plain = client.denoise(FRAME, tmp_path / "plain.exr")
    assert plain["id"] != job["id"] and not plain["has_reference"]


def test_reference_upload_is_streamed_with_its_length_up_front(tmp_path):
    # The multipart body is made of the files' chunks, never the whole files at once.
    big = big_frame(tmp_path, 3)
    ctype, length, body = mc._multipart({"label": "x"}, [("frame", big), ("reference", REF)])
    chunks = list(body())
    assert ctype.startswith("multipart/form-data; boundary=")
    assert sum(map(len, chunks)) == length
    assert max(map(len, chunks)) <= 1 << 20
    assert chunks[0].decode().count('name="options"') == 1  # options first


# --- listings ----------------------------------------------------------------------------

def test_listing_with_filters_across_pages(make_daemon):
    d = make_daemon("--debug-tile-delay", "3s")
    requests = []

    class Recording(mc.Client):
        def _open(self, method, path, *a, **kw):
            requests.append((method, path))
            return super()._open(method, path, *a, **kw)

    client = Recording(d.url, token=TOKEN)
    a = [client.submit(FRAME, label="A", priority="high" if i < 2 else "low")["id"] for i in range(5)]
    b = [client.submit(FRAME, label="B")["id"] for _ in range(2)]
    requests.clear()
    assert [j["id"] for j in client.jobs(label="A", page_size=2)] == a  # submission order
    pages = [p for m, p in requests if p.startswith("/v1/jobs?")]
    assert len(pages) == 3 and all("limit=2" in p for p in pages)
    assert sum("page_token=" in p for p in pages) == 2
    assert [j["id"] for j in client.jobs(label="A", priority="high", page_size=1)] == a[:2]
    assert [j["id"] for j in client.jobs(priority="normal")] == b
    queued = [j["id"] for j in client.jobs(state="queued", page_size=3)]
    assert len(queued) >= 5 and set(queued) <= set(a + b)  # the first one runs
    cancelled = [i for i in queued if client.cancel(i)["state"] == "cancelled"]
    assert len(cancelled) >= 4
    assert [j["id"] for j in client.jobs(state="cancelled", page_size=4) if j["id"] in cancelled] == cancelled
    assert sorted(j["id"] for j in client.jobs(page_size=1000)) == sorted(a + b)
    r = cli("--server", d.url, "--token", TOKEN, "jobs", "--label", "B", "--page-size", "1")
    assert r.returncode == 0, r.stderr
    assert [ln.split("\t")[:2] for ln in r.stdout.splitlines()] == [[i, client.job(i)["state"]] for i in b]
    with pytest.raises(mc.DaemonError) as e:
        list(client.jobs(page_size=0))
    assert e.value.status == 400


# --- events --------------------------------------------------------------------------------

def test_event_stream_reaches_a_terminal_event(make_daemon):
    d = make_daemon("--debug-tile-delay", "500ms")
    client = mc.Client(d.url, token=TOKEN)
    first = client.submit(FRAME)
    second = client.submit(FRAME, reference=REF)  # queued behind the first
    events = list(client.events(second["id"]))
    names = [e.event for e in events]
    assert names[0] == "queued" and events[0].data["id"] == second["id"]
    assert "started" in names and "progress" in names, names
    assert names[-1] == "succeeded" and names.count("succeeded") == 1
    last = events[-1].data
    assert last["state"] == "succeeded" and last["timings_ms"]["total"] > 0 and last["metrics"]
    assert all(e.data["tiles_done"] <= e.data["tiles_total"] for e in events if e.event == "progress")
    # A finished job's stream is its terminal event alone.
    assert [e.event for e in client.events(first["id"])] == ["succeeded"]
    # The command line prints them and exits 0 for a job that succeeded, 1 otherwise.
    r = cli("--server", d.url, "--token", TOKEN, "events", second["id"])
    assert r.returncode == 0 and r.stdout.splitlines()[-1].startswith("succeeded {"), r.stdout + r.stderr
    client.submit(FRAME)  # runs while the next one waits
    slow = client.submit(FRAME)
    assert client.cancel(slow["id"])["state"] == "cancelled"
    r = cli("--server", d.url, "--token", TOKEN, "events", slow["id"])
    assert r.returncode == 1 and r.stdout.splitlines()[-1].startswith("cancelled {"), r.stdout
    with pytest.raises(mc.JobFailed) as e:
        client.wait(slow["id"])
    assert e.value.job["state"] == "cancelled"
    with pytest.raises(mc.DaemonError) as e:
        list(client.events("no-such-job"))
    assert e.value.status == 404


def test_wait_follows_events_and_survives_broken_streams(make_daemon):
    d = make_daemon("--debug-tile-delay", "2s")
    opened = []

    class Flaky(mc.Client):
        """An event stream that breaks after its first event, once."""
        breaks = 1

        def events(self, job_id, **kw):
            opened.append(job_id)
            for ev in super().events(job_id, **kw):
                yield ev
                if self.breaks:
                    self.breaks -= 1
                    raise ConnectionResetError("the stream broke (test)")

    client = Flaky(d.url, token=TOKEN)
    seen = []
    job = client.submit(FRAME)
    done = client.wait(job["id"], timeout=120, on_progress=lambda j: seen.append(j["state"]))
    assert done["state"] == "succeeded" and done["timings_ms"]
    assert len(opened) == 2, opened  # a broken stream, then one to the end
    assert seen[-1] == "succeeded" and set(seen) <= {"queued", "running", "succeeded"}

    class Broken(mc.Client):
        def events(self, job_id, **kw):
            opened.append(job_id)
            raise ConnectionResetError("no streams here (test)")
            yield  # pragma: no cover

    opened.clear()
    client = Broken(d.url, token=TOKEN)
    done = client.wait(client.submit(FRAME)["id"], timeout=120, poll=0.2)
    assert done["state"] == "succeeded"
    assert len(opened) == 3  # then it polls
    # The default client waits through events, not by polling the job.
    before_get = metric(d, 'mcdenoise_http_requests_total{route="/v1/jobs/{id}",')
    before_events = metric(d, 'mcdenoise_http_requests_total{route="/v1/jobs/{id}/events",')
    plain = mc.Client(d.url, token=TOKEN)
    plain.wait(plain.submit(FRAME)["id"], timeout=120)
    assert metric(d, 'mcdenoise_http_requests_total{route="/v1/jobs/{id}",') == before_get
    assert metric(d, 'mcdenoise_http_requests_total{route="/v1/jobs/{id}/events",') == before_events + 1
    # A deadline is kept while the stream is quiet.
    plain.submit(FRAME)
    slow = plain.submit(FRAME)
    t = time.monotonic()
    with pytest.raises(TimeoutError):
        plain.wait(slow["id"], timeout=0.5)
    assert time.monotonic() - t < 10
    plain.cancel(slow["id"])


# --- refused uploads -----------------------------------------------------------------------

def test_wrong_token_on_a_large_upload_is_401_at_once(daemon, tmp_path):
    big = big_frame(tmp_path)
    retries = []
    client = mc.Client(daemon.url, token="wrong", on_retry=lambda r, w: retries.append(r))
    for kw in ({}, {"reference": big}):
        t = time.monotonic()
        with pytest.raises(mc.DaemonError) as e:
            client.submit(big, **kw)
        assert time.monotonic() - t < 20
        assert (e.value.status, e.value.code) == (401, "unauthenticated"), e.value
    # 401 is never retried, whatever the request.
    with pytest.raises(mc.DaemonError) as e:
        client.job("anything")
    assert e.value.status == 401
    assert retries == []
    t = time.monotonic()
    r = cli("--server", daemon.url, "--token", "wrong", "denoise", big, "-o", tmp_path / "out.exr", timeout=60)
    assert r.returncode == 1 and "401 unauthenticated" in r.stderr, r.stderr
    assert "retrying" not in r.stderr and time.monotonic() - t < 20
    assert not (tmp_path / "out.exr").exists()


def test_upload_over_the_size_limit_is_413_at_once(make_daemon, tmp_path):
    d = make_daemon("--max-body-bytes", "1000000")
    retries = []
    client = mc.Client(d.url, token=TOKEN, on_retry=lambda r, w: retries.append(r))
    t = time.monotonic()
    with pytest.raises(mc.DaemonError) as e:
        client.submit(big_frame(tmp_path))
    assert (e.value.status, e.value.code) == (413, "too_large") and time.monotonic() - t < 20
    assert retries == []


class ClosingProxy:
    """A TCP proxy in front of the daemon that makes it behave as a daemon that does not
    read a refused upload's body: for a request with a body over 1 MB, mode "close" passes
    on the daemon's early answer and then resets the connection (as the kernel does when a
    socket is closed with unread data), mode "reset" resets the connection after the
    request head, before any answer (the answer lost with the connection). Other requests
    pass through."""

    def __init__(self, upstream_url: str, mode: str):
        self.upstream = upstream_url.rsplit(":", 1)[1]
        self.mode = mode
        self.uploads = 0
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(16)
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}"
        threading.Thread(target=self._accept, daemon=True).start()

    def close(self):
        self.sock.close()

    def _accept(self):
        while True:
            try:
                c, _ = self.sock.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(c,), daemon=True).start()

    def _serve(self, c):
        u = socket.create_connection(("127.0.0.1", int(self.upstream)))
        try:
            head = b""
            while b"\r\n\r\n" not in head:
                data = c.recv(65536)
                if not data:
                    return
                head += data
            lines = head.split(b"\r\n\r\n")[0].split(b"\r\n")[1:]
            length = max([int(v) for k, _, v in (ln.partition(b":") for ln in lines)
                          if k.strip().lower() == b"content-length"] or [0])
            u.sendall(head)
            if length <= 1_000_000:
                threading.Thread(target=self._pump, args=(u, c), daemon=True).start()
                self._pump(c, u)
                return
            self.uploads += 1
            if self.mode == "close":
                u.settimeout(10)
                c.sendall(u.recv(65536))  # the daemon answers before reading the body
                time.sleep(0.05)
            c.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        except OSError:
            pass
        finally:
            c.close()
            u.close()

    @staticmethod
    def _pump(a, b):
        try:
            while True:
                data = a.recv(65536)
                if not data:
                    break
                b.sendall(data)
            b.shutdown(socket.SHUT_WR)
        except OSError:
            pass


@pytest.mark.parametrize("mode", ["close", "reset"])
def test_refused_upload_on_a_closed_connection_is_the_daemons_answer(daemon, tmp_path, monkeypatch, mode):
    # The daemon answers 401 and the connection is reset while the client still sends:
    # the client reads the answer after the failed send ("close"), or, when it was lost
    # ("reset"), learns it from an authenticated probe; either way 401, not a broken pipe.
    # The client's check for an early answer between chunks is off, as when the answer
    # arrives just after it.
    monkeypatch.setattr(mc, "_readable", lambda sock: False)
    proxy = ClosingProxy(daemon.url, mode)
    try:
        big = big_frame(tmp_path)
        retries = []
        t = time.monotonic()
        with pytest.raises(mc.DaemonError) as e:
            mc.Client(proxy.url, token="wrong", on_retry=lambda r, w: retries.append(r)).submit(big)
        assert (e.value.status, e.value.code) == (401, "unauthenticated") and time.monotonic() - t < 20
        assert retries == [] and proxy.uploads == 1
        if mode == "reset":
            assert isinstance(e.value.__cause__, ConnectionError)
            # With a good token the probe passes: the broken connection is retried as one.
            retries.clear()
            with pytest.raises(ConnectionError):
                mc.Client(proxy.url, token=TOKEN, retry_timeout=1.5,
                          on_retry=lambda r, w: retries.append(r)).submit(big)
            assert retries and proxy.uploads >= 2
    finally:
        proxy.close()


def test_requests_go_through_the_environments_proxy(daemon, monkeypatch):
    # As with urllib: http_proxy is used, no_proxy bypasses it. The daemon itself stands in
    # for the proxy (it takes absolute-form request targets); the server's name does not
    # resolve, so only a request through the proxy can reach it.
    for var in ("no_proxy", "NO_PROXY", "HTTP_PROXY"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("http_proxy", daemon.url)
    client = mc.Client("http://mcdenoise.invalid:8080", token=TOKEN, retry_timeout=0)
    job = client.submit(FRAME, label="via-proxy")
    assert client.job(job["id"])["label"] == "via-proxy"
    monkeypatch.setenv("no_proxy", "mcdenoise.invalid")
    with pytest.raises(OSError):
        client.job(job["id"])

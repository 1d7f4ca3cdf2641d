"""Shared by the deploy and client tests: paths, and a real daemon (target/release/mcdenoise
serve with the shipped models) on free loopback ports with a temporary data directory.

The binary comes from MCDENOISE_BIN (set by the Makefile), else target/release/mcdenoise;
the ONNX Runtime library from ORT_DYLIB_PATH, else $MCDENOISE_HOME/lib (scripts/setup).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FRAMES = ROOT / "tests" / "fixtures" / "frames"
VENV_BIN = Path(sys.executable).parent
TOKEN = "ops-test-token"

sys.path.insert(0, str(ROOT / "clients" / "python"))
sys.path.insert(0, str(ROOT / "examples" / "farm"))


def mcdenoise_bin() -> Path:
    p = Path(os.environ.get("MCDENOISE_BIN", ROOT / "target" / "release" / "mcdenoise"))
    assert p.is_file(), f"{p} is missing: build it first (make build)"
    return p


def ort_library() -> str:
    lib = os.environ.get("ORT_DYLIB_PATH") or str(
        Path(os.environ.get("MCDENOISE_HOME", Path.home() / ".cache" / "mcdenoise")) / "lib" / "libonnxruntime.so.1.31.1"
    )
    assert Path(lib).is_file(), f"{lib} is missing: run scripts/setup"
    return lib


def free_ports(n: int) -> list[int]:
    """`n` distinct free ports: the sockets are held open together while the ports are
    chosen (one at a time, a port just released can be handed out again)."""
    sockets = [socket.socket() for _ in range(n)]
    try:
        for s in sockets:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


def free_port() -> int:
    return free_ports(1)[0]


class Daemon:
    def __init__(self, tmp: Path, *extra: str, token: str | None = TOKEN, wait: bool = True, data: Path | None = None):
        tmp.mkdir(parents=True, exist_ok=True)
        self.data = data or tmp / "data"
        self.http_port, self.grpc_port = free_ports(2)
        self.url = f"http://127.0.0.1:{self.http_port}"
        self.token = token
        self.log = open(tmp / "daemon.log", "wb")
        env = dict(os.environ, ORT_DYLIB_PATH=ort_library())
        env.pop("MCDENOISE_AUTH_TOKENS", None)
        args = [str(mcdenoise_bin()), "serve", "--http", f"127.0.0.1:{self.http_port}",
                "--grpc", f"127.0.0.1:{self.grpc_port}", "--data-dir", str(self.data),
                "--models", str(ROOT / "models"), "--workers", "1", "--threads-per-worker", "1",
                "--tile", "32", "--log", "warn", *extra]
        if token:
            args += ["--auth-token", token]
        self.proc = subprocess.Popen(args, env=env, stdout=self.log, stderr=subprocess.STDOUT)
        if wait:
            self.wait_ready()

    def wait_ready(self, timeout: float = 60.0):
        t = time.monotonic()
        while time.monotonic() - t < timeout:
            assert self.proc.poll() is None, f"the daemon exited: {self.read_log()}"
            try:
                with urllib.request.urlopen(self.url + "/readyz", timeout=2):
                    return
            except (urllib.error.URLError, OSError):
                time.sleep(0.1)
        raise AssertionError(f"the daemon did not become ready: {self.read_log()}")

    def read_log(self) -> str:
        self.log.flush()
        return Path(self.log.name).read_text(errors="replace")[-4000:]

    def get(self, path: str, token: str | None = None) -> tuple[int, str]:
        req = urllib.request.Request(self.url + path)
        if token or self.token:
            req.add_header("Authorization", f"Bearer {token or self.token}")
        try:
            with urllib.request.urlopen(req, timeout=10) as r:
                return r.status, r.read().decode()
        except urllib.error.HTTPError as e:
            return e.code, e.read().decode()

    def stop(self):
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()


@pytest.fixture(scope="session")
def daemon(tmp_path_factory):
    d = Daemon(tmp_path_factory.mktemp("daemon"))
    yield d
    d.stop()


@pytest.fixture()
def make_daemon(tmp_path):
    started = []

    def start(*extra, token=TOKEN, wait=True):
        d = Daemon(tmp_path / f"d{len(started)}", *extra, token=token, wait=wait)
        started.append(d)
        return d

    yield start
    for d in started:
        d.stop()

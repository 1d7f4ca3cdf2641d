"""The web dashboard in a real browser against a real daemon: Debian's chromium, headless,
driven by playwright-core from npm (both installed by scripts/setup test; playwright-core
into $MCDENOISE_HOME/node from tests/ops/browser/package-lock.json, never with a browser of
its own). browser/dashboard.mjs opens the page, is refused without a token and with a wrong
one, signs in, submits fixture frames through the API, watches one reach done in the
queue, filters by label, deletes a job, moves the before/after slider, changes exposure and
view, zooms to 1:1 and back, opens the metrics, reads a failed job's error, and visits the
models and daemon pages, taking screenshots; every request the page makes is intercepted
and must go to the daemon itself.

With MCDENOISE_SCREENSHOTS=DIR the screenshots are also copied there (docs/img is made so).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from conftest import FRAMES, ROOT, Daemon

HERE = Path(__file__).parent
OPERATOR = "ops-dashboard-operator"
HOME = Path(os.environ.get("MCDENOISE_HOME", Path.home() / ".cache" / "mcdenoise"))
PLAYWRIGHT = HOME / "node" / "node_modules" / "playwright-core"
SHOTS = ["dashboard-queue.png", "dashboard-job.png", "dashboard-models.png", "dashboard-daemon.png", "dashboard-login.png"]


def browser_tools() -> tuple[str, str]:
    """node and chromium, or a skip naming what is missing and how to get it."""
    node = shutil.which("node")
    chromium = shutil.which("chromium") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").is_file() else None)
    missing = []
    if not node:
        missing.append("node (Debian: apt-get install nodejs npm)")
    if not chromium:
        missing.append("chromium (Debian: apt-get install chromium)")
    if not (PLAYWRIGHT / "package.json").is_file():
        missing.append(f"playwright-core in {PLAYWRIGHT.parent} (scripts/setup test)")
    if missing:
        pytest.skip("the browser test needs " + ", ".join(missing))
    return node, chromium


def test_the_dashboard_in_headless_chromium(tmp_path):
    node, chromium = browser_tools()
    d = Daemon(tmp_path / "daemon", "--operator-token", OPERATOR)
    shots = tmp_path / "shots"
    shots.mkdir()
    try:
        env = dict(os.environ, DAEMON_URL=d.url, TOKEN=OPERATOR, FRAMES=str(FRAMES), OUT=str(shots),
                   CHROMIUM=chromium, PLAYWRIGHT=str(PLAYWRIGHT))
        r = subprocess.run([node, str(HERE / "browser" / "dashboard.mjs")], env=env, capture_output=True,
                           text=True, timeout=300, cwd=tmp_path)
        assert r.returncode == 0, f"{r.stdout[-4000:]}\n{r.stderr[-4000:]}\n{d.read_log()}"
        findings = json.loads(r.stdout.strip().splitlines()[-1])
    finally:
        d.stop()
    assert findings["ok"]
    assert findings["unauthenticated_status"] == 401
    assert findings["outside"] == []
    assert findings["requests"] > 20
    assert findings["slider"] == "30%"
    assert findings["models"] >= 2
    for name in SHOTS:
        png = (shots / name).read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000, name
    if os.environ.get("MCDENOISE_SCREENSHOTS"):
        dest = Path(os.environ["MCDENOISE_SCREENSHOTS"])
        dest.mkdir(parents=True, exist_ok=True)
        for name in SHOTS:
            shutil.copyfile(shots / name, dest / name)


def test_the_page_and_its_files_are_served_with_their_policy(daemon):
    """The shell needs no token and holds no data; every file of the page names nothing
    outside the daemon, and the API it calls refuses it without a token."""
    import urllib.request

    for path in ["/", "/ui/app.js", "/ui/app.css", "/ui/icon.svg"]:
        with urllib.request.urlopen(daemon.url + path, timeout=10) as resp:
            body = resp.read().decode()
            csp = resp.headers["Content-Security-Policy"]
        assert "default-src 'none'" in csp and "connect-src 'self'" in csp, path
        assert "http://" not in body.replace("http://www.w3.org/2000/svg", "") and "https://" not in body, path
    status, _ = daemon.get("/v1/jobs", token="wrong-token")
    assert status == 401

"""The daemon driven from its own OpenAPI document by Schemathesis, a property-based API
tester: every operation with generated valid and invalid requests (examples, coverage,
fuzzing and the stateful phase, which follows the document's links from a created job to
its operations), every check (no server error, documented status codes, content types,
headers and response schemas, invalid requests refused, valid ones accepted), no failure.
The one exception is in schemathesis.toml beside this file, with its reason."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import json
import urllib.request

from conftest import ROOT, Daemon

HERE = Path(__file__).parent


def test_the_daemon_keeps_its_api_document(tmp_path):
    d = Daemon(tmp_path, token=None)
    try:
        # Real jobs, so that the operations on a job's id reach more than 404 (generated
        # bodies are not OpenEXR frames and never create one): one for deleteJob, which
        # removes it, one for every other operation.
        frame = (ROOT / "tests/fixtures/frames/cornell-spp8.exr").read_bytes()

        def submit() -> str:
            req = urllib.request.Request(d.url + "/v1/jobs", data=frame, headers={"Content-Type": "image/x-exr"})
            with urllib.request.urlopen(req, timeout=30) as r:
                return json.load(r)["id"]

        kept, deleted = submit(), submit()
        config = tmp_path / "schemathesis.toml"
        config.write_text((HERE / "schemathesis.toml").read_text()
                          + f'\n[parameters]\n"path.id" = "{kept}"\n'
                          + f'\n[[operations]]\ninclude-operation-id = "deleteJob"\n'
                          + f'parameters = {{ "path.id" = "{deleted}" }}\n')
        st = Path(sys.executable).parent / "st"
        cmd = [str(st), "--config-file", str(config), "--no-color", "run",
               f"{d.url}/v1/openapi.json", "--max-examples", "25", "--seed", "1",
               "--workers", "1", "--request-timeout", "20"]
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=tmp_path)
        summary = r.stdout[-8000:]
        assert r.returncode == 0, summary
        assert "Tested: 14" in summary, summary
        assert "Missing test data" not in summary, summary
    finally:
        d.stop()

"""The set-up is split by need (scripts/setup serve|train|test): serving takes only the ONNX
Runtime library (with OpenVINO's provider plugin), never the training environment (torch, Mitsuba: about 5 GB). Checked
offline: the make targets' dry runs, and scripts/setup serve against stubbed tools and a
local package index."""

from __future__ import annotations

import http.server
import os
import re
import shutil
import subprocess
import threading

import pytest

from conftest import ROOT, ort_library
from test_dockerfile import instructions, stages

WHEEL = "onnxruntime-1.31.1-cp311-cp311-manylinux_2_28_x86_64.whl"
TRAINING = re.compile(r"pip3? install|requirements|python3? -m venv|/venv/|apt-get|libllvm|setup-bpy|scripts/setup( (train|test))?\s*$")


def dry_run(target: str, home) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MFLAGS", "MAKELEVEL")}
    env["MCDENOISE_HOME"] = str(home)
    r = subprocess.run(["make", "-n", "--no-print-directory", target], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stdout.splitlines()


def recipes() -> dict[str, str]:
    """Each Makefile target and its recipe (continuation lines joined)."""
    out, target = {}, None
    for line in (ROOT / "Makefile").read_text().splitlines():
        m = re.match(r"^([\w.-]+):(?!=)", line)
        if m:
            target = m.group(1)
            out.setdefault(target, "")
        elif line.startswith("\t") and target:
            out[target] += line + "\n"
        elif not line.startswith(" "):
            target = None
    return {t: r for t, r in out.items() if not t.startswith(".")}


def test_make_serve_sets_up_only_the_onnx_runtime_library(tmp_path):
    lines = dry_run("serve", tmp_path / "home")
    assert lines[0] == "bash scripts/setup serve", lines
    assert lines[1] == "bash scripts/build-release", lines
    assert lines[2].endswith("/target/release/mcdenoise serve --models models"), lines
    assert not [l for l in lines if TRAINING.search(l)], lines


def test_every_target_sets_up_what_its_recipe_needs(tmp_path):
    """A recipe that runs the project's Python ($(PY)) sets up the training environment;
    one that runs the engine (the daemon, cargo test/bench, the fuzzers) at least the
    ONNX Runtime library; `make test` everything, the deploy checks' tools included."""
    rules = recipes()
    python = {t for t, r in rules.items() if "$(PY)" in r}
    engine = {t for t, r in rules.items() if re.search(r"\$\(MCDENOISE_BIN\)|cargo (test|bench|\+nightly fuzz)", r)}
    assert {"test", "dataset", "datagen-timing", "fixtures", "train", "eval", "bench", "ablation", "train-ms"} <= python
    assert {"serve", "test", "bench", "reliability", "fuzz", "fuzz-cmin"} <= engine
    for t in sorted(python | engine):
        lines = dry_run(t, tmp_path / "home")
        setups = [l for l in lines if l.startswith("bash scripts/setup")]
        assert len(setups) == 1, (t, lines)
        want = {"bash scripts/setup train", "bash scripts/setup test"} if t in python else {
            "bash scripts/setup serve", "bash scripts/setup train", "bash scripts/setup test"}
        assert setups[0] in want, (t, setups)
    assert [l for l in dry_run("test", tmp_path / "home") if "scripts/setup" in l] == ["bash scripts/setup test"]
    assert dry_run("setup", tmp_path / "home") == ["bash scripts/setup test"]
    # Building needs only Rust.
    assert dry_run("build", tmp_path / "home") == ["bash scripts/build-release"]


def stub_tools(tmp_path):
    """A PATH directory whose python, pip, apt-get, ldconfig and cargo only record that they
    were called, and fail."""
    stubs, log = tmp_path / "stubs", tmp_path / "calls.log"
    stubs.mkdir()
    for name in ["python", "python3", "python3.11", "pip", "pip3", "apt-get", "ldconfig", "cargo"]:
        (stubs / name).write_text(f'#!/bin/sh\necho "{name} $*" >> {log}\nexit 97\n')
        (stubs / name).chmod(0o755)
    return f"{stubs}:{os.environ['PATH']}", log


def files_under(path) -> list[str]:
    return sorted(str(p.relative_to(path)) for p in path.rglob("*"))


def library_in_place(home):
    """The library and OpenVINO's plugin as `scripts/install-ort` left them, copied from this
    machine's set-up into `home`."""
    (home / "lib").mkdir(parents=True)
    shutil.copy(ort_library(), home / "lib" / "libonnxruntime.so.1.31.1")
    shutil.copytree(os.path.join(os.path.dirname(ort_library()), "openvino"), home / "lib" / "openvino")


def test_setup_serve_with_the_library_in_place_does_nothing_else(tmp_path):
    home = tmp_path / "home"
    library_in_place(home)
    installed = files_under(home)
    assert "lib/openvino/SHA256SUMS" in installed and "lib/libonnxruntime.so.1.31.1" in installed
    path, log = stub_tools(tmp_path)
    env = dict(os.environ, MCDENOISE_HOME=str(home), PATH=path)
    env.pop("PYTHON", None)
    for _ in range(2):  # idempotent
        r = subprocess.run(["bash", str(ROOT / "scripts" / "setup"), "serve"], env=env, capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        assert "ready: ORT library" in r.stderr
        assert not log.exists(), log.read_text()
        assert files_under(home) == installed


def test_setup_train_with_everything_in_place_does_nothing_else(tmp_path):
    """With the library, an environment whose stamp matches the requirements and libllvm19
    in ldconfig's list, `scripts/setup train` runs neither pip nor apt-get, however long
    the list: the check reads all of it (a grep that stopped at the first match left
    ldconfig writing into a closed pipe, which pipefail took for a missing library)."""
    import hashlib

    home = tmp_path / "home"
    library_in_place(home)
    venv_bin = home / "venv" / "bin"
    venv_bin.mkdir(parents=True)
    for tool in ["python", "pip"]:
        (venv_bin / tool).write_text(f'#!/bin/sh\necho "venv {tool} $*" >> {tmp_path / "calls.log"}\nexit 97\n')
        (venv_bin / tool).chmod(0o755)
    reqs = b"".join((ROOT / "training" / f).read_bytes() for f in ["requirements.txt", "requirements-nodeps.txt"])
    (home / "venv" / ".requirements.sha256").write_text(hashlib.sha256(reqs).hexdigest() + "\n")
    path, log = stub_tools(tmp_path)
    stubs = path.split(":")[0]
    # ldconfig -p as on a Debian machine: the library early in a list of thousands of lines.
    (tmp_path / "ldconfig.txt").write_text(
        "\tlibLLVM.so.19.1 (libc6,x86-64) => /lib/x86_64-linux-gnu/libLLVM.so.19.1\n"
        + "".join(f"\tlibx{i}.so.1 (libc6,x86-64) => /lib/x86_64-linux-gnu/libx{i}.so.1\n" for i in range(20000)))
    with open(os.path.join(stubs, "ldconfig"), "w") as f:
        f.write(f"#!/bin/sh\ncat {tmp_path / 'ldconfig.txt'}\n")
    env = dict(os.environ, MCDENOISE_HOME=str(home), PATH=path)
    for _ in range(2):
        r = subprocess.run(["bash", str(ROOT / "scripts" / "setup"), "train"], env=env, capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        assert "ready: ORT library" in r.stderr and "installing" not in r.stderr, r.stderr
        assert not log.exists(), log.read_text()


class Index(http.server.BaseHTTPRequestHandler):
    """A package index with one (wrong) onnxruntime wheel: /simple/onnxruntime/ links to it."""

    requests: list[str] = []

    def do_GET(self):
        Index.requests.append(self.path)
        if self.path == "/simple/onnxruntime/":
            body = (f'<html><body><a href="../../files/{WHEEL}#sha256=00">{WHEEL}</a>'
                    f'<a href="../../files/onnxruntime-1.31.1.tar.gz">sdist</a></body></html>').encode()
        elif self.path == f"/files/{WHEEL}":
            body = b"PK\x05\x06" + b"\0" * 18  # an empty zip, not the pinned wheel
        else:
            self.send_error(404)
            return
        self.send_response(200)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


@pytest.fixture
def index():
    Index.requests = []
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Index)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{server.server_address[1]}/simple"
    server.shutdown()
    server.server_close()


def test_setup_serve_on_a_fresh_home_fetches_the_wheel_without_pip_or_a_venv(tmp_path, index):
    """A Python without pip (Debian's python3 without python3-pip) is enough: install-ort
    finds the wheel on the index's simple page, downloads it with urllib and checks its
    sha256 (which this index's wheel fails). No environment is created."""
    nopip = tmp_path / "nopip"
    subprocess.run(["python3", "-m", "venv", "--without-pip", str(nopip)], check=True, timeout=60)
    home = tmp_path / "home"
    path, log = stub_tools(tmp_path)
    env = {k: v for k, v in os.environ.items() if "proxy" not in k.lower()}
    env.update(MCDENOISE_HOME=str(home), PATH=path, PYTHON=str(nopip / "bin" / "python"), PIP_INDEX_URL=index)
    r = subprocess.run(["bash", str(ROOT / "scripts" / "setup"), "serve"], env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode != 0
    assert "has no pip" in r.stderr and f"{WHEEL}: sha256 " in r.stderr and "expected 5752bd50" in r.stderr, r.stderr
    assert Index.requests == ["/simple/onnxruntime/", f"/files/{WHEEL}"]
    assert not log.exists(), log.read_text()
    assert files_under(home) == ["lib"]


def test_the_image_takes_only_what_serving_needs():
    """The Dockerfile runs install-ort and build-release, never the training set-up; each
    image (the default `cpu` and `gpu`: the `runtime` stage and their own) holds its
    library, the binary, the healthcheck and the models."""
    ins = instructions()
    runs = " ".join(r for i, r in ins if i == "RUN")
    assert "scripts/install-ort" in runs and "scripts/build-release" in runs
    assert not re.search(r"scripts/setup|requirements|pip install|torch|mitsuba", runs, re.I), runs
    all_stages = stages()

    def copied(stage: str) -> list:
        """COPY sources of a stage, after those of the stage it is built FROM."""
        base = all_stages[stage][0][1].split()[0]
        own = [r.split()[-2] for i, r in all_stages[stage] if i == "COPY"]
        return (copied(base) if base in all_stages else []) + own

    serving = ["/out/bin/mcdenoise", "scripts/healthcheck", "models/full", "models/nocov", "models/lin2020",
               "models/lin2020-narrow", "models/beauty", "models/MODEL_CARD.md"]
    assert list(all_stages)[-1] == "cpu"
    assert copied("cpu") == [*serving, "/out/lib/libonnxruntime.so.1.31.1", "/out/lib/openvino/"], copied("cpu")
    assert copied("gpu") == [*serving, "/out/lib/"], copied("gpu")

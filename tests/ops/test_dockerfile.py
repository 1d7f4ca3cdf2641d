"""The Dockerfile without a container engine: hadolint, and the steps it runs (the shared
scripts) run here: scripts/install-ort, scripts/healthcheck, the image's defaults."""

from __future__ import annotations

import fnmatch
import hashlib
import os
import re
import shlex
import subprocess

import pytest

from conftest import ROOT, VENV_BIN, Daemon, mcdenoise_bin, free_port

DOCKERFILE = ROOT / "Dockerfile"


def instructions():
    """(INSTRUCTION, arguments) of the Dockerfile, continuation lines joined."""
    text = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def env_defaults() -> dict:
    """ENV of the runtime stage (the last FROM)."""
    env = {}
    for ins, rest in instructions():
        if ins == "FROM":
            env = {}
        if ins == "ENV":
            for tok in shlex.split(rest):
                k, _, v = tok.partition("=")
                env[k] = v
    return env


def serve_env_vars() -> set:
    help_text = subprocess.run([str(mcdenoise_bin()), "serve", "--help"], capture_output=True, text=True, check=True).stdout
    return set(re.findall(r"\[env: ([A-Z_]+)[=\]]", help_text))


def test_hadolint_passes():
    hadolint = VENV_BIN / "hadolint"
    assert hadolint.is_file(), "hadolint missing: scripts/setup installs tests/ops/requirements.txt"
    r = subprocess.run([str(hadolint), "--no-color", str(DOCKERFILE)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_hadolint_catches_a_bad_dockerfile(tmp_path):
    bad = tmp_path / "Dockerfile"
    bad.write_text("FROM debian:latest\nRUN apt-get install curl\n")
    r = subprocess.run([str(VENV_BIN / "hadolint"), "--no-color", str(bad)], capture_output=True, text=True)
    assert r.returncode != 0 and "DL3007" in r.stdout


def test_install_ort_installs_the_pinned_library(tmp_path):
    script = ROOT / "scripts" / "install-ort"
    pinned = re.search(r"^LIB_SHA256=([0-9a-f]{64})$", script.read_text(), re.M).group(1)
    env = dict(os.environ, PYTHON=str(VENV_BIN / "python"))
    r = subprocess.run(["bash", str(script), str(tmp_path / "lib")], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    lib = tmp_path / "lib" / "libonnxruntime.so.1.31.1"
    data = lib.read_bytes()
    assert data[:4] == b"\x7fELF" and hashlib.sha256(data).hexdigest() == pinned
    assert list((tmp_path / "lib").iterdir()) == [lib]  # no leftovers
    again = subprocess.run(["bash", str(script), str(tmp_path / "lib")], capture_output=True, text=True, env=env)
    assert again.returncode == 0 and "already installed" in again.stderr
    # A damaged library is replaced, not trusted.
    lib.write_bytes(b"not a library")
    fixed = subprocess.run(["bash", str(script), str(tmp_path / "lib")], capture_output=True, text=True, env=env, timeout=300)
    assert fixed.returncode == 0 and hashlib.sha256(lib.read_bytes()).hexdigest() == pinned


def test_the_library_setup_installed_is_the_pinned_one():
    from conftest import ort_library
    pinned = re.search(r"^LIB_SHA256=([0-9a-f]{64})$", (ROOT / "scripts" / "install-ort").read_text(), re.M).group(1)
    assert hashlib.sha256(open(ort_library(), "rb").read()).hexdigest() == pinned


def dockerignore_includes(path: str) -> bool:
    """Docker's rule: the last matching pattern wins; `!` re-includes."""
    included = True
    for pat in (ROOT / ".dockerignore").read_text().splitlines():
        pat = pat.strip()
        if not pat or pat.startswith("#"):
            continue
        neg = pat.startswith("!")
        pat = pat.lstrip("!").rstrip("/")
        if fnmatch.fnmatch(path, pat) or path.startswith(pat + "/"):
            included = neg
    return included


def test_every_copied_path_and_script_exists_in_the_build_context():
    sources = []
    for ins, rest in instructions():
        if ins == "COPY" and "--from=" not in rest:
            sources += [a for a in shlex.split(rest)[:-1] if not a.startswith("--")]
        if ins == "RUN":
            sources += re.findall(r"\b(scripts/[\w.-]+)", rest)
    assert "scripts/install-ort" in sources and "scripts/build-release" in sources
    for src in sources:
        p = ROOT / src.rstrip("/")
        assert p.exists(), f"{src} named in the Dockerfile does not exist"
        assert dockerignore_includes(src.rstrip("/")), f"{src} is excluded by .dockerignore"
    for model in ["models/full/model.onnx", "models/nocov/model.onnx", "models/lin2020/diffuse.onnx", "src/main.rs", "proto/mcdenoise/v1/denoise.proto"]:
        assert dockerignore_includes(model), model
    for heavy in ["target/release/mcdenoise", "runs/x", "data/x.exr", ".git/HEAD"]:
        assert not dockerignore_includes(heavy), heavy


def test_image_defaults_are_options_of_the_daemon():
    env = env_defaults()
    known = serve_env_vars()
    assert {"MCDENOISE_HTTP", "MCDENOISE_DATA_DIR", "MCDENOISE_MODELS", "ORT_DYLIB_PATH"} <= set(env)
    assert set(env) <= known, set(env) - known
    assert env["ORT_DYLIB_PATH"].endswith("/libonnxruntime.so.1.31.1")
    ins = instructions()
    assert ("USER", "10001:10001") in ins
    assert any(i == "HEALTHCHECK" and "mcdenoise-healthcheck" in r for i, r in ins)
    assert ("CMD", '["serve"]') in ins and ("ENTRYPOINT", '["mcdenoise"]') in ins
    ports = {r for i, r in ins if i == "EXPOSE"}
    port = {k: env[k].rsplit(':', 1)[1] for k in ("MCDENOISE_HTTP", "MCDENOISE_PROBE_HTTP", "MCDENOISE_GRPC")}
    assert ports == {f"{port['MCDENOISE_HTTP']} {port['MCDENOISE_PROBE_HTTP']} {port['MCDENOISE_GRPC']}"}


def test_daemon_runs_on_the_image_defaults(tmp_path):
    """`mcdenoise serve` with the image's environment (paths mapped into a temporary
    directory laid out like the image) becomes ready, and the HEALTHCHECK passes."""
    env = env_defaults()
    root = tmp_path / "image"
    (root / "opt/mcdenoise/lib").mkdir(parents=True)
    (root / "opt/mcdenoise/models").symlink_to(ROOT / "models")
    from conftest import ort_library
    os.symlink(ort_library(), root / env["ORT_DYLIB_PATH"].lstrip("/"))
    port = free_port()
    run_env = dict(os.environ)
    for k, v in env.items():
        run_env[k] = str(root / v.lstrip("/")) if v.startswith("/") else v
    run_env.update(MCDENOISE_HTTP=f"127.0.0.1:{port}", MCDENOISE_GRPC=f"127.0.0.1:{free_port()}",
                   MCDENOISE_PROBE_HTTP=f"127.0.0.1:{free_port()}")
    run_env.pop("MCDENOISE_AUTH_TOKENS", None)
    proc = subprocess.Popen([str(mcdenoise_bin()), "serve"], env=run_env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, cwd=tmp_path)
    try:
        d = Daemon.__new__(Daemon)
        d.url, d.proc, d.token = f"http://127.0.0.1:{port}", proc, None
        d.log = open(tmp_path / "unused.log", "wb")
        d.wait_ready()
        assert (root / "var/lib/mcdenoise/jobs.redb").is_file()
        # The healthcheck asks the probe port (MCDENOISE_PROBE_HTTP).
        hc = subprocess.run(["bash", str(ROOT / "scripts" / "healthcheck")], env=run_env, capture_output=True, text=True)
        assert hc.returncode == 0, hc.stderr
    finally:
        proc.terminate()
        assert proc.wait(30) == 0
    line = proc.stderr.read().decode().splitlines()[0]
    assert line.startswith("{"), "the image logs JSON"


def test_healthcheck_fails_without_a_daemon():
    r = subprocess.run(["bash", str(ROOT / "scripts" / "healthcheck"), str(free_port())], capture_output=True, text=True)
    assert r.returncode == 1 and "/livez" in r.stderr

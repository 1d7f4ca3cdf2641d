"""The Dockerfile without a container engine: hadolint, and the steps it runs (the shared
scripts) run here: scripts/install-ort, scripts/healthcheck, the image's defaults."""

from __future__ import annotations

import fnmatch
import hashlib
import os
import re
import shlex
import subprocess
from pathlib import Path

import pytest

from conftest import ROOT, VENV_BIN, Daemon, mcdenoise_bin, free_port, free_ports

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


def stages() -> dict:
    """Instructions per stage, by name (`FROM x AS name`; unnamed stages by their index), in
    order: the last one is what `docker build` makes without `--target`."""
    out = {}
    for ins, rest in instructions():
        if ins == "FROM":
            words = rest.split()
            name = words[2] if len(words) > 2 and words[1].upper() == "AS" else str(len(out))
            out[name] = [(ins, rest)]
        elif out:
            out[list(out)[-1]].append((ins, rest))
    return out


def env_defaults(stage: str | None = None) -> dict:
    """ENV of a stage (default: the last, the default image), with what it inherits from the
    stage it is built FROM."""
    all_stages = stages()
    stage = stage or list(all_stages)[-1]
    env = {}
    for ins, rest in all_stages[stage]:
        if ins == "FROM" and rest.split()[0] in all_stages:
            env = env_defaults(rest.split()[0])
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
    # Beside it, OpenVINO's plugin and runtime, each file as recorded; no leftovers.
    openvino = tmp_path / "lib" / "openvino"
    assert sorted((tmp_path / "lib").iterdir()) == [lib, openvino]
    sums = (openvino / "SHA256SUMS").read_text().splitlines()
    assert sums[0] == "# install-ort --openvino: onnxruntime-ep-openvino==1.8.1 openvino==2026.4.1"
    recorded = {line.split()[1] for line in sums[1:]}
    for name in ["libonnxruntime_providers_openvino_plugin.so", "libopenvino_intel_cpu_plugin.so", "libopenvino_c.so.2641"]:
        assert name in recorded, recorded
    assert {p.name for p in openvino.iterdir()} == recorded | {"SHA256SUMS"}
    check = subprocess.run("grep -v '^#' SHA256SUMS | sha256sum --quiet -c -", shell=True, cwd=openvino)
    assert check.returncode == 0
    again = subprocess.run(["bash", str(script), str(tmp_path / "lib")], capture_output=True, text=True, env=env)
    assert again.returncode == 0 and "already installed" in again.stderr
    assert "the openvino build is already installed" in again.stderr
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
    for model in ["models/full/model.onnx", "models/nocov/model.onnx", "models/lin2020/diffuse.onnx", "models/lin2020-narrow/diffuse.onnx", "src/main.rs", "proto/mcdenoise/v1/denoise.proto"]:
        assert dockerignore_includes(model), model
    for heavy in ["target/release/mcdenoise", "runs/x", "data/x.exr", ".git/HEAD"]:
        assert not dockerignore_includes(heavy), heavy


def test_the_build_stage_fetch_layer_parses_with_only_the_manifests(tmp_path):
    """The build stage runs `cargo fetch` with nothing but what it copied before (the
    manifests): every target in Cargo.toml must name its path, since cargo looks for an
    unnamed one (`benches/<name>.rs`) when it reads the manifest."""
    build = stages()["build"]
    fetch = next(i for i, (ins, rest) in enumerate(build) if ins == "RUN" and "cargo fetch" in rest)
    copied = [a for ins, rest in build[:fetch] if ins == "COPY" for a in shlex.split(rest)[:-1]]
    assert copied == ["Cargo.toml", "Cargo.lock"], copied
    for name in copied:
        (tmp_path / name).write_bytes((ROOT / name).read_bytes())
    host = re.search(r"^host: (\S+)$", subprocess.run(["rustc", "-vV"], capture_output=True, text=True, check=True).stdout, re.M).group(1)
    res = subprocess.run(["cargo", "fetch", "--locked", "--offline", "--target", host], cwd=tmp_path,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr


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


def test_the_gpu_image_runs_the_networks_on_cuda():
    """`--target gpu`: the CUDA build of ONNX Runtime with its libraries where the loader
    finds them, `--device cuda`, and otherwise the default image's settings."""
    all_stages = stages()
    assert list(all_stages)[-1] == "cpu", "the default image is the CPU one"
    gpu, cpu = env_defaults("gpu"), env_defaults()
    own = {k for k in gpu if k.startswith("MCDENOISE_") or k == "ORT_DYLIB_PATH"}
    assert own <= serve_env_vars(), own - serve_env_vars()
    assert set(gpu) - own == {"LD_LIBRARY_PATH", "NVIDIA_VISIBLE_DEVICES", "NVIDIA_DRIVER_CAPABILITIES"}
    assert gpu["MCDENOISE_DEVICE"] == "cuda" and "MCDENOISE_DEVICE" not in cpu
    lib_dir = os.path.dirname(gpu["ORT_DYLIB_PATH"])
    assert gpu["LD_LIBRARY_PATH"] == lib_dir
    assert {k: v for k, v in gpu.items() if k in cpu} == cpu, "the GPU image keeps the default image's settings"
    # The library comes from install-ort's CUDA build, copied whole (provider and CUDA
    # libraries beside the library); the CPU image copies the CPU build alone.
    runs = [rest for ins, rest in all_stages[gpu_source()] if ins == "RUN"]
    assert any("scripts/install-ort --cuda /out/lib" in r for r in runs), runs
    assert ("COPY", f"--from={gpu_source()} /out/lib/ {lib_dir}/") in all_stages["gpu"]
    assert ("COPY", f"--from=ort /out/lib/libonnxruntime.so.1.31.1 {lib_dir}/") in all_stages["cpu"]
    # The CPU image also carries OpenVINO's plugin where the engine looks for it, beside the
    # library (src/engine/runtime.rs).
    assert ("COPY", f"--from=ort /out/lib/openvino/ {lib_dir}/openvino/") in all_stages["cpu"]


def gpu_source() -> str:
    """The stage the GPU image copies its library directory from."""
    (src,) = [re.search(r"--from=(\S+)", rest).group(1) for ins, rest in stages()["gpu"] if ins == "COPY" and "--from=" in rest]
    return src


def test_the_gpu_image_without_a_gpu_stops_at_start_naming_what_is_missing(tmp_path):
    """The GPU image's environment on a machine without a GPU: `serve` exits before taking
    jobs, with the reason. With the CPU library the CUDA provider is missing; with the CUDA
    build (`scripts/install-ort --cuda $MCDENOISE_HOME/lib-cuda`, about 1.8 GB, not part of
    the default setup) the NVIDIA driver is."""
    from conftest import ort_library
    env = env_defaults("gpu")
    home = Path(os.environ.get("MCDENOISE_HOME", Path.home() / ".cache" / "mcdenoise"))
    libraries = [(ort_library(), "has no CUDA execution provider (it is the CPU build)")]
    cuda_build = home / "lib-cuda" / "libonnxruntime.so.1.31.1"
    if (home / "lib-cuda" / "SHA256SUMS").is_file() and not Path("/dev/nvidiactl").exists():
        libraries.append((str(cuda_build), "libcuda.so.1 cannot be loaded"))
    for library, reason in libraries:
        run_env = dict(os.environ, **{k: v for k, v in env.items() if k.startswith("MCDENOISE_")})
        http, grpc, probe = free_ports(3)
        run_env.update(ORT_DYLIB_PATH=library, LD_LIBRARY_PATH=os.path.dirname(library),
                       MCDENOISE_MODELS=str(ROOT / "models"), MCDENOISE_DATA_DIR=str(tmp_path / "data"),
                       MCDENOISE_HTTP=f"127.0.0.1:{http}", MCDENOISE_GRPC=f"127.0.0.1:{grpc}",
                       MCDENOISE_PROBE_HTTP=f"127.0.0.1:{probe}")
        run_env.pop("MCDENOISE_AUTH_TOKENS", None)
        r = subprocess.run([str(mcdenoise_bin()), "serve"], env=run_env, capture_output=True, text=True, timeout=60)
        assert r.returncode != 0, library
        assert "--device cuda:0" in r.stderr and reason in r.stderr, r.stderr[-2000:]


def test_daemon_runs_on_the_image_defaults(tmp_path):
    """`mcdenoise serve` with the image's environment (paths mapped into a temporary
    directory laid out like the image) becomes ready, and the HEALTHCHECK passes."""
    env = env_defaults()
    root = tmp_path / "image"
    (root / "opt/mcdenoise/lib").mkdir(parents=True)
    (root / "opt/mcdenoise/models").symlink_to(ROOT / "models")
    from conftest import ort_library
    os.symlink(ort_library(), root / env["ORT_DYLIB_PATH"].lstrip("/"))
    port, grpc, probe = free_ports(3)
    run_env = dict(os.environ)
    for k, v in env.items():
        run_env[k] = str(root / v.lstrip("/")) if v.startswith("/") else v
    run_env.update(MCDENOISE_HTTP=f"127.0.0.1:{port}", MCDENOISE_GRPC=f"127.0.0.1:{grpc}",
                   MCDENOISE_PROBE_HTTP=f"127.0.0.1:{probe}")
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


def test_install_ort_pins_the_cuda_build():
    """install-ort's GPU lists: each wheel pinned by version and sha256, the GPU build of the
    same ONNX Runtime version as the CPU one. Where `scripts/install-ort --cuda` has run
    into $MCDENOISE_HOME/lib-cuda, its files still match what it recorded, and the only
    library the provider cannot find beside them is the NVIDIA driver's."""
    text = (ROOT / "scripts" / "install-ort").read_text()
    version = re.search(r"^ORT_VERSION=(\S+)$", text, re.M).group(1)
    entries = re.findall(r'^  "(\S+)==(\S+) (\S+\.whl) ([0-9a-f]{64}) (.+)"$', text, re.M)
    names = {e[0] for e in entries}
    assert names == {"onnxruntime-gpu", "nvidia-cuda-runtime", "nvidia-cublas", "nvidia-curand", "nvidia-cudnn-cu13",
                     "onnxruntime-ep-openvino", "openvino"}
    assert ("onnxruntime-gpu", version) in {(e[0], e[1]) for e in entries}
    for name, ver, wheel, _, members in entries:
        assert wheel.startswith(name.replace("-", "_") + "-" + ver + "-"), wheel
        assert members.split(), name
    home = Path(os.environ.get("MCDENOISE_HOME", Path.home() / ".cache" / "mcdenoise"))
    lib = home / "lib-cuda"
    if not (lib / "SHA256SUMS").is_file():
        pytest.skip(f"no CUDA build in {lib} (scripts/install-ort --cuda {lib}, 1.8 GB) to check further")
    check = subprocess.run("grep -v '^#' SHA256SUMS | sha256sum --quiet -c -", shell=True, cwd=lib,
                           capture_output=True, text=True)
    assert check.returncode == 0, check.stdout + check.stderr
    ldd = subprocess.run(["ldd", str(lib / "libonnxruntime_providers_cuda.so")], capture_output=True, text=True,
                         env=dict(os.environ, LD_LIBRARY_PATH=str(lib)))
    missing = {line.split()[0] for line in ldd.stdout.splitlines() if "not found" in line}
    assert missing <= {"libcuda.so.1"}, missing

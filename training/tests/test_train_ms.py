"""The contract-v2 training path: PyTorch preprocessing against the engine's, augmentation,
a few training steps end to end with resume and export."""

import json
import math
import os
import subprocess

import numpy as np
import pytest
import torch

from mcdenoise_train import train_ms
from mcdenoise_train.checkpoint import load_msnet, load_state, save_msnet, save_state
from mcdenoise_train.export_ms import read_metadata_v2
from mcdenoise_train.exr import read_exr, write_exr
from mcdenoise_train.frames import synthetic_frame
from mcdenoise_train.preprocess import (ALBEDO, ALBEDO_PASSES, DIFFUSE, RAW, SPECULAR, VAR, estimated_albedo_variance,
                                        nl_means_pass, prefilter_albedo, preprocess, raw_from_channels, targets)

from test_train import make_dataset, needs_engine

BIN = os.environ.get("MCDENOISE_BIN", "")


@needs_engine
@pytest.mark.parametrize("covariance,dome_rows", [(True, 1), (False, 1), (False, 28)])
def test_preprocessing_matches_the_engine(tmp_path, covariance, dome_rows):
    ch = synthetic_frame(40, 48, seed=3, covariance=covariance)
    ref = {k: v * 0.9 for k, v in ch.items()}
    # A background written as "infinitely far" (1e10, 1e30): both sides read it as no hit.
    ch["depth.Z"][0, :5], ch["depth.Z"][1, :3] = 1e10, 1e30
    # A sky dome far beyond the scene (over part of a row, or over most of the frame), read
    # as no hit too, and a depth variance far above the square of the depth scale (a pixel
    # mixing a near surface with the dome), saturated.
    ch["depth.Z"][2:2 + dome_rows, :44], ch["depthVariance.Z"][31, :2] = 1e5, 1e6
    write_exr(tmp_path / "f.exr", ch)
    write_exr(tmp_path / "r.exr", ref)
    # The firefly stage and the albedo prefilter are the engine's own (off here, tested
    # below): this compares the transforms.
    subprocess.run([BIN, "preprocess", str(tmp_path / "f.exr"), "--reference", str(tmp_path / "r.exr"), "--fireflies", "off",
                    "--albedo-prefilter", "off", "-o", str(tmp_path / "f.npz")], check=True, capture_output=True)
    engine = np.load(tmp_path / "f.npz")
    raw, dmax, cmax = raw_from_channels(read_exr(tmp_path / "f.exr"), albedo_prefilter=False)
    np.testing.assert_allclose(raw[ALBEDO], engine["albedo"], rtol=1e-6, atol=0, err_msg="albedo")
    t = preprocess(torch.from_numpy(raw)[None], torch.tensor([dmax]), torch.tensor([cmax]),
                   "full" if covariance else "nocov")
    for name, key in (("diffuse", "diffuse_color"), ("specular", "specular_color"), ("features", "features")):
        np.testing.assert_allclose(t[name][0].numpy(), engine[key], rtol=1e-5, atol=1e-6, err_msg=name)
    r, _, _ = raw_from_channels(read_exr(tmp_path / "r.exr"))
    tg = targets(torch.from_numpy(r[DIFFUSE])[None], torch.from_numpy(r[SPECULAR])[None], t["albedo"])
    np.testing.assert_allclose(tg["diffuse_target"][0].numpy(), engine["diffuse_target"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(tg["specular_target"][0].numpy(), engine["specular_target"], rtol=1e-5, atol=1e-6)


@needs_engine
def test_the_albedo_prefilter_is_the_engines(tmp_path):
    ch = synthetic_frame(24, 20, seed=5, covariance=True)
    ref = {k: v * 0.9 for k, v in ch.items()}
    write_exr(tmp_path / "f.exr", ch)
    write_exr(tmp_path / "r.exr", ref)
    # Both sides prefilter by default.
    subprocess.run([BIN, "preprocess", str(tmp_path / "f.exr"), "--reference", str(tmp_path / "r.exr"), "--fireflies",
                    "off", "-o", str(tmp_path / "f.npz")], check=True, capture_output=True)
    engine = np.load(tmp_path / "f.npz")
    raw, dmax, cmax = raw_from_channels(read_exr(tmp_path / "f.exr"))
    np.testing.assert_allclose(raw[ALBEDO], engine["albedo"], rtol=1e-5, atol=1e-6, err_msg="albedo")
    plain = raw_from_channels(read_exr(tmp_path / "f.exr"), albedo_prefilter=False)[0]
    assert np.abs(raw[ALBEDO] - plain[ALBEDO]).max() > 1e-3, "the synthetic albedo is noisy with a variance"
    # The division, the albedo features and the targets use the prefiltered albedo.
    t = preprocess(torch.from_numpy(raw)[None], torch.tensor([dmax]), torch.tensor([cmax]), "full")
    for name, key in (("diffuse", "diffuse_color"), ("features", "features")):
        np.testing.assert_allclose(t[name][0].numpy(), engine[key], rtol=1e-5, atol=1e-5, err_msg=name)
    r, _, _ = raw_from_channels(read_exr(tmp_path / "r.exr"))
    tg = targets(torch.from_numpy(r[DIFFUSE])[None], torch.from_numpy(r[SPECULAR])[None], t["albedo"])
    np.testing.assert_allclose(tg["diffuse_target"][0].numpy(), engine["diffuse_target"], rtol=1e-5, atol=1e-6)


@needs_engine
def test_a_frame_without_albedo_variance_is_prefiltered_by_the_engines_estimate(tmp_path):
    """Written without variances, a frame's albedo is prefiltered by the variance estimated
    from it, on both sides alike; the estimate is what its method says."""
    ch = synthetic_frame(40, 36, seed=7, covariance=False)
    bare = {k: v for k, v in ch.items() if "Variance" not in k}
    noise = np.random.default_rng(0).uniform(-0.05, 0.05, (3, 40, 36)).astype(np.float32)
    for i, c in enumerate("RGB"):  # the synthetic albedo is smooth: noisy as a defocused one is
        bare[f"albedo.{c}"] = bare[f"albedo.{c}"] + noise[i]
    write_exr(tmp_path / "f.exr", bare)
    subprocess.run([BIN, "preprocess", str(tmp_path / "f.exr"), "--fireflies", "off", "-o", str(tmp_path / "f.npz")],
                   check=True, capture_output=True)
    engine = np.load(tmp_path / "f.npz")
    raw = raw_from_channels(read_exr(tmp_path / "f.exr"))[0]
    # Both keep the result in half float: a float32 sum in another order may round a sample
    # to the neighbouring half (one of 4,320 here), never further.
    np.testing.assert_allclose(raw[ALBEDO], engine["albedo"], rtol=2.0 ** -10, atol=1e-6, err_msg="albedo")
    assert np.mean(raw[ALBEDO] != engine["albedo"]) < 0.005
    plain = raw_from_channels(read_exr(tmp_path / "f.exr"), albedo_prefilter=False)[0]
    assert np.abs(raw[ALBEDO] - plain[ALBEDO]).max() > 1e-3, "prefiltered without a variance in the file"
    # The method, written out for one pixel inside the frame.
    a = plain[ALBEDO]
    lum = np.float32(0.2126) * a[0] + np.float32(0.7152) * a[1] + np.float32(0.0722) * a[2]
    y, x = 17, 20
    res = lambda yy, xx: (lum[yy, xx] - np.median(lum[yy - 1:yy + 2, xx - 1:xx + 2])) ** 2
    block = lambda yy, xx: np.median([res(yy + i, xx + j) for i in (-1, 0, 1) for j in (-1, 0, 1)])
    expect = np.median([block(y + i, x + j) for i in (-3, 0, 3) for j in (-3, 0, 3)])
    assert estimated_albedo_variance(a)[y, x] == pytest.approx(expect, rel=1e-6)
    # A given albedo variance is used as it is, zeros too (an exact albedo).
    zeros = dict(bare, **{"albedoVariance.Z": np.zeros_like(bare["albedo.R"])})
    np.testing.assert_allclose(raw_from_channels(zeros)[0][ALBEDO], plain[ALBEDO], atol=1e-3)


@pytest.mark.parametrize("k", ALBEDO_PASSES)
def test_the_albedo_prefilter_follows_its_method(k):
    # One pass of src/engine/albedo.rs written out pixel by pixel in float64, on a frame
    # smaller than the window in one direction so that clamping matters.
    rng = np.random.default_rng(0)
    h, w, r, f = 9, 6, 3, 1
    a = rng.uniform(0, 1, (3, h, w)).astype(np.float32)
    a[:, :, 4] = a[:, :, 3]  # equal pixels without variance
    v = (rng.uniform(0, 0.05, (h, w)) * (rng.uniform(size=(h, w)) > 0.3)).astype(np.float32)
    v[:, 3:5] = 0
    a[:, 2, 1] = (40.0, 70.0, 50.0)  # an emitter's strength in the albedo pass
    v[2, 1] = 500.0
    cl = lambda i, n: min(max(i, 0), n - 1)

    def d(py, px, qy, qx):
        diff = ((a[:, py, px].astype(np.float64) - a[:, qy, qx]) ** 2).mean()
        vp, vq = float(v[py, px]), float(v[qy, qx])
        return (diff - (vp + min(vp, vq))) / (1e-10 + k * k * (vp + vq))

    want, want_v = np.zeros((3, h, w)), np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            num, den, var = np.zeros(3), 0.0, 0.0
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    patch = np.mean([d(cl(y + i, h), cl(x + j, w), cl(cl(y + i, h) + dy, h), cl(cl(x + j, w) + dx, w))
                                     for i in range(-f, f + 1) for j in range(-f, f + 1)])
                    weight = np.exp(-max(patch, 0.0)) * float((a[:, cl(y + dy, h), cl(x + dx, w)] <= 1).all())
                    num += weight * a[:, cl(y + dy, h), cl(x + dx, w)]
                    var += weight * weight * float(v[cl(y + dy, h), cl(x + dx, w)])
                    den += weight
            keep = not (a[:, y, x] <= 1).all()
            want[:, y, x] = a[:, y, x] if keep else num / den
            want_v[y, x] = v[y, x] if keep else var / (den * den)
    got, got_v = nl_means_pass(a, v, k)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(got_v, want_v, rtol=1e-5, atol=1e-9)
    assert np.abs(got - a).max() > 1e-2, "noisy pixels move"
    others = (a <= 1).all(0)
    assert got_v[others].mean() < v[others].mean(), "weighted means have less variance"
    assert got[:, others].max() <= 1, "the emitter pulls no neighbour"
    assert np.array_equal(got[:, 2, 1], a[:, 2, 1]), "and keeps its value"


def test_the_albedo_prefilter_is_its_passes_in_turn_exact_pixels_kept():
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 1, (3, 12, 10)).astype(np.float32)
    v = rng.uniform(0, 0.05, (12, 10)).astype(np.float32)
    v[::3, ::2] = 0  # exact pixels
    first, v1 = nl_means_pass(a, v, ALBEDO_PASSES[0])
    second = nl_means_pass(first, v1, ALBEDO_PASSES[1])[0]
    got = prefilter_albedo(a, v)
    np.testing.assert_array_equal(got[:, v > 0], second[:, v > 0])
    np.testing.assert_array_equal(got[:, v == 0], first[:, v == 0], "an exact pixel keeps the first pass's value")
    assert np.abs(got - first).max() > 1e-3, "the second pass moves what the first left"
    assert np.abs(second - first)[:, v == 0].max() > 1e-4, "which it would move at exact pixels too"


def _raw_batch(n=3, size=33, seed=0):
    raws, refs = [], []
    for i in range(n):
        raw, dmax, cmax = raw_from_channels(synthetic_frame(size, size, seed=seed + i))
        raws.append(raw)
        refs.append(np.concatenate([raw[DIFFUSE], raw[SPECULAR]]) * 0.5)
    return torch.from_numpy(np.stack(raws)), torch.from_numpy(np.stack(refs))


def _args(**kw):
    a = train_ms.parse(["--data", "x", "--out", "y"])
    a.exposure, a.fireflies = 0.0, 0.0
    for k, v in kw.items():
        setattr(a, k, v)
    return a


def test_augmentation_keeps_inputs_and_references_aligned():
    raw, ref = _raw_batch()
    g = torch.Generator().manual_seed(1)
    a_raw, a_ref = train_ms.augment(raw, ref, g, _args())
    # Flips, transposes and colour permutations move input and reference together: the
    # reference stays 0.5 x the noisy radiance, pixel for pixel and channel for channel.
    np.testing.assert_allclose(a_ref[:, 0:3].numpy(), 0.5 * a_raw[:, DIFFUSE].numpy(), rtol=1e-6)
    np.testing.assert_allclose(a_ref[:, 3:6].numpy(), 0.5 * a_raw[:, SPECULAR].numpy(), rtol=1e-6)
    assert not torch.equal(a_raw, raw)  # something was applied with this seed


def test_exposure_scales_radiance_and_variance_together():
    raw, ref = _raw_batch(1)
    g = torch.Generator().manual_seed(5)
    a_raw, a_ref = train_ms.augment(raw, ref, g, _args(exposure=3.0))
    ratio = float(a_raw[0, DIFFUSE].sum() / raw[0, DIFFUSE].sum())
    var_ratio = float(a_raw[0, VAR["diffuse"]].sum() / raw[0, VAR["diffuse"]].sum())
    assert 2 ** -3 <= ratio <= 2 ** 3 and ratio != 1.0
    assert var_ratio == pytest.approx(ratio ** 2, rel=1e-4)


def test_injected_fireflies_touch_inputs_only():
    raw, ref = _raw_batch(2)
    before = raw.clone()
    g = torch.Generator().manual_seed(0)
    train_ms.inject_fireflies(raw, g, fraction=1.0, per_patch=3)
    changed = (raw != before).any(1)  # pixels changed in any channel
    assert 1 <= int(changed[0].sum()) <= 3 and 1 <= int(changed[1].sum()) <= 3
    y, x = [int(v[0]) for v in torch.nonzero(changed[0], as_tuple=True)]
    comp = DIFFUSE if (raw[0, DIFFUSE, y, x] != before[0, DIFFUSE, y, x]).any() else SPECULAR
    assert float(raw[0, comp, y, x].mean()) >= 5 * float(before[0, comp, y, x].mean())
    var = VAR["diffuse"] if comp is DIFFUSE else VAR["specular"]
    assert float(raw[0, var, y, x]) > float(before[0, var, y, x])


def test_training_steps_resume_and_export(tmp_path):
    root = make_dataset(tmp_path / "d", frames=3, size=48)
    out, models = tmp_path / "run", tmp_path / "models"
    small = ["--ext-width", "4", "--enc", "6,6,8,8", "--dec", "6,6,8,8", "--patch", "32", "--batch", "2",
             "--threads", "2", "--device", "cpu", "--val-every", "2"]
    assert train_ms.main(["--data", str(root), "--out", str(out), "--steps", "3", *small]) == 0
    val = [json.loads(l) for l in open(out / "val.jsonl")]
    assert [v["step"] for v in val] == [2, 3] and all(np.isfinite(v["relmse"]) for v in val)
    assert "nocov" in val[0] and np.isfinite(val[0]["nocov"]["relmse"])
    # Resume continues from step 3 to 5 with the saved optimizer and schedule; a time limit
    # counts this run's seconds only, not those the earlier runs took.
    state = load_state(out / "state.pt")
    state = {k: v for k, v in state.items() if k not in ("format", "version")}
    save_state(out / "state.pt", **{**state, "elapsed": 1e6})
    assert train_ms.main(["--data", str(root), "--out", str(out), "--steps", "5", "--resume", *small,
                          "--time-limit", "3600", "--export", str(models)]) == 0
    val = [json.loads(l) for l in open(out / "val.jsonl")]
    assert [v["step"] for v in val] == [2, 3, 4, 5]
    for variant in ("full", "nocov"):
        meta = read_metadata_v2(models / variant / "model.onnx")
        assert meta["mcdenoise.contract"] == "2" and meta["mcdenoise.variant"] == variant
    # Fine-tuning starts from the best weights, keeps their shape whatever the options say,
    # and begins a fresh schedule at step 0.
    tuned = tmp_path / "tuned"
    assert train_ms.main(["--data", str(root), "--out", str(tuned), "--steps", "2", *small, "--enc", "9,9,9,9",
                          "--init", str(out / "best.pt"), "--ssim", "0.5"]) == 0
    # The network it starts from is scored first, on the same frames (step 0), and best.pt
    # holds it until a later step scores better: a fine-tune never keeps a worse network.
    rows = [json.loads(l) for l in open(tuned / "val.jsonl")]
    assert [r["step"] for r in rows] == [0, 2] and rows[0]["init"] == str(out / "best.pt")
    start = min(v["score"] for v in val)  # the --init checkpoint is the run's best
    assert rows[0]["score"] == pytest.approx(start, rel=1e-5)
    assert load_msnet(tuned / "best.pt")[1]["step"] == (2 if rows[1]["score"] < rows[0]["score"] else 0)
    cfg = json.loads((tuned / "config.json").read_text())
    assert cfg["enc"] == "6,6,8,8" and cfg["ssim"] == 0.5
    # --reshape trains the shape the options give from the checkpoint's weights where they fit.
    slim = tmp_path / "slim"
    assert train_ms.main(["--data", str(root), "--out", str(slim), "--steps", "2", *small, "--ext-blocks", "0",
                          "--dec", "4,6,8,8", "--init", str(out / "best.pt"), "--reshape"]) == 0
    net = load_msnet(slim / "best.pt")[0]
    assert net.config["ext_blocks"] == 0 and net.config["dec"] == [4, 6, 8, 8]
    with pytest.raises(SystemExit, match="--reshape needs --init"):
        train_ms.main(["--data", str(root), "--out", str(slim), "--steps", "2", *small, "--reshape"])
    # --teacher adds the distillation term, logged beside the others; here into a network
    # whose decoder level 0 is lean (--lean0: new there, the rest from the checkpoint).
    taught = tmp_path / "taught"
    assert train_ms.main(["--data", str(root), "--out", str(taught), "--steps", "20", *small, "--val-every", "20",
                          "--ext-blocks", "0", "--dec", "4,6,8,8", "--lean0", "--init", str(out / "best.pt"),
                          "--reshape", "--teacher", str(out / "best.pt"), "--distill", "0.7"]) == 0
    rows = [json.loads(l) for l in open(taught / "log.jsonl")]
    assert rows and all(np.isfinite(r["distill"]) and r["distill"] > 0 for r in rows)
    assert load_msnet(taught / "best.pt")[0].lean0
    with pytest.raises(SystemExit, match="between 0 and 1"):
        train_ms.main(["--data", str(root), "--out", str(taught), "--steps", "2", *small,
                       "--teacher", str(out / "best.pt"), "--distill", "1.5"])


def test_resume_scores_best_again_when_the_validation_frames_changed(tmp_path, capsys):
    root = make_dataset(tmp_path / "d", frames=3, size=48)
    out = tmp_path / "run"
    small = ["--data", str(root), "--out", str(out), "--ext-width", "4", "--enc", "6,6,8,8", "--dec", "6,6,8,8",
             "--patch", "32", "--batch", "2", "--threads", "2", "--device", "cpu", "--val-every", "2"]
    assert train_ms.main([*small, "--steps", "2"]) == 0
    state = {k: v for k, v in load_state(out / "state.pt").items() if k not in ("format", "version")}
    assert state["val_names"] == ["s2-spp8"]
    # The same frames: the saved best stands (an unbeatable one here, so nothing replaces it).
    save_state(out / "state.pt", **{**state, "best": -1e9})
    assert train_ms.main([*small, "--steps", "4", "--resume"]) == 0
    assert load_state(out / "state.pt")["best"] == -1e9
    # Other frames (a scene rendered between the runs): best.pt is scored again on these.
    state = {k: v for k, v in load_state(out / "state.pt").items() if k not in ("format", "version")}
    save_state(out / "state.pt", **{**state, "best": -1e9, "val_names": ["a scene since removed"]})
    capsys.readouterr()
    assert train_ms.main([*small, "--steps", "6", "--resume"]) == 0
    assert "validation frames changed (1 -> 1): best.pt scored again" in capsys.readouterr().err
    scores = [json.loads(l)["score"] for l in open(out / "val.jsonl")]
    assert -1e9 < load_state(out / "state.pt")["best"] <= scores[-1] + 1e-9


def test_selection_by_both_scores(tmp_path, capsys):
    v = {"score": -10.0, "nocov": {"score": -8.0}}
    assert train_ms.selection_score(v, "full") == -10.0
    assert train_ms.selection_score(v, "both") == -9.0
    assert train_ms.selection_score({"score": -10.0}, "both") == -10.0  # beauty: no nocov row
    root = make_dataset(tmp_path / "d", frames=3, size=48)
    out = tmp_path / "run"
    small = ["--data", str(root), "--out", str(out), "--ext-width", "4", "--enc", "6,6,8,8", "--dec", "6,6,8,8",
             "--patch", "32", "--batch", "2", "--threads", "2", "--device", "cpu", "--val-every", "2"]
    assert train_ms.main([*small, "--steps", "2"]) == 0
    assert load_state(out / "state.pt")["select"] == "full"
    # Resumed with the other selection, the saved best (a `full` score) does not compare:
    # best.pt is scored again by the mean of both.
    capsys.readouterr()
    assert train_ms.main([*small, "--steps", "4", "--resume", "--select", "both"]) == 0
    assert "selection changed (full -> both): best.pt scored again" in capsys.readouterr().err
    rows = [json.loads(l) for l in open(out / "val.jsonl")]
    state = load_state(out / "state.pt")
    assert state["select"] == "both"
    assert state["best"] <= min(train_ms.selection_score(r, "both") for r in rows[1:]) + 1e-9


def test_distillation_targets_are_the_teachers_output():
    args = _args(ext_width=4, ext_blocks=1, enc="6,6,8,8", dec="6,6,8,8")
    torch.manual_seed(0)
    student, other = train_ms.from_arguments(args, 28), train_ms.from_arguments(args, 28)
    raw, ref = _raw_batch(n=2, size=33)
    maxima = torch.ones(2, 2)
    b = train_ms.batch_inputs(raw, ref, maxima, 0.0, torch.Generator().manual_seed(0), crop=32)
    rec = train_ms.forward(student, b, autocast=False)
    same = train_ms.distill_batch(student, b, autocast=False)
    assert torch.equal(same["diffuse"], b["diffuse"]) and not torch.equal(same["reference"], b["reference"])
    loss, parts = train_ms.losses.ms_loss(rec, same, ssim_weight=0.2)
    assert float(loss.detach()) < 1e-5, parts
    loss, _ = train_ms.losses.ms_loss(rec, train_ms.distill_batch(other, b, autocast=False), ssim_weight=0.2)
    assert float(loss.detach()) > 1e-3


def test_variance_dropout_shows_patches_as_frames_without_variances_and_the_teacher_them_whole():
    """--var-dropout: a dropped patch's inputs are those of the frame without any variance
    buffer (variances 0, the albedo prefiltered by its estimated variance); the teacher sees
    every patch whole, and its diffuse target is demodulated by the student's albedo, so
    that the student's final color is held to the teacher's."""
    raw, ref = _raw_batch(n=2, size=33)
    written = raw[:, ALBEDO] * 1.5 + 0.01  # stands for the albedo of the frame without variances
    kept = torch.cat([raw, written], 1)
    assert kept.shape[1] == len(RAW) + 3 and train_ms.ALBEDO_WITHOUT_VARIANCES == slice(len(RAW), len(RAW) + 3)
    bare = train_ms.without_variances(kept)
    assert bare.shape[1] == len(RAW) and torch.equal(bare[:, ALBEDO], written)
    assert not bare[:, VAR["diffuse"]:VAR["covariance"] + 1].any() and torch.equal(bare[:, :6], raw[:, :6])
    maxima = torch.ones(2, 2)
    g = lambda: torch.Generator().manual_seed(0)
    b = train_ms.batch_inputs(kept, ref, maxima, 0.0, g(), crop=32, var_dropout=1.0)
    student = preprocess(bare, maxima[:, 0], maxima[:, 1], "full")
    whole = preprocess(raw, maxima[:, 0], maxima[:, 1], "full")
    for k in ("diffuse", "specular", "features", "albedo"):
        assert torch.equal(b[k], student[k][..., :32, :32]) and torch.equal(b[f"teacher_{k}"], whole[k][..., :32, :32])
    assert torch.equal(b["diffuse_target"], targets(ref[:, 0:3], ref[:, 3:6], written)["diffuse_target"][..., :32, :32])
    # None dropped: the student's inputs are the whole patch's, and so are the teacher's.
    b0 = train_ms.batch_inputs(kept, ref, maxima, 0.0, g(), crop=32, var_dropout=1e-9)
    assert torch.equal(b0["features"], b0["teacher_features"]) and torch.equal(b0["albedo"], whole["albedo"][..., :32, :32])
    # Without --var-dropout the batch is as before: no teacher inputs of its own.
    assert not any(k.startswith("teacher_") for k in train_ms.batch_inputs(raw, ref, maxima, 0.0, g(), crop=32))

    args = _args(ext_width=4, ext_blocks=1, enc="6,6,8,8", dec="6,6,8,8")
    torch.manual_seed(0)
    net = train_ms.from_arguments(args, 28)
    taught = train_ms.distill_batch(net, b, autocast=False)
    seen_whole = train_ms.forward(net, {k[len("teacher_"):]: v for k, v in b.items() if k.startswith("teacher_")},
                                  autocast=False)
    assert torch.allclose(taught["reference"], seen_whole.total)
    # The diffuse target remodulated by the student's albedo is the teacher's diffuse.
    assert torch.allclose(taught["diffuse_target"] * (b["albedo"] + train_ms.EPS), seen_whole.diffuse, rtol=1e-5, atol=1e-6)
    assert not torch.allclose(taught["reference"], train_ms.forward(net, b, autocast=False).total)


def test_step_loss_mixes_the_teacher_in_before_the_blend_penalty():
    args = _args(ext_width=4, ext_blocks=1, enc="6,6,8,8", dec="6,6,8,8", ssim=0.2, msssim=0.0)
    torch.manual_seed(0)
    net = train_ms.from_arguments(args, 28)
    raw, ref = _raw_batch(n=2, size=33)
    b = train_ms.batch_inputs(raw, ref, torch.ones(2, 2), 0.0, torch.Generator().manual_seed(0), crop=32)
    out = train_ms.outputs(net, b, autocast=False)
    rec = train_ms.reconstructed(net, out, b)
    # A bound this tight leaves every blend logit beyond it: the penalty is positive.
    excess = float(train_ms.blend_excess(out, net.levels, 1e-3))
    assert excess > 0
    reference, _ = train_ms.step_loss(net, out, rec, b, args)
    # The student as its own teacher at W = 1: the distillation term is 0 and the references
    # are not compared, so all that is left is the blend penalty at its full weight.
    a1 = _args(**{**vars(args), "distill": 1.0, "blend_bound": 1e-3, "blend_penalty": 2.0})
    loss, parts = train_ms.step_loss(net, out, rec, b, a1, teacher=net)
    assert parts["distill"] < 1e-5 and "smape_diffuse" not in parts
    assert float(loss) == pytest.approx(parts["distill"] + 2.0 * excess, rel=1e-4, abs=1e-6)
    # At W = 0.25 the references weigh 0.75, the penalty still 1.
    a2 = _args(**{**vars(a1), "distill": 0.25})
    loss, parts = train_ms.step_loss(net, out, rec, b, a2, teacher=net)
    assert float(loss) == pytest.approx(0.75 * float(reference) + 0.25 * parts["distill"] + 2.0 * excess, rel=1e-4)


def test_a_run_with_variance_dropout_scores_frames_without_variances_and_selects_on_all(tmp_path):
    root = make_dataset(tmp_path / "d", frames=3, size=48)
    out = tmp_path / "run"
    small = ["--data", str(root), "--out", str(out), "--ext-width", "4", "--enc", "6,6,8,8", "--dec", "6,6,8,8",
             "--patch", "32", "--batch", "2", "--threads", "2", "--device", "cpu", "--val-every", "2"]
    with pytest.raises(SystemExit, match="needs --var-dropout"):
        train_ms.main([*small, "--steps", "2", "--select", "all"])
    with pytest.raises(SystemExit, match="--var-dropout 1.5"):
        train_ms.main([*small, "--steps", "2", "--var-dropout", "1.5"])
    assert train_ms.main([*small, "--steps", "2", "--var-dropout", "0.5", "--select", "all"]) == 0
    rows = [json.loads(l) for l in open(out / "val.jsonl")]
    assert rows and all({"nocov", "novar"} <= set(r) for r in rows)
    # Without variances the frames are denoised differently.
    assert rows[-1]["novar"]["relmse"] != rows[-1]["nocov"]["relmse"]
    v = {"score": -9.0, "nocov": {"score": -8.0}, "novar": {"score": -6.0}}
    assert train_ms.selection_score(v, "all") == pytest.approx(-23.0 / 3)
    state = load_state(out / "state.pt")
    assert state["best"] == pytest.approx(min(train_ms.selection_score(r, "all") for r in rows), abs=1e-9)


def test_paper_network_trains_and_exports_as_lin2020(tmp_path):
    from mcdenoise_train.export import read_metadata

    root = make_dataset(tmp_path / "d", frames=3, size=48)
    models = tmp_path / "models"
    assert train_ms.main(["--data", str(root), "--out", str(tmp_path / "run"), "--arch", "lin2020",
                          "--lin-width", "4", "--lin-blocks", "1", "--lin-predictor-width", "4", "--steps", "2",
                          "--patch", "32", "--batch", "2", "--threads", "2", "--device", "cpu",
                          "--export", str(models)]) == 0
    assert json.loads((tmp_path / "run" / "config.json").read_text())["lr"] == train_ms.PEAK_LR["lin2020"]
    # Validation reports how peaked the kernels are (one-hot kernels are a run that has failed).
    val = [json.loads(line) for line in (tmp_path / "run" / "val.jsonl").read_text().splitlines()]
    assert 1 / 441 <= val[-1]["kernel_peak"] < 0.5 and "kernel_peak" not in val[-1]["nocov"]
    for c in ("diffuse", "specular"):
        meta = read_metadata(models / "lin2020" / f"{c}.onnx")
        assert meta["mcdenoise.contract"] == "1" and meta["mcdenoise.variant"] == "lin2020"
        assert meta["mcdenoise.component"] == c and meta["mcdenoise.kernel_size"] == "21"

    # A run goes on from an earlier one's best.pt (--init): its shape, its weights at the start.
    from mcdenoise_train.checkpoint import load_checkpoint

    start = load_checkpoint(tmp_path / "run" / "best.pt")[0]
    assert train_ms.main(["--data", str(root), "--out", str(tmp_path / "more"), "--arch", "lin2020",
                          "--init", str(tmp_path / "run" / "best.pt"), "--steps", "1", "--lr", "1e-12",
                          "--patch", "32", "--batch", "2", "--threads", "2", "--device", "cpu"]) == 0
    # The start is scored as step 0 and kept as best.pt until a validation beats it.
    rows = [json.loads(line) for line in (tmp_path / "more" / "val.jsonl").read_text().splitlines()]
    assert rows[0]["step"] == 0 and rows[0]["init"] == str(tmp_path / "run" / "best.pt")
    after = load_checkpoint(tmp_path / "more" / "best.pt")[0]
    for c in ("diffuse", "specular"):
        assert after[c].config == start[c].config
        for k, v in start[c].state_dict().items():
            assert torch.allclose(after[c].state_dict()[k], v, atol=1e-6), (c, k)
    # Or from the served pair's directory: its files carry the configuration and the weights,
    # stored rounded to float16.
    assert train_ms.main(["--data", str(root), "--out", str(tmp_path / "served"), "--arch", "lin2020",
                          "--init", str(models / "lin2020"), "--steps", "1", "--lr", "1e-12",
                          "--patch", "32", "--batch", "2", "--threads", "2", "--device", "cpu"]) == 0
    served = load_checkpoint(tmp_path / "served" / "best.pt")[0]
    exported = load_checkpoint(tmp_path / "run" / "best.pt")[0]
    for c in ("diffuse", "specular"):
        assert served[c].config == exported[c].config
        for k, v in exported[c].state_dict().items():
            assert torch.equal(served[c].state_dict()[k], v.half().float()), (c, k)
    with pytest.raises(SystemExit, match="--reshape narrows the production network"):
        train_ms.main(["--data", str(root), "--out", str(tmp_path / "x"), "--arch", "lin2020", "--reshape",
                       "--init", str(tmp_path / "run" / "best.pt"), "--steps", "1"])


def test_the_learning_rate_defaults_by_architecture():
    # The paper's network saturates its kernels at the production network's rate
    # (docs/training.md, "The paper's network at its width"); an explicit --lr wins.
    base = ["--data", "d", "--out", "o"]
    for arch, lr in (("msnet", 2e-3), ("lin2020", 5e-5)):
        a = train_ms.parse(base + ["--arch", arch])
        assert a.lr is None and train_ms.PEAK_LR[arch] == lr
    assert train_ms.parse(base + ["--arch", "lin2020", "--lr", "1e-4"]).lr == 1e-4


def test_as_beauty_is_a_frame_without_the_split():
    from mcdenoise_train.preprocess import COV, DEPTH, as_beauty

    g = torch.Generator().manual_seed(3)
    raw, ref = torch.rand(2, len(RAW), 8, 8, generator=g), torch.rand(2, 6, 8, 8, generator=g)
    b, r = as_beauty(raw, ref, keep_depth=torch.tensor([True, False]))
    assert torch.equal(b[:, DIFFUSE], raw[:, DIFFUSE] + raw[:, SPECULAR])
    assert float(b[:, SPECULAR].abs().max()) == 0 and float(b[:, COV].abs().max()) == 0
    assert float(b[:, VAR["diffuse"]:VAR["covariance"] + 1].abs().max()) == 0
    assert torch.equal(b[0, DEPTH], raw[0, DEPTH]) and float(b[1, DEPTH].abs().max()) == 0
    assert torch.equal(r[:, :3], ref[:, :3] + ref[:, 3:]) and float(r[:, 3:].abs().max()) == 0
    assert torch.equal(b[:, 6:12], raw[:, 6:12]), "albedo and normal unchanged"
    assert not torch.equal(raw[:, SPECULAR], torch.zeros_like(raw[:, SPECULAR])), "the input is not changed"


def test_beauty_training_exports_the_beauty_variant(tmp_path):
    root = make_dataset(tmp_path / "d", frames=3, size=48)
    models = tmp_path / "models"
    assert train_ms.main(["--data", str(root), "--out", str(tmp_path / "run"), "--beauty", "--steps", "2",
                          "--ext-width", "4", "--enc", "6,6,8,8", "--dec", "6,6,8,8", "--patch", "32", "--batch", "2",
                          "--threads", "2", "--device", "cpu", "--export", str(models)]) == 0
    assert sorted(p.name for p in models.iterdir()) == ["beauty"]
    meta = read_metadata_v2(models / "beauty" / "model.onnx")
    assert meta["mcdenoise.variant"] == "beauty" and "covariance" not in meta["mcdenoise.features"]
    val = [json.loads(l) for l in open(tmp_path / "run" / "val.jsonl")]
    assert val and all(np.isfinite(v["relmse"]) and "nocov" not in v for v in val)


def test_crops_are_the_frames_windows():
    class Frames:
        raw = torch.randn(3, 20, 40, 36)
        ref = torch.randn(3, 6, 40, 36)
        maxima = torch.rand(3, 2)

        def __len__(self):
            return 3

    fs = Frames()
    g = torch.Generator().manual_seed(3)
    raw, ref, maxima = train_ms.crops(fs, 5, 16, g)
    # The same draws, made again, name each crop's frame and corner.
    g = torch.Generator().manual_seed(3)
    f = torch.randint(0, 3, (5,), generator=g)
    ys, xs = torch.randint(0, 40 - 17 + 1, (5,), generator=g), torch.randint(0, 36 - 17 + 1, (5,), generator=g)
    assert raw.shape == (5, 20, 17, 17) and ref.shape == (5, 6, 17, 17)
    for k in range(5):
        i, y, x = int(f[k]), int(ys[k]), int(xs[k])
        assert torch.equal(raw[k], fs.raw[i, :, y:y + 17, x:x + 17])
        assert torch.equal(ref[k], fs.ref[i, :, y:y + 17, x:x + 17])
        assert torch.equal(maxima[k], fs.maxima[i])


def test_a_time_budget_is_refitted_on_the_rate_of_later_steps():
    # Fitted at step 50 on a slow start (0.7 steps/s over 70 s of a 300-s budget), the
    # schedule is short; refitted at step 250 on the steady rate, it fills the budget.
    first = train_ms.fitted_steps(50, 0.7, 300.0, 70.0)
    assert first == int(50 + 0.7 * (0.95 * 300 - 70))
    again = train_ms.fitted_steps(250, 12.0, 300.0, 87.0)
    assert again == int(250 + 12.0 * (0.95 * 300 - 87))
    assert again > 10 * first
    # Past the budget, the schedule still has steps left to anneal the learning rate.
    assert train_ms.fitted_steps(1000, 12.0, 300.0, 320.0) == 1100
    assert 250 in train_ms.FIT_AT and 50 in train_ms.FIT_AT


def _tiny_start(tmp_path, *extra):
    """The arguments of a tiny network's runs on a tiny data set (`extra` appended), and a
    one-step run of them to start fine-tunes from."""
    root = make_dataset(tmp_path / "d", frames=3, size=48)
    small = ["--data", str(root), "--ext-width", "4", "--enc", "6,6,8,8", "--dec", "6,6,8,8", "--patch", "32",
             "--batch", "2", "--threads", "2", "--device", "cpu", *extra]
    start = tmp_path / "start"
    assert train_ms.main([*small, "--out", str(start), "--steps", "1"]) == 0
    return small, start


def test_a_moving_average_of_the_weights_is_what_is_validated_and_kept(tmp_path):
    small, start = _tiny_start(tmp_path, "--val-every", "1", "--lr", "0.05")
    init = load_msnet(start / "best.pt")[0].state_dict()
    # A decay this close to 1 keeps the average at the weights it started from (those of
    # --init): every validation scores the start again, although the trained weights moved.
    slow = tmp_path / "slow"
    assert train_ms.main([*small, "--out", str(slow), "--steps", "3", "--init", str(start / "best.pt"),
                          "--ema", "0.999999"]) == 0
    rows = [json.loads(l) for l in open(slow / "val.jsonl")]
    assert [r["step"] for r in rows] == [0, 1, 2, 3]
    assert all(r["score"] == pytest.approx(rows[0]["score"], abs=1e-4) for r in rows)
    state = load_state(slow / "state.pt")
    trained = {k: v for k, v in state["model"].items()}
    averaged = {k[len("module."):]: v for k, v in state["ema"].items() if k.startswith("module.")}
    assert max(float((trained[k] - init[k]).abs().max()) for k in init) > 1e-3
    assert max(float((averaged[k] - init[k]).abs().max()) for k in init) < 1e-4
    # Resumed, the average continues from the saved one (not from the trained weights).
    assert train_ms.main([*small, "--out", str(slow), "--steps", "4", "--init", str(start / "best.pt"),
                          "--ema", "0.999999", "--resume"]) == 0
    averaged = {k[len("module."):]: v for k, v in load_state(slow / "state.pt")["ema"].items()
                if k.startswith("module.")}
    assert max(float((averaged[k] - init[k]).abs().max()) for k in init) < 1e-4
    with pytest.raises(SystemExit, match="below 1"):
        train_ms.main([*small, "--out", str(slow), "--steps", "1", "--ema", "1"])


def test_a_blend_shift_raises_the_blends_of_the_network_a_fine_tune_starts_from(tmp_path):
    small, start = _tiny_start(tmp_path, "--val-every", "1")
    before = load_msnet(start / "best.pt")[0].state_dict()
    shifted = tmp_path / "shifted"
    assert train_ms.main([*small, "--out", str(shifted), "--steps", "1", "--lr", "1e-12", "--init",
                          str(start / "best.pt"), "--blend-shift", "3"]) == 0
    after = load_state(shifted / "state.pt")["model"]
    heads = [k for k in before if k.startswith("blend_heads.") and k.endswith(".bias")]
    assert heads and all(torch.allclose(after[k], before[k] + 3, atol=1e-4) for k in heads)
    others = [k for k in before if k not in heads]
    assert all(torch.allclose(after[k], before[k], atol=1e-6) for k in others)
    # The network to beat (step 0, kept as best.pt until beaten) is the start before the
    # shift: the score a run without the shift gives it, not the shifted network's.
    plain = tmp_path / "plain"
    assert train_ms.main([*small, "--out", str(plain), "--steps", "1", "--lr", "1e-12", "--init",
                          str(start / "best.pt")]) == 0
    scores = lambda run: [json.loads(line)["score"] for line in (run / "val.jsonl").read_text().splitlines()]  # noqa: E731
    assert scores(shifted)[0] == pytest.approx(scores(plain)[0], abs=1e-6)
    assert abs(scores(shifted)[1] - scores(shifted)[0]) > 1e-4
    with pytest.raises(SystemExit, match="--blend-shift raises"):
        train_ms.main([*small, "--out", str(shifted), "--steps", "1", "--blend-shift", "3"])


def test_a_fine_tune_adds_detail_gains_and_they_learn(tmp_path):
    from mcdenoise_train.msnet import GAIN_START

    small, start = _tiny_start(tmp_path, "--val-every", "2")
    gain = tmp_path / "gain"
    assert train_ms.main([*small, "--out", str(gain), "--steps", "4", "--lr", "0.01", "--init",
                          str(start / "best.pt"), "--detail-gain", "--export", str(tmp_path / "models")]) == 0
    model = load_state(gain / "state.pt")["model"]
    biases = torch.cat([model[k] for k in model if k.startswith("gain_heads.") and k.endswith(".bias")])
    assert biases.numel() and float((biases - GAIN_START).abs().max()) > 1e-3  # the heads trained
    # The network to beat is the start without gains (step 0); every later row is the one with them.
    rows = [json.loads(line) for line in (gain / "val.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [0, 2, 4]
    # Resumed, the heads are there again; a fresh network with --detail-gain has them too.
    assert train_ms.main([*small, "--out", str(gain), "--steps", "5", "--lr", "0.01", "--init",
                          str(start / "best.pt"), "--detail-gain", "--resume"]) == 0
    assert json.loads((gain / "val.jsonl").read_text().splitlines()[-1])["step"] == 5
    fresh = tmp_path / "fresh"
    assert train_ms.main([*small, "--out", str(fresh), "--steps", "1", "--detail-gain"]) == 0
    assert any(k.startswith("gain_heads.") for k in load_state(fresh / "state.pt")["model"])
    # --train-only gains: every other weight stays the checkpoint's.
    only = tmp_path / "only"
    assert train_ms.main([*small, "--out", str(only), "--steps", "3", "--lr", "0.01", "--init",
                          str(start / "best.pt"), "--detail-gain", "--train-only", "gains"]) == 0
    before, after = load_msnet(start / "best.pt")[0].state_dict(), load_state(only / "state.pt")["model"]
    assert all(torch.equal(after[k], v) for k, v in before.items())
    assert any(not torch.equal(after[k], torch.full_like(after[k], GAIN_START)) for k in after
               if k.startswith("gain_heads.") and k.endswith(".bias"))
    with pytest.raises(SystemExit, match="needs --detail-gain"):
        train_ms.main([*small, "--out", str(tmp_path / "x"), "--steps", "1", "--train-only", "gains"])
    # --train-only gains,blends: those two kinds of heads move, the kernel heads and the trunk stay.
    heads = tmp_path / "heads"
    assert train_ms.main([*small, "--out", str(heads), "--steps", "3", "--lr", "0.01", "--init",
                          str(start / "best.pt"), "--detail-gain", "--train-only", "gains,blends"]) == 0
    after = load_state(heads / "state.pt")["model"]
    moved = {k for k, v in before.items() if not torch.equal(after[k], v)}
    assert moved and all(k.startswith("blend_heads.") for k in moved)
    with pytest.raises(SystemExit):
        train_ms.main([*small, "--out", str(tmp_path / "y"), "--steps", "1", "--train-only", "gains,trunk"])


def test_blend_excess_is_zero_inside_the_bound_and_quadratic_beyond():
    levels = 2
    kernels = [torch.zeros(1, 4, 4, 4), torch.zeros(1, 4, 2, 2)]
    inside = [torch.full((1, 2, 4, 4), 3.9)]
    assert float(train_ms.blend_excess([*kernels, *inside], levels, 4.0)) == 0.0
    # Half the logits 2 beyond the bound (either side), half inside: mean (2²) / 2.
    beyond = torch.full((1, 2, 4, 4), 1.0)
    beyond[:, 0], beyond[:, 1, :2] = -6.0, 6.0
    assert abs(float(train_ms.blend_excess([*kernels, beyond], levels, 4.0)) - (4.0 * 24 / 32)) < 1e-6


def test_a_blend_bound_reopens_saturated_blends_that_a_fine_tune_leaves_shut(tmp_path):
    small, start = _tiny_start(tmp_path, "--val-every", "100", "--ema", "0")
    net = load_msnet(start / "best.pt")[0]
    with torch.no_grad():
        for head in net.blend_heads:  # every blend at sigmoid(-10): shut, as a trained network's can be
            head.weight.zero_()
            head.bias.fill_(-10.0)
    save_msnet(tmp_path / "shut.pt", net, step=0)

    def blend_biases(run: str, *extra: str) -> torch.Tensor:
        assert train_ms.main([*small, "--out", str(tmp_path / run), "--steps", "20", "--lr", "0.05",
                              "--init", str(tmp_path / "shut.pt"), *extra]) == 0
        model = load_state(tmp_path / run / "state.pt")["model"]
        return torch.cat([model[k] for k in model if k.startswith("blend_heads.") and k.endswith(".bias")])

    left = blend_biases("plain")
    bounded = blend_biases("bounded", "--blend-bound", "4", "--blend-penalty", "1")
    # The loss alone passes almost no gradient through sigmoid(-10), and what Adam makes of
    # it moves the logits either way; the penalty pulls every one of them towards the bound.
    assert float((left + 10).abs().max()) < 0.5, left
    assert float(bounded.min()) > -10 + 0.15, bounded
    logged = [json.loads(line) for line in (tmp_path / "bounded" / "log.jsonl").read_text().splitlines()]
    assert logged[-1]["blend_excess"] > 0
    assert all("blend_excess" not in json.loads(line) for line in (tmp_path / "plain" / "log.jsonl").read_text().splitlines())
    with pytest.raises(SystemExit, match="lin2020 has none"):
        train_ms.main([*small, "--out", str(tmp_path / "x"), "--steps", "1", "--arch", "lin2020", "--blend-bound", "4"])


def test_relmse_loss_is_the_metric_within_delta_and_linear_beyond():
    r = torch.full((1, 3, 4, 4), 0.1)
    x = r.clone()
    x[0, :, 1, 1] = 0.1 + 0.5 * math.sqrt(0.02)  # e = 0.5: e² = 0.25
    assert float(train_ms.losses.relmse_huber(x, r)) == pytest.approx(float(train_ms.losses.relmse(x, r)), rel=1e-5)
    # A pixel lifted 20x its scale (an emitter's leak), delta 10: 2·10·20 − 100 = 300, not 400.
    x[0, :, 1, 1] = 0.1 + 20 * math.sqrt(0.02)
    assert float(train_ms.losses.relmse_huber(x, r)) * x.numel() / 3 == pytest.approx(300, rel=1e-4)
    assert float(train_ms.losses.relmse(x, r)) * x.numel() / 3 == pytest.approx(400, rel=1e-4)
    # Its gradient is the metric's where the metric is quadratic and bounded beyond.
    x.requires_grad_(True)
    train_ms.losses.relmse_huber(x, r).backward()
    assert float(x.grad[0, 0, 1, 1]) == pytest.approx(2 * 10 / math.sqrt(0.02) / x.numel(), rel=1e-4)


def _logged_rows(tiny, run, *options: str) -> list[dict]:
    """The training log's rows of 20 steps into `run` from the tiny start (`_tiny_start`'s
    pair) with `options`."""
    small, start = tiny
    assert train_ms.main([*small, "--out", str(run), "--steps", "20", "--init", str(start / "best.pt"), *options]) == 0
    rows = [json.loads(line) for line in open(run / "log.jsonl") if '"loss"' in line]
    assert rows
    return rows


def test_relmse_weight_enters_the_loss_and_the_log(tmp_path):
    tiny = _tiny_start(tmp_path)
    rows = _logged_rows(tiny, tmp_path / "rel", "--relmse", "1")
    assert all(np.isfinite(r["relmse"]) and r["relmse"] > 0 for r in rows)
    assert all("relmse" not in r for r in _logged_rows(tiny, tmp_path / "plain"))


def test_ms_ssim_sees_blotches_that_single_scale_ssim_barely_sees(tmp_path):
    import torch.nn.functional as F

    g = torch.Generator().manual_seed(3)
    r = F.avg_pool2d(torch.rand(1, 3, 128, 128, generator=g), 9, 1, 4) * 0.6 + 0.2
    assert float(train_ms.losses.ms_ssim(r, r)) == pytest.approx(1.0, abs=1e-6)
    # Noise of the same energy, at the pixel scale and in blotches of 8 pixels (what a
    # kernel that only reweights a few noisy pixels leaves at low sample counts).
    fine = torch.randn(1, 3, 128, 128, generator=g)
    blotches = F.interpolate(torch.randn(1, 3, 16, 16, generator=g), scale_factor=8, mode="bilinear")
    fine, blotches = (r + 0.05 * n / n.std() for n in (fine, blotches))
    dssim = {k: float(train_ms.losses.dssim(x, r)) for k, x in (("fine", fine), ("blotches", blotches))}
    dms = {k: 1 - float(train_ms.losses.ms_ssim(x, r)) for k, x in (("fine", fine), ("blotches", blotches))}
    assert dssim["blotches"] < 0.5 * dssim["fine"] and dms["blotches"] > 1.5 * dms["fine"]
    # 128² has four scales (a fifth, 8², would be smaller than the window); 12² has one;
    # below the window's 11 pixels there is none.
    assert 0 < 1 - float(train_ms.losses.ms_ssim(fine[..., :12, :12], r[..., :12, :12])) < 1
    with pytest.raises(ValueError, match="at least 11x11"):
        train_ms.losses.ms_ssim(r[..., :10, :10], r[..., :10, :10])
    # In training: the weight enters the loss and the log.
    rows = _logged_rows(_tiny_start(tmp_path), tmp_path / "ms", "--msssim", "0.5")
    assert all(np.isfinite(r["msssim"]) and 0 < r["msssim"] < 1 for r in rows)


def test_level_loss_holds_every_coarser_level_to_the_averaged_target(tmp_path):
    from mcdenoise_train.recon_ms import Reconstruction, color_pyramid

    g = torch.Generator().manual_seed(7)
    b = {"diffuse_target": torch.rand(1, 3, 16, 16, generator=g),
         "specular_target": torch.log1p(torch.rand(1, 3, 16, 16, generator=g) ** 4 * 20)}
    dl, sl = color_pyramid(b["diffuse_target"], 3, "log"), color_pyramid(b["specular_target"], 3, "linear")
    rec = Reconstruction(dl[0], sl[0], None, None, None, tuple(dl[1:]), tuple(sl[1:]))
    assert float(train_ms.losses.level_smape(rec, b, "linear")) == pytest.approx(0.0, abs=1e-6)
    # The specular's levels are held to its own pyramid: the log pyramid's means are not those.
    assert float(train_ms.losses.level_smape(rec, b, "log")) > 0.01
    worse = rec._replace(diffuse_levels=(dl[1] * 1.5, dl[2]))
    assert float(train_ms.losses.level_smape(worse, b, "linear")) > 0.01
    # In training: the weight enters the loss and the log; the option is the production network's.
    tiny = _tiny_start(tmp_path)
    assert all(np.isfinite(r["levels"]) and r["levels"] > 0 for r in _logged_rows(tiny, tmp_path / "levels", "--level-loss", "0.5"))
    small, _ = tiny
    with pytest.raises(SystemExit, match="lin2020 has none"):
        train_ms.main([*small, "--out", str(tmp_path / "x"), "--steps", "1", "--arch", "lin2020", "--level-loss", "1"])

"""Data generator: renders tiny frames with Mitsuba 3 (LLVM) and checks their invariants.

- every channel of docs/frame-layout.md is written, with the names the engine reads;
- diffuse + specular = colour, per pixel, within float rounding;
- the variance channels agree with the observed squared error against an independent
  reference: mean(w (x - ref)^2) / mean(w (Var[x] + Var[ref])), w = 1 / (ref^2 + 0.01),
  within a factor 2 (0.5 to 2), per buffer (the expectation is 1);
- covariance is in [0, 1] and at least 5x larger on the shadow edge of `shadow_test`
  than on its flat, lit, diffuse floor;
- the covariance operators: a flat mirror is plain travel, a concave mirror of curvature
  k focuses collimated light at 1/(2k);
- the data set CLI writes a manifest, splits by scene and resumes;
- the committed fixture frames are complete and small;
- Blender Cycles frames (when a Python with bpy is installed, scripts/setup-bpy): every
  channel present, diffuse + specular (each from its own passes) = Combined, variances
  from independent renders agree with the observed error (factor 2), and the engine reads
  them with no variance missing.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mcdenoise_train.datagen.backend import set_variant

mi = set_variant("llvm_ad_rgb")

import drjit as dr  # noqa: E402

from mcdenoise_train.datagen import covariance as cv  # noqa: E402
from mcdenoise_train import exr  # noqa: E402
from mcdenoise_train.datagen import cycles, dataset, render, scenes  # noqa: E402
from mcdenoise_train.files import read_manifest  # noqa: E402
from mcdenoise_train.datagen.integrator import LUM, Options  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
FRAMES = REPO / "tests" / "fixtures" / "frames"
LAYOUT = {
    "R", "G", "B", "colorVariance.Z", "diffuse.R", "diffuse.G", "diffuse.B", "diffuseVariance.Z",
    "specular.R", "specular.G", "specular.B", "specularVariance.Z", "albedo.R", "albedo.G", "albedo.B",
    "albedoVariance.Z", "normal.R", "normal.G", "normal.B", "normalVariance.Z", "depth.Z", "depthVariance.Z",
    "covariance", "covarianceVariance.Z",
}
VARIANCE_FACTOR = 2.0


def _render(spec, w, h, spp, seed):
    scene = scenes.build(spec, w, h)
    pa = scenes.camera_params(spec, w)["pixel_angle"]
    return render.render(scene, w, h, spp, seed, pa, Options())


@pytest.fixture(scope="module")
def cornell():
    spec = scenes.cornell(5)  # glossy sphere and a box: diffuse and specular both present
    return _render(spec, 48, 48, 16, 1), _render(spec, 48, 48, 512, 10**6)


@pytest.fixture(scope="module")
def shadow():
    spec = scenes.shadow_test()
    return _render(spec, 64, 64, 16, 1), _render(spec, 64, 64, 512, 10**6)


def test_all_channels_written(cornell, tmp_path):
    ch, meta = render.frame_channels(cornell[0])
    exr.write_frame(tmp_path / "f.exr", ch, meta)
    back, meta2 = exr.read_frame(tmp_path / "f.exr")
    assert set(back) == LAYOUT
    assert set(exr.CHANNELS) == LAYOUT
    for k, v in back.items():
        assert v.shape == (48, 48) and v.dtype == np.float32, k
        assert np.isfinite(v).all(), k
    assert meta2["spp"] == 16
    assert all(np.all(back[f"{b}Variance.Z"] >= 0) for b in ("color", "diffuse", "specular", "albedo", "normal", "depth", "covariance"))
    assert exr.is_complete(tmp_path / "f.exr")


def test_diffuse_plus_specular_is_color(cornell):
    ch, _ = render.frame_channels(cornell[0])
    for c in "RGB":
        total = ch[c]
        split = ch[f"diffuse.{c}"] + ch[f"specular.{c}"]
        assert np.all(np.abs(split - total) <= 1e-5 * (1.0 + np.abs(total))), c
    # both components carry light in this scene (the split is not trivial)
    assert ch["diffuse.G"].mean() > 0.05 and ch["specular.G"].mean() > 0.005


@pytest.mark.parametrize("which", ["cornell", "shadow"])
@pytest.mark.parametrize("buf", ["color", "diffuse", "specular", "albedo", "normal", "depth", "cov"])
def test_variance_matches_error(which, buf, request):
    noisy, ref = request.getfixturevalue(which)

    def mv(m):
        if buf == "cov":  # energy-weighted mean of the per-sample feature, before normalisation
            r, v = m.cov_mean_and_var()
            return r[..., None], v[..., None]
        return m.mean[buf], m.var_of_mean(buf)

    (xn, vn), (xr, vr) = mv(noisy), mv(ref)
    nc = xn.shape[-1]
    w = LUM if nc == 3 else (1.0,)
    # relative weighting 1 / (ref^2 + 0.01) (as in relMSE): keeps a few bright fireflies from
    # deciding the ratio; it does not change its expectation (the weights are fixed by the
    # independent reference)
    rel = 1.0 / (sum(w[c] * xr[..., c] for c in range(nc)) ** 2 + 0.01)
    err = sum(w[c] * (xn[..., c] - xr[..., c]) ** 2 for c in range(nc)) * rel
    var = sum(w[c] * (vn[..., c] + vr[..., c]) for c in range(nc)) * rel
    if var.mean() < 1e-12:  # buffer without noise in this scene (e.g. specular of shadow_test)
        assert err.mean() < 1e-10
        return
    ratio = err.mean() / var.mean()
    assert 1 / VARIANCE_FACTOR < ratio < VARIANCE_FACTOR, f"{which}/{buf}: error/variance = {ratio:.3f}"


def test_reference_error_below_input(cornell):
    noisy, ref = cornell
    rv = ref.var_of_mean("color").mean()
    nv = noisy.var_of_mean("color").mean()
    assert rv < nv / 10  # 512 vs 16 spp: expected 1/32


def test_covariance_range_and_shadow_edge(shadow):
    noisy, ref = shadow
    for m in (noisy, ref):
        ch, meta = render.frame_channels(m)
        cov = ch["covariance"]
        assert cov.min() >= 0 and cov.max() <= 1 and meta["covariance_scale"] > 0
        col = scenes.shadow_test_edge_column(64)  # edge between columns 31 and 32
        lum = ch["R"]
        edge = cov[8:56, int(col) - 2:int(col) + 2]
        # flat diffuse floor on the lit side, far from the edge and the wall
        flat = cov[8:56, 2:20]
        assert lum[8:56, 2:20].min() > 0.1  # lit
        assert edge.mean() > 5 * flat.mean(), (edge.mean(), flat.mean())


def _cov_full(S):
    return np.block([[np.array([[float(S.A[i][j][0]) for j in range(2)] for i in range(2)]),
                      np.array([[float(S.B[i][j][0]) for j in range(2)] for i in range(2)])],
                     [np.array([[float(S.B[j][i][0]) for j in range(2)] for i in range(2)]),
                      np.array([[float(S.C[i][j][0]) for j in range(2)] for i in range(2)])]])


def test_covariance_flat_mirror_is_travel():
    V = mi.Vector3f
    geo = cv.SurfaceGeo(V(0, 1, 0), V(1, 0, 0), V(0, 0, 1), cv.eye2(mi.Float(0.0)))
    wi, wo = dr.normalize(V(1, -1, 0)), dr.normalize(V(1, 1, 0))
    S = cv.light_at_receiver(mi.Float(50.0), mi.Float(2.0), mi.Float(0.0), cv.zeros2())
    S1 = cv.travel(cv.specular_transfer(S, geo, wi, cv.basis(-wi), wo, cv.basis(-wo), mi.Bool(False),
                                        mi.Float(1.0), mi.Float(cv.B_INFINITE)), mi.Float(1.5))
    S2 = cv.light_at_receiver(mi.Float(50.0 * (3.5 / 2.0) ** 2), mi.Float(3.5), mi.Float(0.0), cv.zeros2())
    np.testing.assert_allclose(np.linalg.eigvalsh(_cov_full(S1)), np.linalg.eigvalsh(_cov_full(S2)), rtol=1e-3, atol=1e-3)


def test_covariance_concave_mirror_focuses():
    V = mi.Vector3f
    wi, wo = V(0, -1, 0), V(0, 1, 0)
    S0 = cv.light_at_receiver(mi.Float(1e4), mi.Float(float("inf")), mi.Float(0.0), cv.zeros2())
    ds = np.linspace(0.0, 2.0, 41)
    for k, focus in ((-1.0, 0.5), (-0.5, 1.0)):
        geo = cv.SurfaceGeo(V(0, 1, 0), V(1, 0, 0), V(0, 0, 1), cv.eye2(mi.Float(k)))
        S1 = cv.specular_transfer(S0, geo, wi, cv.basis(-wi), wo, cv.basis(-wo), mi.Bool(False), mi.Float(1.0),
                                  mi.Float(cv.B_INFINITE))
        irr = []
        for d in ds:  # spatial frequency of the irradiance a diffuse receiver at distance d sees
            St = cv.travel(S1, mi.Float(float(d)))
            irr.append(float((St.A - St.B @ cv.inv2(St.C + cv.eye2(1e-3)) @ cv.T(St.B))[0][0][0]))
        assert abs(ds[int(np.argmax(irr))] - focus) < 0.06


def test_scene_generator_is_seeded_and_varied():
    a, b = scenes.generate(42), scenes.generate(42)
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)
    kinds = {scenes.generate(s)["kind"] for s in range(60)}
    assert kinds == set(scenes.KINDS)
    mats = {o["material"]["type"] for s in range(30) for o in scenes.generate(s)["objects"] if "material" in o}
    assert {"diffuse", "roughplastic", "roughconductor", "dielectric"} <= mats
    for s in range(3):
        scenes.build(scenes.generate(s), 8, 8)  # loads (meshes, textures, instances)


@pytest.mark.parametrize("family", scenes.KINDS)
def test_every_family_is_seeded_and_loads(family):
    a, b = scenes.generate(7, family), scenes.generate(7, family)
    assert a == b and a["kind"] == family and scenes.generate(8, family) != a
    scene = scenes.build(a, 8, 8)  # curves, leaves, water, bump maps, emissive shapes load
    assert len(scene.emitters()) >= 1 and len(scene.shapes()) >= 2


def test_dataset_cli_manifest_split_resume(tmp_path):
    out, test_out = tmp_path / "d", tmp_path / "d-test"
    args = ["--out", str(out), "--scenes", "2", "--size", "16", "--spp", "1,2,4", "--ref-spp", "8",
            "--val-fraction", "0.5", "--no-progress", "--families", "cornell", "--test-scenes", "1"]
    assert dataset.main(args) == 0
    recs = read_manifest(out / "manifest.jsonl")
    assert [r["split"] for r in recs] == ["train", "val"]
    for r in recs:
        assert r["seed"] < dataset.TEST_SEED_BASE and (r["renderer"], r["family"]) == ("mitsuba", "cornell")
        assert set(r["frames"]) == {"1", "2", "4", "ref"}
        for k, f in r["frames"].items():
            assert exr.is_complete(out / f["path"], exr.CHANNELS if k != "ref" else exr.CHANNELS_NOCOV)
            assert f["seed"] == r["seed"] and f["spp"] == (8 if k == "ref" else int(k))
        # the reference's noise floor is recorded and lies below every input's error
        assert 0 < r["frames"]["ref"]["noise_floor"] < min(r["frames"][s]["rel_error"] for s in ("1", "2", "4"))
        assert r["ref_clean"] == (max(r["frames"][s]["noise_floor_ratio"] for s in ("1", "2", "4"))
                                  <= dataset.CLEAN_REF_RATIO)
        assert all(np.isfinite(v) and v > 0 for v in r["ref_variance_ratio"]["1"].values())
        assert r["timings"]["noisy"]["seconds"] > 0 and r["timings"]["ref"]["seconds"] > 0
    # the test set: its own directory, disjoint seeds, split "test"
    (t,) = read_manifest(test_out / "manifest.jsonl")
    assert t["split"] == "test" and t["seed"] >= dataset.TEST_SEED_BASE
    assert (test_out / t["frames"]["ref"]["path"]).is_file() and not list(out.glob("test"))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["rendered"] == 3 and summary["frames"] == 12
    assert summary["mean_seconds_per_scene"]["noisy"]["seconds"] > 0
    # resume: nothing to do; then one missing frame makes that scene render again
    assert dataset.main(args) == 0
    assert json.loads((out / "summary.json").read_text())["skipped"] == 3
    (out / recs[1]["frames"]["2"]["path"]).unlink()
    assert dataset.main(args) == 0
    s = json.loads((out / "summary.json").read_text())
    assert (s["rendered"], s["skipped"]) == (1, 2)
    assert not list(tmp_path.rglob("*.tmp"))
    # a test set never shares a directory with training data
    with pytest.raises(SystemExit):
        dataset.main(["--out", str(tmp_path / "x"), "--test-out", str(out), "--scenes", "0", "--test-scenes", "1",
                      "--size", "8", "--spp", "2", "--ref-spp", "4", "--no-progress"])


def test_dataset_workers_share_one_manifest(tmp_path):
    args = ["--out", str(tmp_path), "--scenes", "3", "--size", "12", "--spp", "2,4", "--ref-spp", "4",
            "--no-progress", "--families", "cornell", "--workers", "2"]
    assert dataset.main(args) == 0
    recs = read_manifest(tmp_path / "manifest.jsonl")
    assert sorted(r["index"] for r in recs) == [0, 1, 2] and all(r["complete"] for r in recs)
    assert sorted(r["worker"] for r in recs) == [0, 0, 1]  # scene i on worker i mod 2
    assert len((tmp_path / "manifest.jsonl").read_text().splitlines()) == 3
    assert dataset.main(args) == 0
    assert json.loads((tmp_path / "summary.json").read_text())["skipped"] == 3


def test_dataset_time_limit_and_bad_arguments(tmp_path):
    args = ["--out", str(tmp_path), "--scenes", "3", "--test-scenes", "1", "--size", "8", "--spp", "2",
            "--ref-spp", "4", "--no-progress", "--max-minutes", "0"]
    assert dataset.main(args) == 0  # the deadline has passed before the first scene
    s = json.loads((tmp_path / "summary.json").read_text())
    assert (s["rendered"], s["not_started"]) == (0, 4)
    for bad in (["--families", "cornell,nosuch"], ["--workers", "0"], ["--seed-base", str(dataset.TEST_SEED_BASE)],
                ["--spp", "0,4"], ["--renderer", "cycles", "--frames", "ref"]):
        with pytest.raises(SystemExit):
            dataset.parse_args(["--out", str(tmp_path)] + bad)


def test_half_precision_frames(cornell, tmp_path):
    import OpenEXR

    ch, meta = render.frame_channels(cornell[0])
    exr.write_frame(tmp_path / "h.exr", ch, meta, precision="half")
    with OpenEXR.File(str(tmp_path / "h.exr"), separate_channels=True) as f:
        types = {k: c.pixels.dtype for k, c in f.channels().items()}
        assert f.header()["compression"] == OpenEXR.PXR24_COMPRESSION
    assert all(t == (np.float32 if "Variance" in k else np.float16) for k, t in types.items()), types
    back, _ = exr.read_frame(tmp_path / "h.exr")
    for k, v in ch.items():
        np.testing.assert_allclose(back[k], v, rtol=1e-3, atol=1e-4 if "Variance" not in k else 0, err_msg=k)


def test_one_spp_frame_has_variance():
    spec = scenes.cornell(5)
    scene = scenes.build(spec, 24, 24)
    pa = scenes.camera_params(spec, 24)["pixel_angle"]
    frames = {}
    render.render_ladder(scene, 24, 24, [1, 4], 3, pa, Options(), on_frame=lambda s, m, t: frames.update({s: m}))
    assert sorted(frames) == [1, 4] and frames[1].n == 1 and frames[4].n == 4
    v1, v4 = frames[1].var_of_mean("color").mean(), frames[4].var_of_mean("color").mean()
    assert v1 > 0 and 2.0 < v1 / v4 < 8.0  # expected 4


def test_committed_fixture_frames():
    files = sorted(FRAMES.glob("*.exr"))
    names = {f.name for f in files}
    assert {"cornell-spp8.exr", "cornell-ref.exr", "cornell-nocov-spp8.exr", "caustic-spp8.exr", "caustic-ref.exr"} <= names
    assert sum(f.stat().st_size for f in files) < 5 * 2**20
    for f in files:
        ch, _ = exr.read_frame(f)
        want = LAYOUT - {"covariance", "covarianceVariance.Z"} if "nocov" in f.name else LAYOUT
        assert set(ch) == want, f.name


needs_bpy = pytest.mark.skipif(not cycles.available(), reason="no Python with bpy (run scripts/setup-bpy)")


@pytest.fixture(scope="module")
def cycles_frames():
    # 24x24 Cornell box: 16 spp (8 renders of 2) and an independent 512-spp reference
    return cycles.render_frames(scenes.cornell(5), 24, 24, [16], 512, 5)[0]


@needs_bpy
def test_cycles_frame_channels_and_split(cycles_frames, tmp_path):
    ch, meta = cycles_frames[16]
    assert set(ch) == set(exr.CHANNELS_NOCOV) and meta == {"spp": 16, "renders": 8}
    assert all(np.isfinite(v).all() and v.shape == (24, 24) for v in ch.values())
    for c in "RGB":  # specular is built from the glossy/transmission/emission/environment passes
        split = ch[f"diffuse.{c}"] + ch[f"specular.{c}"]
        assert np.all(np.abs(split - ch[c]) <= 1e-4 * (1.0 + np.abs(ch[c]))), c
    assert ch["diffuse.G"].mean() > 0.05 and ch["specular.G"].mean() > 0.005
    assert ch["depth.Z"].max() < 100 and (ch["albedo.G"] > 0).mean() > 0.9


@needs_bpy
@pytest.mark.parametrize("buf", ["color", "diffuse", "specular"])
def test_cycles_variance_matches_error(cycles_frames, buf):
    (xn, _), (xr, _) = cycles_frames[16], cycles_frames["ref"]
    names = ("R", "G", "B") if buf == "color" else tuple(f"{buf}.{c}" for c in "RGB")
    lum = lambda ch: sum(w * ch[n] for w, n in zip(LUM, names))  # noqa: E731
    rel = 1.0 / (lum(xr) ** 2 + 0.01)
    err = sum(w * (xn[n] - xr[n]) ** 2 for w, n in zip(LUM, names)) * rel
    var = (xn[f"{buf}Variance.Z"] + xr[f"{buf}Variance.Z"]) * rel
    ratio = err.mean() / var.mean()
    assert 1 / VARIANCE_FACTOR < ratio < VARIANCE_FACTOR, f"cycles/{buf}: error/variance = {ratio:.3f}"


@needs_bpy
def test_engine_reads_cycles_frames_with_every_variance(cycles_frames, tmp_path):
    import os
    import subprocess

    binary = os.environ.get("MCDENOISE_BIN") or str(REPO / "target" / "release" / "mcdenoise")
    if not Path(binary).is_file() or not os.environ.get("ORT_DYLIB_PATH"):
        pytest.skip("needs the engine (make build) and ORT_DYLIB_PATH")
    ch, meta = cycles_frames[16]
    exr.write_frame(tmp_path / "c.exr", ch, meta, precision="half")
    r = subprocess.run([binary, "run", str(tmp_path / "c.exr"), "-o", str(tmp_path / "out.exr"),
                        "--models", str(REPO / "models")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    report = json.loads(r.stdout)
    assert report["missing_variances"] == [] and report["variant"] == "nocov"


@needs_bpy
def test_dataset_cli_both_renderers(tmp_path):
    args = ["--out", str(tmp_path), "--scenes", "1", "--size", "12", "--spp", "2,4", "--ref-spp", "16",
            "--no-progress", "--families", "cornell", "--renderer", "both"]
    assert dataset.main(args) == 0
    recs = {r["renderer"]: r for r in read_manifest(tmp_path / "manifest.jsonl")}
    assert set(recs) == {"mitsuba", "cycles"}
    assert recs["cycles"]["scene"] == recs["mitsuba"]["scene"] + "-cycles"
    assert recs["cycles"]["split"] == recs["mitsuba"]["split"] and recs["cycles"]["complete"]
    for k, f in recs["cycles"]["frames"].items():
        ch, meta = exr.read_frame(tmp_path / f["path"])
        assert set(ch) == set(exr.CHANNELS_NOCOV) and f["renderer"] == "cycles"
        assert meta["spp"] == (16 if k == "ref" else int(k))
    assert dataset.main(args) == 0  # resumes: both complete
    assert json.loads((tmp_path / "summary.json").read_text())["skipped"] == 2


def test_engine_reads_half_frames(cornell, tmp_path):
    import os
    import subprocess

    binary = os.environ.get("MCDENOISE_BIN") or str(REPO / "target" / "release" / "mcdenoise")
    if not Path(binary).is_file():
        pytest.skip("needs the engine (make build)")
    for name, m in (("noisy", cornell[0]), ("ref", cornell[1])):
        ch, meta = render.frame_channels(m)
        exr.write_frame(tmp_path / f"{name}.exr", ch, meta, precision="half")
    r = subprocess.run([binary, "preprocess", str(tmp_path / "noisy.exr"), "--reference", str(tmp_path / "ref.exr"),
                        "-o", str(tmp_path / "p.npz")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    z = np.load(tmp_path / "p.npz")
    assert int(z["variant"]) == 1 and z["features"].shape[1:] == (48, 48) and np.isfinite(z["features"]).all()

"""Parity with the Rust engine (`mcdenoise preprocess` and `mcdenoise run`).

The binary is taken from MCDENOISE_BIN (the Makefile sets it, and ORT_DYLIB_PATH for the
engine's onnxruntime). Without it these tests are skipped, or fail when CI is set.

A synthetic 48x40 frame with every channel of docs/frame-layout.md is written as a
float32 single-part EXR, with and without the covariance pair. Small random networks
(separate, width 8, 4 blocks, predictor 3 x 16, receptive radius 13; head weights scaled
so the kernels are far from uniform) are exported for both variants. Then:

1. `preprocess` of the frame without covariance gives 24 feature channels equal to the
   full frame's features at NOCOV_INDICES, and identical color tensors;
2. `preprocess` agrees with the formulas of frame-layout.md, recomputed here in float64;
3. `run --tile 32` (tiles smaller than the frame) agrees with the torch networks run on
   the whole preprocessed frame plus `reconstruct` in float64, for R,G,B and the
   `diffuse.*` / `specular.*` layers. Per sample, |engine - torch| / max(|torch|, 1e-3)
   must be <= 1e-4 when the engine writes float32 (2^-10, half's precision, if it writes
   half).
4. Contract v2: a random multi-scale network (msnet.py, 4 levels, 5x5 kernels, heads
   scaled so kernels and blends are far from uniform) exported by export_ms.py for both
   variants; `run --tile-v2 16` on a 44x60 frame (not a multiple of the size multiple 8, so
   the engine pads; 16-px tiles with a halo of the receptive radius) agrees with the torch
   network on the whole preprocessed frame padded by edge replication (`pad_to_multiple`),
   plus recon_ms's reconstruction, cropped, and v1's inverse transforms, to 1e-5 relative
   (float32 output; measured: 5e-7). The torch side filters in float32 (recon_ms casts to
   it), so the tolerance covers two float32 reconstructions and onnxruntime against torch.
   The network's specular pyramid is the default, `linear`; `full-log` is the same network
   exported with the `log` pyramid of the networks before it.
5. `beauty`: the `nocov` network exported as the `beauty` variant; `preprocess --variant
   beauty` of the frame with the split equals the torch preprocessing of
   `preprocess.as_beauty` (the training side's view of a beauty-only frame), and `run
   --variant beauty` agrees with the torch network on those inputs, as in 4.

The torch reference runs the network on the whole frame, so the conv's zero padding
applies at the frame border only: the engine's tiles must take their context from the
frame (cut at the frame border, not padded) for the two to agree.
"""

import copy
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from mcdenoise_train.contract import COMPONENTS, EPS, NOCOV_INDICES
from mcdenoise_train.export import export_onnx, random_models, scale_head
from mcdenoise_train.exr import exr_pixel_types, read_exr, write_exr
from mcdenoise_train.frames import synthetic_frame
from mcdenoise_train.preprocess import stored_as_engine
from mcdenoise_train.recon import inverse_diffuse, inverse_specular, reconstruct

H, W = 40, 48
TILE = 32
NET = dict(arch="separate", width=8, blocks=4, predictor_width=16, predictor_depth=3)
HEAD_GAIN = 250  # 25x the Xavier scale (the initialisation scales the head by 0.1): sharp random kernels
LUM = np.array([0.2126, 0.7152, 0.0722])


def require_engine() -> str:
    exe = os.environ.get("MCDENOISE_BIN")
    if exe and Path(exe).is_file():
        return exe
    problem = (
        f"MCDENOISE_BIN={exe!r} is not a file: build the engine (`make build`) and set "
        "MCDENOISE_BIN to target/release/mcdenoise (the Makefile's `make test` does both)"
        if exe
        else "MCDENOISE_BIN is not set: run through `make test`, or set it to the built "
        "mcdenoise binary (target/release/mcdenoise)"
    )
    if os.environ.get("CI"):
        pytest.fail(problem, pytrace=False)
    pytest.skip(problem)


def engine(exe: str, *args) -> None:
    cmd = [exe, *map(str, args)]
    # Parity is of the float32 engine: ONNX Runtime's CPU provider, whatever `auto` would
    # choose on this machine (OpenVINO in bfloat16 on a CPU with AMX).
    env = {**os.environ, "MCDENOISE_DEVICE": "cpu"}
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    if p.returncode != 0:
        pytest.fail(
            f"`{' '.join(cmd)}` exited with {p.returncode}\n"
            f"stdout:\n{p.stdout}\nstderr:\n{p.stderr}",
            pytrace=False,
        )


def preprocess(exe: str, frame: Path, out: Path, *args) -> dict[str, np.ndarray]:
    engine(exe, "preprocess", frame, "-o", out, *args)
    with np.load(out) as z:
        return {k: z[k] for k in z.files}


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """Frames (full and nocov) and a models directory with the torch networks."""
    root = tmp_path_factory.mktemp("parity")
    frames = {
        "full": synthetic_frame(H, W, seed=21, covariance=True),
        "nocov": synthetic_frame(H, W, seed=21, covariance=False),
    }
    paths = {}
    for v, ch in frames.items():
        paths[v] = root / f"frame-{v}.exr"
        write_exr(paths[v], ch)
    nets = random_models(11, **NET)
    for (v, c), net in nets.items():
        scale_head(net, HEAD_GAIN)
        export_onnx(net, root / "models" / v / f"{c}.onnx", c, v)
    return dict(root=root, frames=frames, paths=paths, nets=nets, models=root / "models")


def test_preprocess_nocov_is_full_without_covariance(request):
    exe = require_engine()
    case = request.getfixturevalue("case")
    full = preprocess(exe, case["paths"]["full"], case["root"] / "full.npz")
    nocov = preprocess(exe, case["paths"]["nocov"], case["root"] / "nocov.npz")
    assert int(full["variant"]) == 1 and int(nocov["variant"]) == 0
    assert full["features"].shape == (28, H, W) and nocov["features"].shape == (24, H, W)
    for arrs in (full, nocov):
        for k in ("diffuse_color", "specular_color", "features", "albedo", "noisy"):
            assert arrs[k].dtype == np.float32, k
    np.testing.assert_allclose(
        nocov["features"], full["features"][list(NOCOV_INDICES)], rtol=1e-6, atol=1e-7
    )
    for k in ("diffuse_color", "specular_color", "albedo", "noisy"):
        np.testing.assert_allclose(nocov[k], full[k], rtol=1e-6, atol=1e-7, err_msg=k)


def _grads(b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gx = np.zeros_like(b)
    gy = np.zeros_like(b)
    gx[..., :, :-1] = b[..., :, 1:] - b[..., :, :-1]
    gy[..., :-1, :] = b[..., 1:, :] - b[..., :-1, :]
    return gx, gy


def reference_preprocess(ch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """frame-layout.md's preprocessing in float64 (variances given as one channel), of the
    channels as the engine stores them (half floats for the auxiliary buffers)."""
    f = {k: v.astype(np.float64) for k, v in stored_as_engine(ch).items()}
    rgb = lambda name: np.stack([f[f"{name}.{c}"] for c in "RGB"])
    lum = lambda x: np.tensordot(LUM, x, axes=1)
    d, s, a, n = rgb("diffuse"), rgb("specular"), rgb("albedo"), rgb("normal")
    sp = np.maximum(s, 0.0)

    def color(c, v):
        gx, gy = _grads(c)
        return np.concatenate([c, v[None], gx, gy])

    dc = d / (a + EPS)
    sc = np.log1p(sp)
    out = {
        "diffuse_color": color(dc, lum(f["diffuseVariance.Z"] / (a + EPS) ** 2)),
        "specular_color": color(sc, lum(f["specularVariance.Z"] / (1.0 + sp) ** 2)),
        "albedo": a,
        "noisy": d + s,
    }
    base = [n, a]
    variances = [f["normalVariance.Z"] * LUM.sum(), f["albedoVariance.Z"] * LUM.sum()]
    z = f["depth.Z"]
    mz = z[np.isfinite(z)].max()
    base.append((np.clip(z, 0, mz) / mz)[None])
    variances.append(f["depthVariance.Z"] * LUM.sum() / mz**2)
    if "covariance" in f:
        eta = f["covariance"]
        me = eta[np.isfinite(eta)].max()
        base.append((np.clip(eta, 0, me) / me)[None])
        variances.append(f["covarianceVariance.Z"] * LUM.sum() / me**2)
    b = np.concatenate(base)
    gx, gy = _grads(b)
    out["features"] = np.concatenate([b, np.stack(variances), gx, gy])
    return out


@pytest.mark.parametrize("variant", ["full", "nocov"])
def test_preprocess_matches_frame_layout(request, variant):
    exe = require_engine()
    case = request.getfixturevalue("case")
    # The albedo prefilter (on by default) has its own tests (test_train_ms.py).
    got = preprocess(exe, case["paths"][variant], case["root"] / f"layout-{variant}.npz", "--albedo-prefilter", "off")
    ref = reference_preprocess(case["frames"][variant])
    for k, r in ref.items():
        assert got[k].shape == r.shape, k
        for i in range(r.shape[0]):
            np.testing.assert_allclose(
                got[k][i], r[i], rtol=1e-5, atol=1e-5 * max(np.abs(r[i]).max(), 1e-3),
                err_msg=f"{k}[{i}]",
            )



def _compare_output(out, expect, shape, float_tol):
    """Every `<prefix>R/G/B` channel of the engine's output `out` against `expect[prefix]`
    ([3, H, W]): `float_tol` where the engine wrote float32, half's precision otherwise."""
    got = read_exr(out)
    types = exr_pixel_types(out)
    for prefix, ref in expect.items():
        for i, c in enumerate("RGB"):
            name = prefix + c
            assert name in got, f"{out} has no channel {name!r}; channels: {sorted(got)}"
            assert got[name].shape == shape, name
            tol = float_tol if types[name] == "FLOAT" else 2.0**-10
            _compare(name, got[name], ref[i], tol)

def _compare(name, got, ref, tol):
    """Relative error of each pixel, against its own magnitude or, where that is small, a
    thousandth of the channel's largest (at least 1e-3): float32 sums that pass through the
    channel's magnitudes carry rounding of that size into values that cancel to near zero.
    (With a floor of 1e-3 alone, a specular value of -2.5e-4 in a channel reaching 2.1 failed
    by 1.3e-7 on an AMD EPYC with AVX2, where ONNX Runtime's kernels round otherwise; the
    channel's largest error there was 12 float32 ulps of its maximum.)"""
    floor = 1e-3 * max(1.0, float(np.abs(ref).max()))
    err = np.abs(got.astype(np.float64) - ref) / np.maximum(np.abs(ref), floor)
    i = tuple(int(j) for j in np.unravel_index(int(err.argmax()), err.shape))
    if not err.max() <= tol:
        raise AssertionError(
            f"{name}: max relative error {err.max():.3g} at (y, x) = {i} "
            f"(engine {got[i]:.7g}, torch {ref[i]:.7g}), tolerance {tol:g}"
        )


def torch_v1_output(nets: dict, arrs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """What `mcdenoise run --layers diffuse,specular` should write for a contract-v1 pair
    (`nets[component]`) on the engine's preprocessed tensors `arrs`, in float64: the total
    and the two components, each [3, H, W], by output channel prefix."""
    t = lambda k: torch.from_numpy(arrs[k])[None]
    with torch.no_grad():
        logits = {c: nets[c](t(f"{c}_color"), t("features")).double() for c in COMPONENTS}
    r = reconstruct(logits["diffuse"], logits["specular"], t("diffuse_color").double(),
                    t("specular_color").double(), t("albedo").double())
    return {"": r.total[0].numpy(), "diffuse.": r.diffuse[0].numpy(), "specular.": r.specular[0].numpy()}


def torch_v2_output(net, arrs: dict[str, np.ndarray], h: int, w: int) -> tuple[dict[str, np.ndarray], dict]:
    """The same for a contract-v2 network on its inputs padded by edge replication
    (`pad_to_multiple`), cropped to `h` x `w`; also the intermediates (`pad`, `kernels`,
    `blends`, `gains`, `pre`: each component filtered in its preprocessed domain) for checks
    of their own."""
    from mcdenoise_train.msnet import pad_to_multiple
    from mcdenoise_train.recon_ms import reconstruct_component, split_outputs

    t = lambda k: torch.from_numpy(arrs[k])[None]
    pad = lambda x: pad_to_multiple(x, net.size_multiple)
    with torch.no_grad():
        outputs = net(pad(t("diffuse_color")), pad(t("specular_color")), pad(t("features")))
        kernels, blends, gains = split_outputs(outputs, net.levels)
        gains = gains or {c: None for c in COMPONENTS}
        pyramid = {"diffuse": "log", "specular": net.specular_pyramid}
        pre = {
            c: reconstruct_component(kernels[c], blends[c], pad(t(f"{c}_color"))[:, :3],
                                     pyramid=pyramid[c], gains=gains[c])[..., :h, :w].double()
            for c in COMPONENTS
        }
    d = inverse_diffuse(pre["diffuse"], t("albedo").double())[0].numpy()
    s = inverse_specular(pre["specular"])[0].numpy()
    return {"": d + s, "diffuse.": d, "specular.": s}, dict(pad=pad, kernels=kernels, blends=blends, gains=gains, pre=pre)


@pytest.mark.parametrize("variant", ["full", "nocov"])
def test_run_matches_torch(request, variant):
    exe = require_engine()
    case = request.getfixturevalue("case")
    root = case["root"]
    arrs = preprocess(exe, case["paths"][variant], root / f"run-{variant}.npz")
    assert int(arrs["variant"]) == (1 if variant == "full" else 0)
    expect = torch_v1_output({c: case["nets"][(variant, c)] for c in COMPONENTS}, arrs)

    out = root / f"out-{variant}.exr"
    engine(exe, "run", case["paths"][variant], "-o", out, "--models", case["models"],
           "--layers", "diffuse,specular", "--tile", TILE)
    _compare_output(out, expect, (H, W), float_tol=1e-4)


# --- Contract v2 ---------------------------------------------------------------------------

H2, W2 = 44, 60
TILE2 = 16
NET2 = dict(ext_width=6, ext_blocks=1, enc=(8, 12, 12), dec=(8, 8, 12), kernel_size=5, levels=4)
HEAD_GAIN2 = 15.0


@pytest.fixture(scope="module")
def case_v2(tmp_path_factory):
    """Frames and a models directory with a random contract-v2 network per variant."""
    from mcdenoise_train.export_ms import export_onnx as export_v2, nocov_from_full
    from mcdenoise_train.msnet import MSNet

    root = tmp_path_factory.mktemp("parity-v2")
    paths = {}
    for v, cov in (("full", True), ("nocov", False)):
        paths[v] = root / f"frame-{v}.exr"
        write_exr(paths[v], synthetic_frame(H2, W2, seed=5, covariance=cov))
    torch.manual_seed(17)
    full = MSNet(28, **NET2).eval()
    with torch.no_grad():
        for h in [*full.kernel_heads, *full.blend_heads]:
            h.weight.mul_(HEAD_GAIN2)
    nets = {"full": full, "nocov": nocov_from_full(full)}
    nets["beauty"] = nets["nocov"]
    paths["beauty"] = paths["full"]  # the engine turns the split frame into a beauty-only one
    for v, net in nets.items():
        export_v2(net, root / "models" / v / "model.onnx", v)
    # The same full network with the symlog in its graph (`input_compression` `graph`).
    export_v2(full, root / "models-graph" / "full" / "model.onnx", "full", compression="graph")
    # And with its reconstruction in the graph (`--reconstruction graph`, for GPUs).
    from mcdenoise_train.export_ms import RECON_FILE, export_recon

    export_recon(full, root / "models-graph" / "full" / RECON_FILE, "full")
    # And with the log specular pyramid of the networks before 2026-11-29 (metadata
    # `mcdenoise.specular_pyramid` `log`; the default since is `linear`).
    assert full.specular_pyramid == "linear"
    log = copy.deepcopy(full)
    log.specular_pyramid = "log"
    nets["full-log"] = log
    paths["full-log"] = paths["full"]
    export_v2(log, root / "models-log" / "full" / "model.onnx", "full")
    # And with detail gains (outputs `gain_<l>`), far from one so that they matter.
    gain = copy.deepcopy(full)
    gain.add_detail_gain()
    with torch.no_grad():
        for h in gain.gain_heads:
            h.weight.normal_(0, 1.0, generator=torch.Generator().manual_seed(3))
            h.bias.fill_(0.0)
    nets["full-gain"] = gain
    paths["full-gain"] = paths["full"]
    export_v2(gain, root / "models-gain" / "full" / "model.onnx", "full")
    export_recon(gain, root / "models-gain-graph" / "full" / RECON_FILE, "full")
    export_v2(gain, root / "models-gain-graph" / "full" / "model.onnx", "full", compression="graph")
    # And a network whose decoder level 0 is lean (MSNet(lean0=True)).
    torch.manual_seed(18)
    lean = MSNet(28, **NET2, lean0=True).eval()
    with torch.no_grad():
        for h in [*lean.kernel_heads, *lean.blend_heads]:
            h.weight.mul_(HEAD_GAIN2)
    nets["full-lean"] = lean
    paths["full-lean"] = paths["full"]
    export_v2(lean, root / "models-lean" / "full" / "model.onnx", "full")
    return dict(root=root, paths=paths, nets=nets, models=root / "models")


def test_beauty_inputs_match_the_training_side(request):
    from mcdenoise_train import preprocess as pp

    exe = require_engine()
    case = request.getfixturevalue("case_v2")
    # The transforms alone: the albedo prefilter's parity is tested in test_train_ms.py (a
    # float32 weight's last bit moves an albedo near 0 by more than this test's tolerance).
    arrs = preprocess(exe, case["paths"]["beauty"], case["root"] / "pre-beauty.npz", "--variant", "beauty",
                      "--fireflies", "off", "--albedo-prefilter", "off")
    raw, dmax, cmax = pp.raw_from_channels(read_exr(case["paths"]["beauty"]), albedo_prefilter=False)
    raw = pp.as_beauty(torch.from_numpy(raw)[None].double())
    assert float(raw[:, pp.SPECULAR].abs().max()) == 0.0
    want = pp.preprocess(raw, torch.tensor([dmax], dtype=torch.float64), torch.tensor([0.0], dtype=torch.float64),
                         "nocov")
    for key, name in (("diffuse", "diffuse_color"), ("specular", "specular_color"), ("features", "features")):
        got, ref = arrs[name], want[key][0].numpy()
        assert got.shape == ref.shape, name
        err = np.abs(got - ref) / np.maximum(np.abs(ref), 1e-3)
        assert err.max() <= 1e-5, f"{name}: max relative error {err.max():.3g}"


@pytest.mark.parametrize("variant,compression", [("full", "engine"), ("nocov", "engine"), ("beauty", "engine"),
                                                 ("full", "graph"), ("full", "graph-recon"), ("full-log", "engine"),
                                                 ("full-gain", "engine"), ("full-gain", "graph-recon"),
                                                 ("full-lean", "engine")])
def test_run_matches_torch_v2(request, variant, compression):
    from mcdenoise_train.recon_ms import reconstruct_component

    exe = require_engine()
    case = request.getfixturevalue("case_v2")
    root, net = case["root"], case["nets"][variant]
    served = variant.split("-")[0]  # full-log: the full variant of models-log
    arrs = preprocess(exe, case["paths"][variant], root / f"run-{variant}.npz", "--variant", served)
    t = lambda k: torch.from_numpy(arrs[k])[None]
    m = net.size_multiple
    assert H2 % m and W2 % m, "the frame should need padding"
    expect, parts = torch_v2_output(net, arrs, H2, W2)
    pad, kernels, blends, gains, pre = (parts[k] for k in ("pad", "kernels", "blends", "gains", "pre"))
    pyramid = {"diffuse": "log", "specular": net.specular_pyramid}
    if variant != "beauty":  # (a beauty-only frame has no specular)
        # The two specular pyramids give different outputs here: each case tells them apart.
        other = "log" if net.specular_pyramid == "linear" else "linear"
        with torch.no_grad():
            other_pre = reconstruct_component(kernels["specular"], blends["specular"],
                                              pad(t("specular_color"))[:, :3], pyramid=other,
                                              gains=gains["specular"])[..., :H2, :W2].double()
        assert (other_pre - pre["specular"]).abs().max() > 1e-2 * pre["specular"].abs().max()
    # The kernels are far from uniform: the result differs from the noisy input.
    assert np.abs(expect[""] - arrs["noisy"]).max() > 0.05 * np.abs(arrs["noisy"]).max()

    out = root / f"out-{variant}-{compression}.exr"
    models = case["models"] if compression == "engine" else root / "models-graph"
    models = root / "models-log" if variant == "full-log" else root / "models-lean" if variant == "full-lean" else models
    if variant == "full-gain":
        models = root / ("models-gain-graph" if compression == "graph-recon" else "models-gain")
        # The gains change the result: without them it would differ.
        plain = {c: reconstruct_component(kernels[c], blends[c], pad(t(f"{c}_color"))[:, :3], pyramid=pyramid[c])
                 [..., :H2, :W2].double() for c in COMPONENTS}
        assert (plain["diffuse"] - pre["diffuse"]).abs().max() > 1e-2 * pre["diffuse"].abs().max()
    where = "graph" if compression == "graph-recon" else "engine"
    engine(exe, "run", case["paths"][variant], "-o", out, "--models", models, "--reconstruction", where,
           "--layers", "diffuse,specular", "--tile-v2", TILE2, "--variant", served)
    # The lean network's random weights give one specular pixel a value of -2.5e-4 that is the
    # difference of terms near one, where float32 leaves 4.5e-8 (4.5e-5 of the 1e-3 floor);
    # the 99.9th percentile is 2.2e-6 (the other cases' 1e-6).
    _compare_output(out, expect, (H2, W2), float_tol=1e-4 if variant == "full-lean" else 1e-5)

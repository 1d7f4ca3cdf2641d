"""Synthetic frames and EXR round trips."""

import numpy as np

from mcdenoise_train.exr import exr_pixel_types, read_exr, write_exr
from mcdenoise_train.frames import synthetic_frame

LAYOUT = {
    "diffuse.R", "diffuse.G", "diffuse.B", "diffuseVariance.Z",
    "specular.R", "specular.G", "specular.B", "specularVariance.Z",
    "albedo.R", "albedo.G", "albedo.B", "albedoVariance.Z",
    "normal.R", "normal.G", "normal.B", "normalVariance.Z",
    "depth.Z", "depthVariance.Z", "covariance", "covarianceVariance.Z", "R", "G", "B",
}


def test_synthetic_frame_channels():
    full = synthetic_frame(40, 48, seed=1)
    nocov = synthetic_frame(40, 48, seed=1, covariance=False)
    assert set(full) == LAYOUT
    assert set(full) - set(nocov) == {"covariance", "covarianceVariance.Z"}
    assert all(np.array_equal(full[k], nocov[k]) for k in nocov)
    for k, v in full.items():
        assert v.shape == (40, 48) and v.dtype == np.float32 and np.isfinite(v).all(), k
    assert (full["depth.Z"] == 0).any() and (full["depth.Z"] > 0).any()
    n = np.stack([full[f"normal.{c}"] for c in "RGB"])
    norm = np.linalg.norm(n, axis=0)
    assert np.allclose(norm[norm > 0], 1.0, atol=1e-5)
    np.testing.assert_allclose(full["R"], full["diffuse.R"] + full["specular.R"], rtol=1e-6)


def test_exr_roundtrip(tmp_path):
    frame = synthetic_frame(17, 23, seed=2)
    write_exr(tmp_path / "f.exr", frame)
    back = read_exr(tmp_path / "f.exr")
    assert back.keys() == frame.keys()
    assert all(np.array_equal(back[k], frame[k]) for k in frame)
    assert set(exr_pixel_types(tmp_path / "f.exr").values()) == {"FLOAT"}
    write_exr(tmp_path / "h.exr", frame, half=True)
    assert set(exr_pixel_types(tmp_path / "h.exr").values()) == {"HALF"}
    np.testing.assert_allclose(read_exr(tmp_path / "h.exr")["depth.Z"], frame["depth.Z"], rtol=1e-3)

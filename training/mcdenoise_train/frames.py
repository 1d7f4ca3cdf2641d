"""Synthetic frames: every channel of the layout of docs/frame-layout.md, for tests and benchmarks.

`synthetic_frame` makes a frame with every channel of the layout (the covariance pair
optional) from smooth random fields: sinusoid mixtures plus a disc whose edge puts
discontinuities into albedo, normal, depth and covariance, a no-hit corner (depth,
albedo, normal, diffuse and their variances 0; only specular light), and per-pixel noise on the radiance (with a few fireflies in the specular). It is meant
for tests and benchmarks of the engine and the networks, not as training data. Frames are
written and read by `exr.py`.
"""

from __future__ import annotations

import numpy as np


def _smooth(rng: np.random.Generator, h: int, w: int, terms: int = 4) -> np.ndarray:
    """A smooth field in [0, 1]: a few random low-frequency sinusoids."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    s = max(h, w)
    f = np.zeros((h, w))
    for _ in range(terms):
        fx, fy = rng.uniform(0.5, 3.0, size=2) * 2 * np.pi / s
        f += np.sin(fx * x + rng.uniform(0, 2 * np.pi)) * np.cos(fy * y + rng.uniform(0, 2 * np.pi))
    return (f - f.min()) / max(f.max() - f.min(), 1e-12)


def synthetic_frame(
    h: int, w: int, seed: int = 0, covariance: bool = True, color: bool = True
) -> dict[str, np.ndarray]:
    """A frame with every channel of frame-layout.md, float32 [h, w] arrays by name.

    With `covariance=False` the `covariance` and `covarianceVariance.Z` channels are
    left out (the nocov variant); all other channels are identical for a given seed.
    `color` adds `R,G,B` = diffuse + specular.
    """
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    disc = (x - 0.6 * w) ** 2 + (y - 0.55 * h) ** 2 < (0.3 * min(h, w)) ** 2
    sky = (x < 0.2 * w) & (y < 0.25 * h)

    def sm() -> np.ndarray:
        return _smooth(rng, h, w)

    albedo = np.stack([0.05 + 0.9 * sm() for _ in range(3)])
    albedo[:, disc] = np.array([0.8, 0.3, 0.1])[:, None] * (0.7 + 0.3 * sm()[disc])
    albedo[:, sky] = 0.0

    n = np.stack([sm() - 0.5, sm() - 0.5, 0.4 + sm()])
    n[:, disc] = np.stack([(x[disc] - 0.6 * w), (y[disc] - 0.55 * h), np.full(disc.sum(), 0.3 * min(h, w))])
    n /= np.linalg.norm(n, axis=0, keepdims=True)
    n[:, sky] = 0.0

    depth = 2.0 + 6.0 * sm()
    depth[disc] = 1.0 + 0.5 * sm()[disc]
    depth[sky] = 0.0

    irradiance = 0.2 + 2.0 * sm()
    noise = rng.normal(0.0, 0.3, size=(3, h, w))
    diffuse = np.maximum(albedo * irradiance * (1.0 + noise), 0.0)
    specular = 0.3 * sm() * rng.exponential(1.0, size=(3, h, w))
    fireflies = rng.random((h, w)) < 0.01
    specular[:, fireflies] *= 40.0
    specular[:, sky] = 0.05 + 0.01 * rng.random((3, sky.sum()))

    def var(scale: float, hit_only: bool = True) -> np.ndarray:
        v = scale * sm() * rng.uniform(0.5, 1.5, size=(h, w))
        if hit_only:
            v[sky] = 0.0
        return v

    ch: dict[str, np.ndarray] = {}
    for i, c in enumerate("RGB"):
        ch[f"diffuse.{c}"] = diffuse[i]
        ch[f"specular.{c}"] = specular[i]
        ch[f"albedo.{c}"] = albedo[i]
        ch[f"normal.{c}"] = n[i]
    ch["diffuseVariance.Z"] = var(0.05)
    ch["specularVariance.Z"] = var(0.2, hit_only=False)
    ch["albedoVariance.Z"] = var(0.01)
    ch["normalVariance.Z"] = var(0.02)
    ch["depth.Z"] = depth
    ch["depthVariance.Z"] = var(0.1)
    if covariance:
        cov = 0.5 * sm()
        cov[disc] = 2.0 + sm()[disc]
        cov[sky] = 0.0
        ch["covariance"] = cov
        ch["covarianceVariance.Z"] = var(0.05)
    if color:
        for i, c in enumerate("RGB"):
            ch[c] = diffuse[i] + specular[i]
    return {k: v.astype(np.float32) for k, v in ch.items()}

"""Procedural textures, generated in numpy from a seed (no image files).

Every generator returns a pattern in [0, 1] of shape (H, W) (2-D textures, used through
UV coordinates) or evaluates a 3-D pattern at points (used as per-vertex colours of
generated meshes). `colorize` maps a pattern to RGB between two colours.
"""

from __future__ import annotations

import numpy as np


def _smoothstep(t):
    return t * t * (3.0 - 2.0 * t)


def value_noise_2d(rng: np.random.Generator, size: int, cells: int, octaves: int = 4) -> np.ndarray:
    """Fractal value noise, tileable, in [0, 1]."""
    out = np.zeros((size, size))
    amp, total = 1.0, 0.0
    for o in range(octaves):
        c = cells * 2**o
        grid = rng.random((c, c))
        u = np.arange(size) * c / size
        i0 = np.floor(u).astype(int)
        f = _smoothstep(u - i0)
        i1 = (i0 + 1) % c
        i0 %= c
        g00, g10 = grid[np.ix_(i0, i0)], grid[np.ix_(i1, i0)]
        g01, g11 = grid[np.ix_(i0, i1)], grid[np.ix_(i1, i1)]
        fy, fx = f[:, None], f[None, :]
        out += amp * ((g00 * (1 - fx) + g01 * fx) * (1 - fy) + (g10 * (1 - fx) + g11 * fx) * fy)
        total += amp
        amp *= 0.5
    out /= total
    return (out - out.min()) / max(out.max() - out.min(), 1e-9)


def checker(size: int, n: int) -> np.ndarray:
    y, x = np.mgrid[0:size, 0:size] * n // size
    return ((x + y) % 2).astype(np.float64)


def stripes(rng: np.random.Generator, size: int, freq: float) -> np.ndarray:
    y, x = np.mgrid[0:size, 0:size] / size
    ang = rng.uniform(0, np.pi)
    s = np.sin(2 * np.pi * freq * (x * np.cos(ang) + y * np.sin(ang)))
    return (s > rng.uniform(-0.5, 0.5)).astype(np.float64)


def voronoi(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Voronoi cells with a random grey level each (tileable)."""
    pts = rng.random((cells, 2))
    vals = rng.random(cells)
    y, x = (np.mgrid[0:size, 0:size] + 0.5) / size
    best = np.full((size, size), np.inf)
    out = np.zeros((size, size))
    for (px, py), v in zip(pts, vals):
        dx = np.abs(x - px)
        dy = np.abs(y - py)
        d = np.minimum(dx, 1 - dx) ** 2 + np.minimum(dy, 1 - dy) ** 2
        m = d < best
        best[m] = d[m]
        out[m] = v
    return out


def marble(rng: np.random.Generator, size: int) -> np.ndarray:
    n = value_noise_2d(rng, size, 4, 5)
    y, x = np.mgrid[0:size, 0:size] / size
    return 0.5 + 0.5 * np.sin(2 * np.pi * (x * rng.uniform(2, 6) + 4.0 * n))


def dots(rng: np.random.Generator, size: int, n: int) -> np.ndarray:
    y, x = (np.mgrid[0:size, 0:size] + 0.5) * n / size
    r = rng.uniform(0.2, 0.45)
    return (((x % 1 - 0.5) ** 2 + (y % 1 - 0.5) ** 2) < r * r).astype(np.float64)


def text(rng: np.random.Generator, size: int, rows: int) -> np.ndarray:
    """Text-like high-frequency pattern: rows of 'words' made of glyph-like strokes."""
    img = np.zeros((size, size))
    lh = size // rows
    for r in range(rows):
        y0 = r * lh + lh // 5
        gh = max(2, int(lh * 0.55))
        x = int(rng.integers(0, lh))
        while x < size - 4:
            for _ in range(int(rng.integers(2, 9))):  # one word
                gw = max(2, int(gh * rng.uniform(0.4, 0.8)))
                if x + gw >= size:
                    break
                for _ in range(int(rng.integers(2, 4))):  # strokes of one glyph
                    if rng.random() < 0.5:  # vertical
                        cx = x + int(rng.integers(0, gw))
                        img[y0:y0 + gh, cx:cx + max(1, gw // 4)] = 1.0
                    else:  # horizontal
                        cy = y0 + int(rng.integers(0, gh))
                        img[cy:cy + max(1, gh // 6), x:x + gw] = 1.0
                x += gw + max(1, gw // 3)
            x += int(gh * rng.uniform(0.6, 1.2))
    return img


PATTERNS_2D = ("noise", "checker", "stripes", "voronoi", "marble", "dots")
#: High-frequency patterns (fine checkers, text) for the `textures` family.
PATTERNS_HF = ("finechecker", "text", "noise", "stripes")


def pattern_2d(kind: str, seed: int, size: int = 256) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if kind == "noise":
        return value_noise_2d(rng, size, int(rng.integers(2, 8)))
    if kind == "checker":
        return checker(size, int(rng.integers(2, 12)) * 2)
    if kind == "stripes":
        return stripes(rng, size, int(rng.integers(3, 16)))
    if kind == "voronoi":
        return voronoi(rng, size, int(rng.integers(8, 40)))
    if kind == "marble":
        return marble(rng, size)
    if kind == "dots":
        return dots(rng, size, int(rng.integers(3, 12)))
    if kind == "finechecker":
        return checker(size, int(rng.integers(12, 33)) * 2)
    if kind == "text":
        return text(rng, size, int(rng.integers(8, 20)))
    raise ValueError(f"unknown pattern {kind!r}")


def colorize(p: np.ndarray, c0, c1) -> np.ndarray:
    c0, c1 = np.asarray(c0, np.float64), np.asarray(c1, np.float64)
    return (p[..., None] * c1 + (1.0 - p[..., None]) * c0).astype(np.float32)


def noise_3d(points: np.ndarray, seed: int, freq: float, octaves: int = 3) -> np.ndarray:
    """Smooth 3-D noise at points (N, 3) in [0, 1]: a sum of random sinusoid products."""
    rng = np.random.default_rng(seed)
    out = np.zeros(len(points))
    amp = 1.0
    for o in range(octaves):
        for _ in range(3):
            k = rng.normal(size=3)
            k *= freq * 2**o / np.linalg.norm(k)
            out += amp * np.sin(points @ k + rng.uniform(0, 2 * np.pi))
        amp *= 0.5
    return (out - out.min()) / max(out.max() - out.min(), 1e-9)


def pattern_3d(kind: str, points: np.ndarray, seed: int) -> np.ndarray:
    """3-D patterns for per-vertex colours: 'noise', 'bands', 'spots'."""
    rng = np.random.default_rng(seed)
    if kind == "noise":
        return noise_3d(points, seed, rng.uniform(2, 6))
    if kind == "bands":
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        return (np.sin(points @ axis * rng.uniform(8, 30)) > 0).astype(np.float64)
    if kind == "spots":
        return (noise_3d(points, seed, rng.uniform(4, 10)) > 0.6).astype(np.float64)
    raise ValueError(f"unknown 3-D pattern {kind!r}")

"""Generated triangle meshes: displaced icospheres and tori.

Meshes carry per-vertex normals (smooth shading) and a per-vertex `vertex_curv`
attribute, the mean curvature estimated from the normals along the mesh edges, which the
covariance tracer reads (Mitsuba's mesh normal derivatives are taken in barycentric
coordinates and cannot be turned into a shape operator when the mesh has UVs). Meshes
have no UVs: procedural colour is baked into a `vertex_color` attribute instead.
"""

from __future__ import annotations

import numpy as np

from .textures import noise_3d


def icosphere(level: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere: (vertices (N, 3), faces (M, 3) uint32), counter-clockwise outwards."""
    t = (1.0 + 5**0.5) / 2.0
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t),
         (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
         (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
         (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.array(p, np.float64) / np.linalg.norm(p) for p in v]
    faces = f
    for _ in range(level):
        cache: dict[tuple[int, int], int] = {}

        def mid(i, j):
            key = (min(i, j), max(i, j))
            if key not in cache:
                m = verts[i] + verts[j]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        nf = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            nf += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = nf
    return np.array(verts), np.array(faces, np.uint32)


def torus(R: float, r: float, nu: int = 96, nv: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """Torus around the z axis (ring radius R, tube radius r), wrapped indices, no seams."""
    u = np.arange(nu) * 2 * np.pi / nu
    v = np.arange(nv) * 2 * np.pi / nv
    U, V = np.meshgrid(u, v, indexing="ij")
    P = np.stack([(R + r * np.cos(V)) * np.cos(U), (R + r * np.cos(V)) * np.sin(U), r * np.sin(V)], -1)
    P = P.reshape(-1, 3)
    idx = lambda i, j: (i % nu) * nv + (j % nv)  # noqa: E731
    F = []
    for i in range(nu):
        for j in range(nv):
            a, b, c, d = idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1)
            F += [(a, b, c), (a, c, d)]
    return P, np.array(F, np.uint32)


def vertex_normals(P: np.ndarray, F: np.ndarray) -> np.ndarray:
    fn = np.cross(P[F[:, 1]] - P[F[:, 0]], P[F[:, 2]] - P[F[:, 0]])  # area-weighted
    n = np.zeros_like(P)
    for k in range(3):
        np.add.at(n, F[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def mean_curvature(P: np.ndarray, N: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Per-vertex mean curvature: the average over incident edges of the normal curvature
    (n_j - n_i) . (p_j - p_i) / |p_j - p_i|^2 (positive on convex surfaces)."""
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1]])
    dp = P[e[:, 1]] - P[e[:, 0]]
    dn = N[e[:, 1]] - N[e[:, 0]]
    k = np.einsum("ij,ij->i", dn, dp) / np.maximum(np.einsum("ij,ij->i", dp, dp), 1e-12)
    s = np.zeros(len(P))
    c = np.zeros(len(P))
    np.add.at(s, e[:, 0], k)
    np.add.at(c, e[:, 0], 1)
    return s / np.maximum(c, 1)


def displaced_sphere(seed: int, amplitude: float, freq: float, level: int = 4):
    """Icosphere displaced along the normal by smooth 3-D noise (radius ~1)."""
    P, F = icosphere(level)
    d = noise_3d(P, seed, freq, octaves=2) - 0.5
    P = P * (1.0 + amplitude * d)[:, None]
    return P, F


def to_mitsuba(P: np.ndarray, F: np.ndarray, name: str, bsdf, colors: np.ndarray | None = None):
    """A mitsuba Mesh with vertex normals, a `vertex_curv` attribute and optionally a
    `vertex_color` attribute; `bsdf` is a loaded BSDF object."""
    import mitsuba as mi

    N = vertex_normals(P, F)
    K = mean_curvature(P, N, F)
    m = mi.Mesh(name, len(P), len(F), has_vertex_normals=True, has_vertex_texcoords=False)
    p = mi.traverse(m)
    p["vertex_positions"] = mi.Float(P.astype(np.float32).ravel())
    p["faces"] = mi.UInt32(F.astype(np.uint32).ravel())
    p["vertex_normals"] = mi.Float(N.astype(np.float32).ravel())
    p.update()
    m.add_attribute("vertex_curv", 1, mi.Float(K.astype(np.float32)))
    if colors is not None:
        m.add_attribute("vertex_color", 3, mi.Float(colors.astype(np.float32).ravel()))
    m.set_bsdf(bsdf)
    return m


def heightfield(seed: int, half: float, amplitude: float, freq: float, n: int = 96):
    """A square grid of side 2 * half in the xz plane (y up) displaced in y by smooth
    noise of the given amplitude (a water surface). Returns (P, F)."""
    from .textures import noise_3d

    u = np.linspace(-half, half, n)
    X, Z = np.meshgrid(u, u)
    pts = np.stack([X.ravel(), np.zeros(X.size), Z.ravel()], 1)
    h = noise_3d(pts / (2 * half) + 0.5, seed, freq) - 0.5
    P = np.stack([X.ravel(), amplitude * h, Z.ravel()], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)]).astype(np.uint32)
    return P, F


def leaf_cards(rng: np.random.Generator, center, count: int, size: float, spread: float):
    """Foliage: `count` leaves, each a flat card cut to a leaf outline (an ellipse-like
    fan of triangles: the shape an alpha-textured card shows), randomly oriented around
    `center`. Returns (P, F) of all leaves."""
    Ps, Fs, base = [], [], 0
    k = 10
    t = np.linspace(0, np.pi, k)
    for _ in range(count):
        L = size * rng.uniform(0.6, 1.4)
        W = L * rng.uniform(0.25, 0.45)
        # outline: tip at x = L, stem at x = 0, width W * sin
        top = np.stack([L * (1 - np.cos(t)) / 2, W * np.sin(t) / 2, np.zeros(k)], 1)
        bot = top[1:-1][::-1] * np.array([1, -1, 1])
        ring = np.concatenate([top, bot])
        cen = np.array([[L / 2, 0.0, 0.0]])
        V = np.concatenate([cen, ring])
        m = len(ring)
        F = np.array([[0, 1 + i, 1 + (i + 1) % m] for i in range(m)])
        a = rng.normal(size=3)
        a /= np.linalg.norm(a)
        ang = rng.uniform(0, 2 * np.pi)
        K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        R = np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K
        off = np.asarray(center) + rng.normal(size=3) * spread * np.array([1, 0.6, 1])
        Ps.append(V @ R.T + off)
        Fs.append(F + base)
        base += len(V)
    return np.concatenate(Ps), np.concatenate(Fs).astype(np.uint32)

"""Seedable procedural scenes.

A scene is first generated as a *spec*: plain JSON-serialisable data (kind, camera,
emitters, objects with shapes, transforms and materials, texture seeds) derived from one
integer seed with numpy's PCG64. `build(spec, width, height)` turns a spec into a Mitsuba
scene, generating meshes and textures on the fly, so a data set is regenerated from the
seeds in its manifest alone.

Kinds (`generate` picks one from the seed unless told):

- `cornell`: a Cornell-like box (coloured side walls, white floor/ceiling/back), a
  ceiling area light of random size (small ones cast sharp shadows), two or three
  objects with random materials.
- `room`: an interior with random wall colours, a textured floor, light from a window
  panel, ceiling panel and/or small bright lamps, furniture-like boxes, objects and
  instanced clutter.
- `open`: a textured ground under an environment gradient (sky/horizon/ground, sometimes
  a small sun), sometimes extra small bright sources; glass (caustics), metals,
  plastics, displaced spheres, tori, thin cylinders, clutter.

Named scenes used by tests and fixtures: `shadow_test` (a known, sharp shadow edge on a
flat diffuse floor, see `shadow_test_edge_column`), `caustic_test` (glass sphere and a
glossy torus on a floor under a small light).

World space is Y-up; the floor is y = 0; units are metres.
"""

from __future__ import annotations

import copy
import math
import os
import tempfile

import numpy as np

from . import meshes, textures

KINDS = ("cornell", "room", "open", "interior", "smalllights", "emissive", "caustics", "metals", "dof", "thin",
         "textures")
_TEMP_FILES: list[str] = []  # curve files written by `build`, removed once the scene is loaded
CONDUCTORS = ("Au", "Cu", "Al", "Ag", "Cr", "W", "Ir", "Rh", "TiN", "CuO")


# ----------------------------------------------------------------------------- specs


def _rgb(rng, lo=0.05, hi=0.85, sat=None):
    """A random reflectance colour (linear RGB)."""
    h = rng.random()
    s = rng.uniform(0.1, 0.8) if sat is None else sat
    v = rng.uniform(lo, hi)
    i = int(h * 6) % 6
    f = h * 6 - int(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return [round(float(x), 4) for x in [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i]]


def _texture(rng):
    kind = str(rng.choice(textures.PATTERNS_2D))
    return {"pattern": kind, "seed": int(rng.integers(1 << 31)), "c0": _rgb(rng), "c1": _rgb(rng),
            "scale": float(rng.choice([1, 2, 3, 4]))}


def random_material(rng, allow_glass=True, textured_p=0.35):
    """A random material spec; weights favour the common cases."""
    kinds = ["diffuse", "plastic", "roughplastic", "conductor", "roughconductor", "dielectric",
             "roughdielectric"]
    w = np.array([0.3, 0.1, 0.2, 0.08, 0.17, 0.1, 0.05])
    if not allow_glass:
        w[5:] = 0
    kind = str(rng.choice(kinds, p=w / w.sum()))
    m: dict = {"type": kind}
    if kind in ("diffuse", "plastic", "roughplastic"):
        m["color"] = _rgb(rng)
        if rng.random() < textured_p:
            m["texture"] = _texture(rng)
    if kind in ("roughplastic", "roughconductor", "roughdielectric"):
        m["alpha"] = round(float(np.exp(rng.uniform(np.log(0.02), np.log(0.5)))), 4)
    if kind == "roughconductor" and rng.random() < 0.3:
        m["alpha_texture"] = {"pattern": str(rng.choice(["noise", "stripes", "voronoi", "checker"])),
                              "seed": int(rng.integers(1 << 31)), "lo": 0.03, "hi": 0.4,
                              "scale": float(rng.choice([1, 2, 4]))}
    if kind in ("conductor", "roughconductor"):
        m["material"] = str(rng.choice(CONDUCTORS))
    if kind in ("dielectric", "roughdielectric"):
        m["ior"] = round(float(rng.uniform(1.3, 1.8)), 3)
    return m


def _look_at_camera(rng, target, dist, fov, elev_deg, azim_deg, dof_p=0.25, focus=None):
    el, az = math.radians(elev_deg), math.radians(azim_deg)
    origin = [target[0] + dist * math.cos(el) * math.sin(az), target[1] + dist * math.sin(el),
              target[2] + dist * math.cos(el) * math.cos(az)]
    cam = {"origin": [round(x, 4) for x in origin], "target": [round(float(x), 4) for x in target],
           "up": [0, 1, 0], "fov": round(float(fov), 3), "aperture": 0.0, "focus": round(float(dist), 4)}
    if rng is not None and rng.random() < dof_p:
        cam["aperture"] = round(float(rng.uniform(0.01, 0.06) * dist / 4.0), 4)
        cam["focus"] = round(float(focus if focus is not None else dist * rng.uniform(0.8, 1.1)), 4)
    return cam


def _object(rng, pos, size, allow_glass=True, shapes=None):
    shapes = shapes or ["sphere", "cube", "dsphere", "torus", "cylinder", "sphere", "dsphere"]
    shape = str(rng.choice(shapes))
    mat = random_material(rng, allow_glass)
    o = {"shape": shape, "material": mat, "rot": [round(float(x), 3) for x in rng.uniform(0, 360, 3)]}
    if shape == "sphere":
        o.update(center=[pos[0], size, pos[1]], radius=size)
    elif shape == "dsphere":
        o.update(center=[pos[0], size * 1.05, pos[1]], radius=size, seed=int(rng.integers(1 << 31)),
                 amplitude=round(float(rng.uniform(0.05, 0.35)), 3), freq=round(float(rng.uniform(1.5, 5)), 3))
        if rng.random() < 0.4 and mat["type"] in ("diffuse", "plastic", "roughplastic"):
            # plastics need Texture::mean(), which per-vertex colours do not provide
            mat["type"] = "diffuse"
            mat.pop("alpha", None)
            mat["vertex_pattern"] = {"pattern": str(rng.choice(["noise", "bands", "spots"])),
                                     "seed": int(rng.integers(1 << 31)), "c0": _rgb(rng), "c1": _rgb(rng)}
            mat.pop("texture", None)
    elif shape == "torus":
        r = size * rng.uniform(0.2, 0.4)
        o.update(center=[pos[0], size * 0.9, pos[1]], R=size * 0.8, r=round(float(r), 4))
    elif shape == "cube":
        o.update(center=[pos[0], size * 0.7, pos[1]], half=[round(float(size * rng.uniform(0.4, 0.9)), 4),
                                                              round(float(size * 0.7), 4),
                                                              round(float(size * rng.uniform(0.4, 0.9)), 4)])
        o["rot"] = [0.0, o["rot"][1], 0.0]
    elif shape == "cylinder":
        h = size * rng.uniform(1.5, 3.5)
        rad = size * rng.uniform(0.03, 0.12)  # thin
        o.update(p0=[pos[0], 0.0, pos[1]], p1=[pos[0] + float(rng.uniform(-0.3, 0.3)) * size, h,
                                                pos[1] + float(rng.uniform(-0.3, 0.3)) * size],
                 radius=round(float(rad), 4))
    return o


def _clutter(rng, center, extent, count, allow_glass=False):
    """Instanced clutter: a shape group of a few small shapes, instanced `count` times."""
    group = []
    for _ in range(int(rng.integers(2, 4))):
        s = float(rng.uniform(0.02, 0.06))
        shape = str(rng.choice(["sphere", "cube", "cylinder"]))
        group.append({"shape": shape, "size": round(s, 4), "material": random_material(rng, allow_glass, 0.0)})
    inst = []
    for _ in range(count):
        p = [center[0] + float(rng.uniform(-extent, extent)), 0.0, center[1] + float(rng.uniform(-extent, extent))]
        inst.append({"pos": [round(x, 4) for x in p], "rot": round(float(rng.uniform(0, 360)), 2),
                     "scale": round(float(rng.uniform(0.6, 1.6)), 3)})
    return {"shape": "clutter", "group": group, "instances": inst}


def _place(rng, n, radius, size_range, min_gap=0.05, center=(0.0, 0.0)):
    """n non-overlapping discs (x, z, size) in a disc of `radius` around `center`."""
    out = []
    for _ in range(200 * n):
        if len(out) == n:
            break
        s = float(rng.uniform(*size_range))
        r = radius * math.sqrt(rng.random())
        a = rng.uniform(0, 2 * math.pi)
        x, z = center[0] + r * math.cos(a), center[1] + r * math.sin(a)
        if all((x - ox) ** 2 + (z - oz) ** 2 > (s + os + min_gap) ** 2 for ox, oz, os in out):
            out.append((x, z, s))
    return [(round(x, 4), round(z, 4), round(s, 4)) for x, z, s in out]


def _rect(name, center, normal, half, material):
    return {"shape": "rect", "name": name, "center": center, "normal": normal, "half": half, "material": material}


def _diffuse(color):
    return {"type": "diffuse", "color": color}


def cornell(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    white = [0.73, 0.73, 0.73]
    red, green = _rgb(rng, 0.3, 0.7, 0.8), _rgb(rng, 0.3, 0.7, 0.8)
    light_size = float(rng.choice([0.12, 0.25, 0.5, 0.7]))
    power = 17.0 * (0.5 / light_size) ** 2 * rng.uniform(0.8, 1.3)
    objs = []
    placed = _place(rng, int(rng.integers(2, 4)), 0.6, (0.18, 0.35), 0.05)
    for x, z, s in placed:
        objs.append(_object(rng, (x, z), s, shapes=["cube", "cube", "sphere", "dsphere", "torus"]))
    walls = [
        # floor, ceiling and side walls reach z = 1.6 so that the camera sees no outside
        _rect("floor", [0, 0, 0.3], [0, 1, 0], [1, 1.3], _diffuse(white)),
        _rect("ceiling", [0, 2, 0.3], [0, -1, 0], [1, 1.3], _diffuse(white)),
        _rect("back", [0, 1, -1], [0, 0, 1], [1, 1], _diffuse(white)),
        _rect("left", [-1, 1, 0.3], [1, 0, 0], [1.3, 1], _diffuse(red)),
        _rect("right", [1, 1, 0.3], [-1, 0, 0], [1.3, 1], _diffuse(green)),
    ]
    if rng.random() < 0.3:
        walls[0]["material"] = {"type": "diffuse", "color": white, "texture": _texture(rng)}
    emitters = [{"type": "rect", "center": [0, 1.98, 0], "normal": [0, -1, 0], "half": [light_size / 2] * 2,
                 "radiance": [round(power * c, 3) for c in (1.0, 0.85, 0.65)]}]
    cam = _look_at_camera(rng, [0, 1, 0], 3.9, 39.3, 0.0, 0.0, dof_p=0.0)
    cam["origin"][0] += round(float(rng.uniform(-0.15, 0.15)), 3)
    cam["origin"][1] += round(float(rng.uniform(-0.15, 0.15)), 3)
    return {"name": f"cornell-{seed}", "kind": "cornell", "seed": seed, "camera": cam,
            "emitters": emitters, "objects": walls + objs}


def room(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    W, D, H = rng.uniform(3, 6), rng.uniform(3, 6), rng.uniform(2.4, 3.2)
    wall = _rgb(rng, 0.3, 0.8, rng.uniform(0, 0.4))
    floor_mat = random_material(rng, False, 0.0)
    if floor_mat["type"] in ("dielectric", "roughdielectric", "conductor"):
        floor_mat = {"type": "roughplastic", "color": _rgb(rng), "alpha": 0.15}
    if floor_mat["type"] in ("diffuse", "plastic", "roughplastic"):
        floor_mat["texture"] = _texture(rng)
        floor_mat["texture"]["scale"] = float(rng.choice([4, 8, 12]))
    objs = [
        _rect("floor", [0, 0, 0], [0, 1, 0], [W / 2, D / 2], floor_mat),
        _rect("ceiling", [0, H, 0], [0, -1, 0], [W / 2, D / 2], _diffuse([0.8, 0.8, 0.8])),
        _rect("wall-n", [0, H / 2, -D / 2], [0, 0, 1], [W / 2, H / 2], _diffuse(wall)),
        _rect("wall-s", [0, H / 2, D / 2], [0, 0, -1], [W / 2, H / 2], _diffuse(wall)),
        _rect("wall-w", [-W / 2, H / 2, 0], [1, 0, 0], [D / 2, H / 2], _diffuse(_rgb(rng, 0.3, 0.8, 0.3))),
        _rect("wall-e", [W / 2, H / 2, 0], [-1, 0, 0], [D / 2, H / 2], _diffuse(wall)),
    ]
    emitters = []
    mode = rng.integers(0, 3)
    if mode in (0, 2):  # window panel on the west wall
        wh, ww = rng.uniform(0.6, 1.2), rng.uniform(0.5, 1.5)
        emitters.append({"type": "rect", "center": [-W / 2 + 0.01, H * 0.55, float(rng.uniform(-D / 4, D / 4))],
                         "normal": [1, 0, 0], "half": [ww / 2, wh / 2], "radiance": [round(x * rng.uniform(6, 14), 3) for x in (0.9, 0.95, 1.0)]})
    if mode in (1, 2) or rng.random() < 0.3:  # ceiling panel
        s = rng.uniform(0.3, 1.0)
        emitters.append({"type": "rect", "center": [float(rng.uniform(-W / 4, W / 4)), H - 0.01, float(rng.uniform(-D / 4, D / 4))],
                         "normal": [0, -1, 0], "half": [s / 2, s / 2], "radiance": [round(x * rng.uniform(5, 10) / s, 3) for x in (1.0, 0.9, 0.75)]})
    for _ in range(int(rng.integers(0 if emitters else 1, 3))):  # small bright lamps
        r = float(rng.uniform(0.01, 0.05))
        emitters.append({"type": "sphere", "center": [float(rng.uniform(-W / 3, W / 3)), float(rng.uniform(1.2, H - 0.3)), float(rng.uniform(-D / 3, D / 3))],
                         "radius": round(r, 4), "radiance": [round(x * 2.0 / (r * r), 3) for x in (1.0, 0.8, 0.6)]})
    # furniture: a table-like box and objects on the floor
    if rng.random() < 0.6:
        th = float(rng.uniform(0.5, 0.9))
        objs.append({"shape": "cube", "center": [float(rng.uniform(-0.5, 0.5)), th / 2, float(rng.uniform(-D / 2 + 0.8, -0.2))],
                     "half": [float(rng.uniform(0.3, 0.7)), th / 2, float(rng.uniform(0.25, 0.5))], "rot": [0, float(rng.uniform(0, 360)), 0],
                     "material": random_material(rng, False)})
    for x, z, s in _place(rng, int(rng.integers(2, 6)), min(W, D) / 3, (0.12, 0.35), 0.1):
        objs.append(_object(rng, (x, z), s))
    if rng.random() < 0.6:
        objs.append(_clutter(rng, (float(rng.uniform(-0.5, 0.5)), float(rng.uniform(-0.5, 0.5))), 0.8, int(rng.integers(10, 60))))
    target = [float(rng.uniform(-0.3, 0.3)), float(rng.uniform(0.3, 0.8)), float(rng.uniform(-0.5, 0.2))]
    dist = float(rng.uniform(1.5, min(W, D) / 2 + 0.8))
    cam = _look_at_camera(rng, target, dist, rng.uniform(35, 75), rng.uniform(5, 35), rng.uniform(-60, 60))
    cam["origin"][0] = float(np.clip(cam["origin"][0], -W / 2 + 0.2, W / 2 - 0.2))
    cam["origin"][1] = float(np.clip(cam["origin"][1], 0.3, H - 0.2))
    cam["origin"][2] = float(np.clip(cam["origin"][2], -D / 2 + 0.2, D / 2 - 0.2))
    return {"name": f"room-{seed}", "kind": "room", "seed": seed, "camera": cam, "emitters": emitters, "objects": objs}


def open_scene(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    ground = random_material(rng, False, 0.0)
    if ground["type"] not in ("diffuse", "roughplastic"):
        ground = {"type": "diffuse", "color": _rgb(rng)}
    if rng.random() < 0.7:
        ground["texture"] = _texture(rng)
        ground["texture"]["scale"] = float(rng.choice([15, 25, 40]))
    objs = [{"shape": "rect", "name": "ground", "center": [0, 0, 0], "normal": [0, 1, 0], "half": [20.0, 20.0], "material": ground}]
    sun = rng.random() < 0.6
    env = {"type": "env", "zenith": _rgb(rng, 0.3, 1.0, rng.uniform(0, 0.6)), "horizon": _rgb(rng, 0.5, 1.2, rng.uniform(0, 0.3)),
           "ground": _rgb(rng, 0.05, 0.3, 0.3), "scale": round(float(rng.uniform(0.3, 1.5)), 3), "seed": int(rng.integers(1 << 31))}
    if sun:
        env["sun"] = {"elevation": round(float(rng.uniform(10, 70)), 2), "azimuth": round(float(rng.uniform(0, 360)), 2),
                      "size_deg": round(float(rng.uniform(0.8, 4.0)), 3), "strength": round(float(rng.uniform(2e3, 2e4)), 1)}
    emitters = [env]
    for _ in range(int(rng.integers(0, 3) if sun else rng.integers(1, 3))):
        r = float(rng.uniform(0.01, 0.06))
        emitters.append({"type": "sphere", "center": [float(rng.uniform(-1.5, 1.5)), float(rng.uniform(0.8, 2.5)), float(rng.uniform(-1.5, 1.5))],
                         "radius": round(r, 4), "radiance": [round(x * rng.uniform(1.0, 4.0) / (r * r), 3) for x in _rgb(rng, 0.8, 1.0, 0.3)]})
    n = int(rng.integers(3, 9))
    for x, z, s in _place(rng, n, 1.6, (0.12, 0.45), 0.08):
        objs.append(_object(rng, (x, z), s))
    if rng.random() < 0.5:
        objs.append(_clutter(rng, (float(rng.uniform(-0.6, 0.6)), float(rng.uniform(-0.6, 0.6))), 1.2, int(rng.integers(15, 80)), True))
    cam = _look_at_camera(rng, [float(rng.uniform(-0.4, 0.4)), float(rng.uniform(0.1, 0.5)), float(rng.uniform(-0.4, 0.4))],
                          float(rng.uniform(2.2, 5.0)), rng.uniform(25, 60), rng.uniform(5, 50), rng.uniform(0, 360))
    return {"name": f"open-{seed}", "kind": "open", "seed": seed, "camera": cam, "emitters": emitters, "objects": objs}


def _exposure(rng, lo=0.05, hi=1.0):
    """An overall light level, log-uniform: dim scenes are where denoisers struggle."""
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _box_room(rng, W, D, H, wall, floor_mat, window=None):
    """Floor, ceiling and four walls of a W x D x H room centred on x = z = 0. With
    `window` = (z_center, y_center, half_w, half_h), the west wall (x = -W/2) gets an
    opening, built from four rectangles around it."""
    objs = [
        _rect("floor", [0, 0, 0], [0, 1, 0], [W / 2, D / 2], floor_mat),
        _rect("ceiling", [0, H, 0], [0, -1, 0], [W / 2, D / 2], _diffuse([0.8, 0.8, 0.78])),
        _rect("wall-n", [0, H / 2, -D / 2], [0, 0, 1], [W / 2, H / 2], _diffuse(wall)),
        _rect("wall-s", [0, H / 2, D / 2], [0, 0, -1], [W / 2, H / 2], _diffuse(wall)),
        _rect("wall-e", [W / 2, H / 2, 0], [-1, 0, 0], [D / 2, H / 2], _diffuse(wall)),
    ]
    if window is None:
        objs.append(_rect("wall-w", [-W / 2, H / 2, 0], [1, 0, 0], [D / 2, H / 2], _diffuse(wall)))
        return objs
    zc, yc, hw, hh = window
    x = -W / 2
    # below, above, and the two sides of the opening (rect half sizes: [along z, along y])
    parts = [((zc, (yc - hh) / 2), (hw, (yc - hh) / 2)), ((zc, (yc + hh + H) / 2), (hw, (H - yc - hh) / 2)),
             (((-D / 2 + zc - hw) / 2, H / 2), ((zc - hw + D / 2) / 2, H / 2)),
             (((D / 2 + zc + hw) / 2, H / 2), ((D / 2 - zc - hw) / 2, H / 2))]
    for j, ((z, y), (a, b)) in enumerate(parts):
        if a > 1e-3 and b > 1e-3:
            # _frame_for_normal([1,0,0]) maps local x to -z... use a rotation-free description
            objs.append({"shape": "rect", "name": f"wall-w{j}", "center": [x, y, z], "normal": [1, 0, 0],
                         "half": [a, b], "material": _diffuse(wall)})
    return objs


def _sky(rng, exposure, sun_dir_range=None, sun=True):
    env = {"type": "env", "zenith": _rgb(rng, 0.3, 1.0, rng.uniform(0.2, 0.6)),
           "horizon": _rgb(rng, 0.5, 1.2, rng.uniform(0, 0.3)), "ground": _rgb(rng, 0.05, 0.3, 0.3),
           "scale": round(float(rng.uniform(0.3, 1.5) * exposure), 4), "seed": int(rng.integers(1 << 31))}
    if sun:
        el_lo, el_hi, az_lo, az_hi = sun_dir_range or (10, 70, 0, 360)
        env["sun"] = {"elevation": round(float(rng.uniform(el_lo, el_hi)), 2),
                      "azimuth": round(float(rng.uniform(az_lo, az_hi)), 2),
                      "size_deg": round(float(rng.uniform(0.6, 2.0)), 3),
                      "strength": round(float(rng.uniform(2e3, 2e4)), 1)}
    return env


def _room_camera(rng, W, D, H, look_from_window=True):
    target = [float(rng.uniform(-W / 4, W / 4)), float(rng.uniform(0.4, 1.2)), float(rng.uniform(-D / 4, D / 4))]
    dist = float(rng.uniform(1.2, min(W, D) / 2 + 0.6))
    az = rng.uniform(30, 150) if look_from_window else rng.uniform(-180, 180)  # camera on the +x side
    cam = _look_at_camera(rng, target, dist, rng.uniform(40, 75), rng.uniform(0, 25), az, dof_p=0.1)
    cam["origin"][0] = float(np.clip(cam["origin"][0], -W / 2 + 0.2, W / 2 - 0.2))
    cam["origin"][1] = float(np.clip(cam["origin"][1], 0.3, H - 0.2))
    cam["origin"][2] = float(np.clip(cam["origin"][2], -D / 2 + 0.2, D / 2 - 0.2))
    return cam


def _lamp(rng, pos, exposure, hanging=False, H=2.6):
    """A shaded lamp: a small bright sphere inside an open cylindrical shade (light leaves
    only through its open ends), on a thin stand or hanging from the ceiling."""
    shade_r, shade_h = float(rng.uniform(0.12, 0.25)), float(rng.uniform(0.15, 0.3))
    y = float(rng.uniform(1.6, H - 0.4)) if hanging else float(rng.uniform(0.9, 1.6))
    r = float(rng.uniform(0.015, 0.035))
    power = rng.uniform(0.5, 2.0) * exposure / (r * r)
    shade = {"shape": "cylinder", "p0": [pos[0], y - shade_h / 2, pos[1]], "p1": [pos[0], y + shade_h / 2, pos[1]],
             "radius": round(shade_r, 4), "material": _diffuse(_rgb(rng, 0.4, 0.9, 0.3))}
    stand = ({"shape": "cylinder", "p0": [pos[0], y, pos[1]], "p1": [pos[0], H, pos[1]], "radius": 0.006,
              "material": _diffuse([0.1, 0.1, 0.1])} if hanging else
             {"shape": "cylinder", "p0": [pos[0], 0.0, pos[1]], "p1": [pos[0], y - shade_h / 2, pos[1]],
              "radius": 0.012, "material": {"type": "roughconductor", "material": "Al", "alpha": 0.2}})
    em = {"type": "sphere", "center": [pos[0], y, pos[1]], "radius": round(r, 4),
          "radiance": [round(x * power, 3) for x in (1.0, 0.8, 0.55)]}
    return [shade, stand], em


def _furnish(rng, W, D, objs, n_lo=2, n_hi=6, glass=True):
    if rng.random() < 0.6:
        th = float(rng.uniform(0.5, 0.9))
        objs.append({"shape": "cube", "center": [float(rng.uniform(-0.5, 0.5)), th / 2, float(rng.uniform(-D / 2 + 0.8, -0.2))],
                     "half": [float(rng.uniform(0.3, 0.7)), th / 2, float(rng.uniform(0.25, 0.5))],
                     "rot": [0, float(rng.uniform(0, 360)), 0], "material": random_material(rng, False)})
    for x, z, sz in _place(rng, int(rng.integers(n_lo, n_hi)), min(W, D) / 3, (0.12, 0.35), 0.1):
        objs.append(_object(rng, (x, z), sz, allow_glass=glass))


def interior(seed: int) -> dict:
    """A room lit mostly indirectly: sun and sky through a window opening, shaded lamps;
    the camera mostly looks away from the window, at dim light levels."""
    rng = np.random.default_rng(seed)
    W, D, H = rng.uniform(3.5, 6), rng.uniform(3.5, 6), rng.uniform(2.4, 3.0)
    exposure = _exposure(rng, 0.03, 0.6)
    wall = _rgb(rng, 0.35, 0.85, rng.uniform(0, 0.3))
    floor_mat = {"type": "roughplastic", "color": _rgb(rng, 0.1, 0.6), "alpha": round(float(rng.uniform(0.05, 0.4)), 3),
                 "texture": {**_texture(rng), "scale": float(rng.choice([4, 8, 12]))}}
    emitters, objs = [], []
    mode = int(rng.integers(0, 3))  # 0: window, 1: lamps, 2: both
    window = None
    if mode in (0, 2):
        hw, hh = float(rng.uniform(0.3, 0.9)), float(rng.uniform(0.35, 0.7))
        window = (float(rng.uniform(-D / 2 + hw + 0.2, D / 2 - hw - 0.2)), float(rng.uniform(hh + 0.5, H - hh - 0.2)), hw, hh)
        # sun outside the west wall (direction to the sun has x < 0), low enough to shine in
        emitters.append(_sky(rng, exposure, (12, 45, 200, 340), sun=rng.random() < 0.75))
    objs += _box_room(rng, W, D, H, wall, floor_mat, window)
    if mode in (1, 2):
        for _ in range(int(rng.integers(1, 3))):
            parts, em = _lamp(rng, (float(rng.uniform(-W / 3, W / 3)), float(rng.uniform(-D / 3, D / 3))),
                              exposure * (3.0 if mode == 1 else 1.0), hanging=rng.random() < 0.4, H=H)
            objs += parts
            emitters.append(em)
    _furnish(rng, W, D, objs)
    if rng.random() < 0.5:
        objs.append(_clutter(rng, (float(rng.uniform(-0.5, 0.5)), float(rng.uniform(-0.5, 0.5))), 0.8, int(rng.integers(10, 40))))
    cam = _room_camera(rng, W, D, H, look_from_window=True)
    return {"name": f"interior-{seed}", "kind": "interior", "seed": seed, "camera": cam, "emitters": emitters,
            "objects": objs, "exposure": round(exposure, 4)}


def smalllights(seed: int) -> dict:
    """Small, dim, partly occluded area lights (under shelves, behind panels) in a room."""
    rng = np.random.default_rng(seed)
    W, D, H = rng.uniform(3, 5), rng.uniform(3, 5), rng.uniform(2.4, 3.0)
    exposure = _exposure(rng, 0.05, 0.8)
    objs = _box_room(rng, W, D, H, _rgb(rng, 0.3, 0.8, 0.3), random_material(rng, False, 0.5)
                     if rng.random() < 0.5 else _diffuse(_rgb(rng, 0.2, 0.7)))
    emitters = []
    for _ in range(int(rng.integers(1, 4))):
        x, z = float(rng.uniform(-W / 3, W / 3)), float(rng.uniform(-D / 3, D / 3))
        y = float(rng.uniform(0.4, H - 0.5))
        s = float(rng.uniform(0.02, 0.1))
        L = rng.uniform(0.5, 2.0) * exposure / (s * s)
        emitters.append({"type": "rect", "center": [x, y, z], "normal": [0, -1, 0], "half": [s / 2, s / 2],
                         "radiance": [round(L * c, 3) for c in _rgb(rng, 0.8, 1.0, 0.3)]})
        # the occluder: a shelf just above (light only downwards) and a side panel
        objs.append({"shape": "cube", "center": [x, y + 0.03, z], "half": [s * 3, 0.015, s * 3], "rot": [0, 0, 0],
                     "material": random_material(rng, False)})
        if rng.random() < 0.7:
            side = float(rng.choice([-1, 1]))
            objs.append({"shape": "cube", "center": [x + side * s * 1.5, y - 0.1, z], "half": [0.01, 0.12, s * 3],
                         "rot": [0, 0, 0], "material": _diffuse(_rgb(rng, 0.2, 0.7))})
    _furnish(rng, W, D, objs)
    cam = _room_camera(rng, W, D, H, look_from_window=False)
    return {"name": f"smalllights-{seed}", "kind": "smalllights", "seed": seed, "camera": cam,
            "emitters": emitters, "objects": objs, "exposure": round(exposure, 4)}


def emissive(seed: int) -> dict:
    """Emissive objects (glowing spheres, cubes, neon tubes, disks) as the main light,
    over a dim environment or in a dark room."""
    rng = np.random.default_rng(seed)
    exposure = _exposure(rng, 0.1, 1.0)
    objs = [_rect("ground", [0, 0, 0], [0, 1, 0], [6, 6], {**_diffuse(_rgb(rng, 0.2, 0.7)), "texture": {**_texture(rng), "scale": 8.0}})]
    emitters = []
    if rng.random() < 0.5:
        emitters.append(_sky(rng, exposure * 0.05, sun=False))
    else:
        objs += [_rect("back", [0, 2, -2.5], [0, 0, 1], [6, 2], _diffuse(_rgb(rng, 0.3, 0.7)))]
    for x, z, sz in _place(rng, int(rng.integers(2, 5)), 1.5, (0.08, 0.3), 0.1):
        L = [round(c * rng.uniform(2, 10) * exposure, 3) for c in _rgb(rng, 0.6, 1.0, rng.uniform(0.2, 0.9))]
        kind = str(rng.choice(["sphere", "cube", "tube", "disk"]))
        if kind == "sphere":
            emitters.append({"type": "sphere", "center": [x, sz, z], "radius": sz, "radiance": L})
        elif kind == "cube":
            emitters.append({"type": "cube", "center": [x, sz, z], "half": [sz * 0.7] * 3, "rot": [0, float(rng.uniform(0, 90)), 0], "radiance": L})
        elif kind == "tube":
            h = float(rng.uniform(0.4, 1.2))
            emitters.append({"type": "cylinder", "p0": [x, 0.05, z], "p1": [x + float(rng.uniform(-0.3, 0.3)), h, z], "radius": round(sz * 0.15, 4), "radiance": L})
        else:
            emitters.append({"type": "disk", "center": [x, sz + 0.3, z], "normal": [float(rng.uniform(-1, 1)), 0.3, float(rng.uniform(-1, 1))], "radius": sz, "radiance": L})
    for x, z, sz in _place(rng, int(rng.integers(2, 6)), 1.8, (0.1, 0.35), 0.1, center=(0.3, 0.3)):
        objs.append(_object(rng, (x, z), sz))
    cam = _look_at_camera(rng, [0, 0.3, 0], float(rng.uniform(2.5, 4.5)), rng.uniform(35, 60), rng.uniform(8, 35), rng.uniform(-70, 70))
    return {"name": f"emissive-{seed}", "kind": "emissive", "seed": seed, "camera": cam, "emitters": emitters, "objects": objs}


def caustics(seed: int) -> dict:
    """Caustics: glass objects and a water surface (a displaced dielectric sheet over a
    pool floor) under a small light or the sun."""
    rng = np.random.default_rng(seed)
    exposure = _exposure(rng, 0.2, 1.0)
    floor = {**_diffuse(_rgb(rng, 0.4, 0.9, 0.3)), "texture": {**_texture(rng), "scale": 6.0}}
    objs = [_rect("floor", [0, 0, 0], [0, 1, 0], [4, 4], floor)]
    emitters = []
    if rng.random() < 0.5:
        r = float(rng.uniform(0.02, 0.06))
        emitters.append({"type": "sphere", "center": [float(rng.uniform(-1, 1)), float(rng.uniform(1.2, 2.2)), float(rng.uniform(-1, 1))],
                         "radius": round(r, 4), "radiance": [round(c * exposure * 1.5 / (r * r), 3) for c in (1.0, 0.92, 0.8)]})
        emitters.append(_sky(rng, exposure * 0.05, sun=False))
    else:
        emitters.append(_sky(rng, exposure * 0.3, (30, 70, 0, 360), sun=True))
    if rng.random() < 0.5:  # water
        objs.append({"shape": "heightfield", "seed": int(rng.integers(1 << 31)), "center": [0, float(rng.uniform(0.15, 0.4)), 0],
                     "half": 1.2, "amplitude": round(float(rng.uniform(0.01, 0.05)), 4), "freq": round(float(rng.uniform(3, 10)), 3),
                     "material": {"type": "dielectric", "ior": 1.33}})
        for x, z, sz in _place(rng, int(rng.integers(1, 4)), 0.8, (0.05, 0.12), 0.05):
            objs.append(_object(rng, (x, z), sz, allow_glass=False))
    for x, z, sz in _place(rng, int(rng.integers(2, 5)), 1.2, (0.12, 0.35), 0.08, center=(0.0, 0.6)):
        o = _object(rng, (x, z), sz, shapes=["sphere", "dsphere", "torus", "cube"])
        o["material"] = {"type": str(rng.choice(["dielectric", "dielectric", "roughdielectric"])), "ior": round(float(rng.uniform(1.3, 1.8)), 3),
                         "alpha": round(float(rng.uniform(0.02, 0.2)), 3)}
        objs.append(o)
    cam = _look_at_camera(rng, [0, 0.2, 0.3], float(rng.uniform(2.0, 3.5)), rng.uniform(30, 55), rng.uniform(20, 55), rng.uniform(-60, 60))
    return {"name": f"caustics-{seed}", "kind": "caustics", "seed": seed, "camera": cam, "emitters": emitters, "objects": objs}


def metals(seed: int) -> dict:
    """Smooth and rough metals reflecting small lights, emissive panels and the sky."""
    rng = np.random.default_rng(seed)
    exposure = _exposure(rng, 0.2, 1.0)
    objs = [_rect("floor", [0, 0, 0], [0, 1, 0], [4, 4], random_material(rng, False, 0.5)),
            _rect("back", [0, 1.5, -1.8], [0, 0, 1], [4, 1.5], _diffuse(_rgb(rng, 0.1, 0.5)))]
    emitters = [_sky(rng, exposure * 0.3, sun=rng.random() < 0.4)]
    for _ in range(int(rng.integers(1, 4))):
        r = float(rng.uniform(0.01, 0.05))
        emitters.append({"type": "sphere", "center": [float(rng.uniform(-1.5, 1.5)), float(rng.uniform(0.5, 2.0)), float(rng.uniform(-1.2, 1.5))],
                         "radius": round(r, 4), "radiance": [round(c * exposure * rng.uniform(0.5, 3) / (r * r), 3) for c in _rgb(rng, 0.8, 1.0, 0.3)]})
    if rng.random() < 0.6:
        emitters.append({"type": "rect", "center": [float(rng.uniform(-1, 1)), float(rng.uniform(1.0, 2.0)), -1.75], "normal": [0, 0, 1],
                         "half": [float(rng.uniform(0.1, 0.5)), float(rng.uniform(0.03, 0.2))], "radiance": [round(8 * exposure, 3)] * 3})
    for x, z, sz in _place(rng, int(rng.integers(3, 7)), 1.3, (0.12, 0.4), 0.08):
        o = _object(rng, (x, z), sz, shapes=["sphere", "dsphere", "torus", "cube", "cylinder"])
        smooth = rng.random() < 0.4
        o["material"] = {"type": "conductor" if smooth else "roughconductor", "material": str(rng.choice(CONDUCTORS)),
                         "alpha": round(float(np.exp(rng.uniform(np.log(0.01), np.log(0.4)))), 4)}
        objs.append(o)
    cam = _look_at_camera(rng, [0, 0.3, 0], float(rng.uniform(2.0, 4.0)), rng.uniform(30, 60), rng.uniform(8, 40), rng.uniform(-50, 50))
    return {"name": f"metals-{seed}", "kind": "metals", "seed": seed, "camera": cam, "emitters": emitters, "objects": objs}


def dof(seed: int) -> dict:
    """Depth of field: a wide thin-lens aperture focused on a near object, with small
    bright highlights far behind it (bokeh)."""
    spec = open_scene(seed) if np.random.default_rng([seed, 3]).random() < 0.5 else room(seed)
    rng = np.random.default_rng([seed, 11])
    cam = spec["camera"]
    o, t = np.asarray(cam["origin"]), np.asarray(cam["target"])
    dist = float(np.linalg.norm(t - o))
    cam["focus"] = round(dist * float(rng.uniform(0.4, 1.0)), 4)
    cam["aperture"] = round(float(rng.uniform(0.03, 0.12)) * dist / 3.0, 4)
    spec.update(name=f"dof-{seed}", kind="dof", seed=seed)
    return spec


def thin(seed: int) -> dict:
    """Thin geometry: grass or fur as curves, hanging wires, foliage (leaf-shaped cards)."""
    rng = np.random.default_rng(seed)
    exposure = _exposure(rng, 0.2, 1.0)
    objs = [_rect("ground", [0, 0, 0], [0, 1, 0], [6, 6], {**_diffuse(_rgb(rng, 0.1, 0.4)), "texture": {**_texture(rng), "scale": 20.0}})]
    emitters = [_sky(rng, exposure, (15, 60, 0, 360), sun=rng.random() < 0.7)]
    if rng.random() < 0.4:
        r = float(rng.uniform(0.02, 0.05))
        emitters.append({"type": "sphere", "center": [float(rng.uniform(-1, 1)), float(rng.uniform(1, 2)), float(rng.uniform(-1, 1))],
                         "radius": round(r, 4), "radiance": [round(c * exposure / (r * r), 3) for c in (1.0, 0.9, 0.7)]})
    # grass/fur: clumps of curved strands
    strands = []
    for _ in range(int(rng.integers(2, 6))):
        cx, cz = float(rng.uniform(-1.2, 1.2)), float(rng.uniform(-1.2, 1.2))
        rad, n = float(rng.uniform(0.1, 0.5)), int(rng.integers(150, 600))
        h = float(rng.uniform(0.1, 0.5))
        for _ in range(n):
            a, r = rng.uniform(0, 2 * np.pi), rad * np.sqrt(rng.random())
            x, z = cx + r * np.cos(a), cz + r * np.sin(a)
            hh = h * rng.uniform(0.6, 1.2)
            bend = rng.normal(size=2) * hh * 0.3
            w = float(rng.uniform(0.001, 0.003))
            strands.append([[round(x + bend[0] * (k / 3) ** 2, 4), round(hh * k / 3, 4), round(z + bend[1] * (k / 3) ** 2, 4),
                             round(w * (1 - 0.8 * k / 3), 5)] for k in range(4)])
    objs.append({"shape": "curves", "strands": strands, "material": _diffuse(_rgb(rng, 0.15, 0.6, rng.uniform(0.3, 0.8)))})
    # wires between poles
    for _ in range(int(rng.integers(1, 4))):
        y = float(rng.uniform(0.6, 1.8))
        p0 = [float(rng.uniform(-2, -0.5)), y, float(rng.uniform(-1.5, 1.5))]
        p1 = [float(rng.uniform(0.5, 2)), y + float(rng.uniform(-0.3, 0.3)), float(rng.uniform(-1.5, 1.5))]
        sag = float(rng.uniform(0.05, 0.3))
        pts = [[round(p0[0] + (p1[0] - p0[0]) * t, 4), round(p0[1] + (p1[1] - p0[1]) * t - 4 * sag * t * (1 - t), 4),
                round(p0[2] + (p1[2] - p0[2]) * t, 4), 0.004] for t in np.linspace(0, 1, 12)]
        objs.append({"shape": "curves", "strands": [pts], "material": random_material(rng, False, 0.0)})
    # foliage
    for _ in range(int(rng.integers(1, 4))):
        objs.append({"shape": "leaves", "seed": int(rng.integers(1 << 31)), "center": [float(rng.uniform(-1, 1)), float(rng.uniform(0.4, 1.4)), float(rng.uniform(-1, 1))],
                     "count": int(rng.integers(30, 120)), "size": round(float(rng.uniform(0.04, 0.1)), 3), "spread": round(float(rng.uniform(0.1, 0.3)), 3),
                     "material": _diffuse(_rgb(rng, 0.1, 0.5, rng.uniform(0.4, 0.9)))})
    for x, z, sz in _place(rng, int(rng.integers(1, 4)), 1.5, (0.1, 0.3), 0.1):
        objs.append(_object(rng, (x, z), sz))
    cam = _look_at_camera(rng, [0, 0.4, 0], float(rng.uniform(1.5, 3.5)), rng.uniform(30, 60), rng.uniform(5, 35), rng.uniform(0, 360))
    return {"name": f"thin-{seed}", "kind": "thin", "seed": seed, "camera": cam, "emitters": emitters, "objects": objs}


def textures_family(seed: int) -> dict:
    """High-frequency textures (fine checkers, text, noise), bump and normal maps, rough
    metals and rough dielectrics."""
    rng = np.random.default_rng(seed)
    exposure = _exposure(rng, 0.2, 1.0)

    def hf_texture():
        return {"pattern": str(rng.choice(textures.PATTERNS_HF)), "seed": int(rng.integers(1 << 31)),
                "c0": _rgb(rng, 0.02, 0.4), "c1": _rgb(rng, 0.5, 0.9), "scale": float(rng.choice([1, 2, 4, 8]))}

    def bump():
        return {"pattern": str(rng.choice(["noise", "voronoi", "stripes", "finechecker"])), "seed": int(rng.integers(1 << 31)),
                "scale": float(rng.choice([2, 4, 8])), "strength": round(float(rng.uniform(0.2, 1.0)), 3),
                "kind": str(rng.choice(["bump", "normal"]))}

    floor = {"type": str(rng.choice(["diffuse", "roughplastic"])), "color": [0.5, 0.5, 0.5], "alpha": 0.2, "texture": hf_texture()}
    floor["texture"]["scale"] = float(rng.choice([6, 12, 20]))
    objs = [_rect("floor", [0, 0, 0], [0, 1, 0], [4, 4], floor),
            _rect("back", [0, 1.5, -1.6], [0, 0, 1], [4, 1.5], {"type": "diffuse", "color": [0.5] * 3, "texture": hf_texture()})]
    if rng.random() < 0.6:
        objs[0]["material"]["bump"] = bump()
    emitters = [_sky(rng, exposure * 0.6, sun=rng.random() < 0.6)]
    if rng.random() < 0.6:
        s = float(rng.uniform(0.2, 0.6))
        emitters.append({"type": "rect", "center": [float(rng.uniform(-1, 1)), 2.2, float(rng.uniform(-0.5, 1))], "normal": [0, -1, 0],
                         "half": [s / 2, s / 2], "radiance": [round(c * exposure * 6 / s, 3) for c in (1.0, 0.95, 0.85)]})
    for x, z, sz in _place(rng, int(rng.integers(3, 7)), 1.3, (0.12, 0.4), 0.08):
        o = _object(rng, (x, z), sz, shapes=["sphere", "cube", "sphere", "cube", "torus"])
        k = rng.random()
        if k < 0.35:
            o["material"] = {"type": "roughconductor", "material": str(rng.choice(CONDUCTORS)), "alpha": round(float(rng.uniform(0.05, 0.5)), 3)}
        elif k < 0.55:
            o["material"] = {"type": "roughdielectric", "ior": round(float(rng.uniform(1.3, 1.8)), 3), "alpha": round(float(rng.uniform(0.05, 0.4)), 3)}
        else:
            o["material"] = {"type": str(rng.choice(["diffuse", "roughplastic"])), "color": [0.5] * 3, "alpha": round(float(rng.uniform(0.05, 0.3)), 3),
                             "texture": hf_texture()}
        if o["material"]["type"] != "roughdielectric" and rng.random() < 0.5 and o["shape"] in ("sphere", "cube"):
            o["material"]["bump"] = bump()
        objs.append(o)
    cam = _look_at_camera(rng, [0, 0.3, 0], float(rng.uniform(1.8, 3.5)), rng.uniform(30, 60), rng.uniform(10, 40), rng.uniform(-50, 50))
    return {"name": f"textures-{seed}", "kind": "textures", "seed": seed, "camera": cam, "emitters": emitters, "objects": objs}


#: Scene families, each a function of the seed; `generate` draws one when none is given.
FAMILIES = {"cornell": lambda s: cornell(s), "room": lambda s: room(s), "open": lambda s: open_scene(s),
            "interior": lambda s: interior(s), "smalllights": lambda s: smalllights(s),
            "emissive": lambda s: emissive(s), "caustics": lambda s: caustics(s), "metals": lambda s: metals(s),
            "dof": lambda s: dof(s), "thin": lambda s: thin(s), "textures": lambda s: textures_family(s)}


def generate(seed: int, kind: str | None = None) -> dict:
    """The scene spec of a seed; the family `kind` is drawn from the seed (uniformly over
    all families) when not given."""
    if kind is None:
        kind = KINDS[int(np.random.default_rng([seed, 7]).integers(len(KINDS)))]
    if kind not in FAMILIES:
        raise ValueError(f"unknown scene family {kind!r}; families: {', '.join(KINDS)}")
    return FAMILIES[kind](seed)


def shadow_test() -> dict:
    """A purpose-built scene with a known shadow edge: a thin wall (x in [-0.05, 0],
    height 0.5, along z) on a white diffuse floor, lit by a small sphere light at
    (1, 2, 0), seen straight down by a camera above x = -0.4. The wall's top edge throws a
    sharp shadow boundary onto the floor at x = -0.4 (`SHADOW_EDGE_X`)."""
    return {
        "name": "shadow_test", "kind": "test", "seed": 0,
        "camera": {"origin": [-0.4, 3.0, 0.0], "target": [-0.4, 0.0, 0.0], "up": [0, 0, -1], "fov": 40.0,
                   "aperture": 0.0, "focus": 3.0},
        "emitters": [{"type": "sphere", "center": [1.0, 2.0, 0.0], "radius": 0.01, "radiance": [25000.0] * 3}],
        "objects": [
            {"shape": "rect", "name": "floor", "center": [0, 0, 0], "normal": [0, 1, 0], "half": [4, 4],
             "material": {"type": "diffuse", "color": [0.7, 0.7, 0.7]}},
            {"shape": "cube", "name": "wall", "center": [-0.025, 0.25, 0.0], "half": [0.025, 0.25, 3.0], "rot": [0, 0, 0],
             "material": {"type": "diffuse", "color": [0.5, 0.5, 0.5]}},
        ],
    }


SHADOW_EDGE_X = -0.4  # 1 + (-0.05 - 1) * 2 / (2 - 0.5)


def shadow_test_edge_column(width: int) -> float:
    """Image column (pixel-centre coordinates) of the shadow edge of `shadow_test`: the
    camera looks straight down from y = 3 at x = -0.4, so the edge is in the middle column;
    world +x maps to image +x (up vector -z)."""
    return width / 2.0


def caustic_test() -> dict:
    """A glass sphere and a glossy torus on a diffuse floor under a small light and a dim sky."""
    return {
        "name": "caustic_test", "kind": "test", "seed": 0,
        "camera": {"origin": [0.0, 1.6, 2.6], "target": [0.0, 0.25, 0.0], "up": [0, 1, 0], "fov": 40.0,
                   "aperture": 0.0, "focus": 3.0},
        "emitters": [
            {"type": "sphere", "center": [0.3, 1.6, -0.5], "radius": 0.1, "radiance": [400.0, 370.0, 320.0]},
            {"type": "env", "zenith": [0.15, 0.2, 0.3], "horizon": [0.3, 0.3, 0.3], "ground": [0.05, 0.05, 0.05],
             "scale": 0.3, "seed": 1},
        ],
        "objects": [
            {"shape": "rect", "name": "floor", "center": [0, 0, 0], "normal": [0, 1, 0], "half": [3, 3],
             "material": {"type": "diffuse", "color": [0.6, 0.6, 0.6]}},
            {"shape": "sphere", "center": [-0.2, 0.3, 0.1], "radius": 0.3,
             "material": {"type": "dielectric", "ior": 1.5}},
            {"shape": "torus", "center": [0.55, 0.22, 0.35], "R": 0.25, "r": 0.08, "rot": [70, 20, 0],
             "material": {"type": "roughconductor", "material": "Au", "alpha": 0.08}},
            {"shape": "cube", "center": [-0.75, 0.2, -0.5], "half": [0.2, 0.2, 0.2], "rot": [0, 30, 0],
             "material": {"type": "roughplastic", "color": [0.1, 0.3, 0.7], "alpha": 0.05}},
        ],
    }


NAMED = {"shadow_test": shadow_test, "caustic_test": caustic_test}


# ----------------------------------------------------------------------------- build


def _transform(center=(0, 0, 0), rot=(0, 0, 0), scale=(1, 1, 1)):
    import mitsuba as mi

    T = mi.ScalarTransform4f()
    return (T.translate(list(center)).rotate([0, 1, 0], rot[1]).rotate([1, 0, 0], rot[0])
            .rotate([0, 0, 1], rot[2]).scale(list(scale) if np.ndim(scale) else [scale] * 3))


def _rot_matrix(rot):
    def R(axis, deg):
        a = math.radians(deg)
        c, s = math.cos(a), math.sin(a)
        x, y, z = axis
        return np.array([[c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
                         [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
                         [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)]])
    return R((0, 1, 0), rot[1]) @ R((1, 0, 0), rot[0]) @ R((0, 0, 1), rot[2])


def _bitmap_texture(tex, size=256):
    import mitsuba as mi

    p = textures.pattern_2d(tex["pattern"], tex["seed"], size)
    img = textures.colorize(p, tex["c0"], tex["c1"])
    k = tex.get("scale", 1.0)
    return {"type": "bitmap", "bitmap": mi.Bitmap(img), "raw": True, "filter_type": "bilinear",
            "wrap_mode": "repeat", "to_uv": mi.ScalarTransform4f().scale([k, k, 1])}


def _material(m):
    """Mitsuba BSDF dict of a material spec (double-sided except dielectrics), wrapped in a
    bump or normal map when the spec has `bump`."""
    b = _material_base(m)
    if "bump" not in m:
        return b
    bm = m["bump"]
    p = textures.pattern_2d(bm["pattern"], bm["seed"], 256)
    k = bm.get("scale", 1.0)
    import mitsuba as mi

    to_uv = mi.ScalarTransform4f().scale([k, k, 1])
    if bm.get("kind", "bump") == "normal":
        gy, gx = np.gradient(p)
        n = np.stack([-gx * bm["strength"] * 8, -gy * bm["strength"] * 8, np.ones_like(p)], -1)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        tex = {"type": "bitmap", "bitmap": mi.Bitmap((0.5 * n + 0.5).astype(np.float32)), "raw": True,
               "wrap_mode": "repeat", "to_uv": to_uv}
        return {"type": "normalmap", "normalmap": tex, "bsdf": b}
    tex = {"type": "bitmap", "bitmap": mi.Bitmap(p.astype(np.float32)[..., None]), "raw": True, "wrap_mode": "repeat",
           "to_uv": to_uv}
    return {"type": "bumpmap", "arbitrary": tex, "scale": float(bm["strength"]) * 0.01, "bsdf": b}


def _material_base(m):
    import mitsuba as mi

    t = m["type"]
    if "vertex_pattern" in m:
        refl = {"type": "mesh_attribute", "name": "vertex_color"}
    elif "texture" in m:
        refl = _bitmap_texture(m["texture"])
    else:
        refl = {"type": "rgb", "value": m.get("color", [0.5, 0.5, 0.5])}
    if t == "diffuse":
        b = {"type": "diffuse", "reflectance": refl}
    elif t == "plastic":
        b = {"type": "plastic", "diffuse_reflectance": refl, "int_ior": 1.5}
    elif t == "roughplastic":
        b = {"type": "roughplastic", "diffuse_reflectance": refl, "int_ior": 1.5, "alpha": m["alpha"],
             "distribution": "ggx"}
    elif t == "conductor":
        b = {"type": "conductor", "material": m["material"]}
    elif t == "roughconductor":
        b = {"type": "roughconductor", "material": m["material"], "distribution": "ggx", "alpha": m["alpha"]}
        if "alpha_texture" in m:
            at = m["alpha_texture"]
            p = textures.pattern_2d(at["pattern"], at["seed"], 128)
            a = (at["lo"] + (at["hi"] - at["lo"]) * p).astype(np.float32)[..., None]
            k = at.get("scale", 1.0)
            b["alpha"] = {"type": "bitmap", "bitmap": mi.Bitmap(a), "raw": True, "wrap_mode": "repeat",
                          "to_uv": mi.ScalarTransform4f().scale([k, k, 1])}
    elif t == "dielectric":
        return {"type": "dielectric", "int_ior": m["ior"], "ext_ior": 1.0}
    elif t == "roughdielectric":
        return {"type": "roughdielectric", "int_ior": m["ior"], "ext_ior": 1.0, "alpha": m["alpha"],
                "distribution": "ggx"}
    else:
        raise ValueError(f"unknown material {t!r}")
    return {"type": "twosided", "bsdf": b}


def _frame_for_normal(normal):
    """Rotation taking +z to `normal` (for rectangles and disks)."""
    n = np.asarray(normal, np.float64)
    n /= np.linalg.norm(n)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, n)
    c = float(z @ n)
    if np.linalg.norm(v) < 1e-9:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def _affine(R, t, s):
    import mitsuba as mi

    M = np.eye(4)
    M[:3, :3] = R @ np.diag(s)
    M[:3, 3] = t
    return mi.ScalarTransform4f(M.tolist())



def generated_mesh(o: dict):
    """Vertices (world space) and faces of a generated-mesh object (`dsphere` or `torus`),
    as both renderers build it."""
    if o["shape"] == "dsphere":
        P, F = meshes.displaced_sphere(o["seed"], o["amplitude"], o["freq"])
        P = P * o["radius"]
    else:
        P, F = meshes.torus(o["R"], o["r"])
    return P @ _rot_matrix(o.get("rot", [0, 0, 0])).T + np.asarray(o["center"]), F

def _shape_dicts(o, key):
    """Mitsuba dicts (or Mesh objects) of one object spec."""
    import mitsuba as mi

    sh = o["shape"]
    bsdf = _material(o["material"]) if sh != "clutter" else None
    if sh == "rect":
        R = _frame_for_normal(o["normal"])
        return {key: {"type": "rectangle", "to_world": _affine(R, o["center"], [o["half"][0], o["half"][1], 1]), "bsdf": bsdf}}
    if sh == "disk":
        R = _frame_for_normal(o["normal"])
        return {key: {"type": "disk", "to_world": _affine(R, o["center"], [o["radius"]] * 2 + [1]), "bsdf": bsdf}}
    if sh == "sphere":
        return {key: {"type": "sphere", "center": o["center"], "radius": o["radius"], "bsdf": bsdf}}
    if sh == "cube":
        return {key: {"type": "cube", "to_world": _affine(_rot_matrix(o.get("rot", [0, 0, 0])), o["center"], o["half"]), "bsdf": bsdf}}
    if sh == "cylinder":
        return {key: {"type": "cylinder", "p0": o["p0"], "p1": o["p1"], "radius": o["radius"], "bsdf": bsdf}}
    if sh in ("dsphere", "torus"):
        P, F = generated_mesh(o)
        colors = None
        vp = o["material"].get("vertex_pattern")
        if vp:
            colors = textures.colorize(textures.pattern_3d(vp["pattern"], P, vp["seed"]), vp["c0"], vp["c1"])
        return {key: meshes.to_mitsuba(P, F, key, mi.load_dict(bsdf), colors)}
    if sh == "heightfield":
        P, F = meshes.heightfield(o["seed"], o["half"], o["amplitude"], o["freq"])
        P = P + np.asarray(o["center"])
        return {key: meshes.to_mitsuba(P, F, key, mi.load_dict(bsdf))}
    if sh == "leaves":
        P, F = meshes.leaf_cards(np.random.default_rng(o["seed"]), o["center"], o["count"], o["size"], o["spread"])
        return {key: meshes.to_mitsuba(P, F, key, mi.load_dict(bsdf))}
    if sh == "curves":
        # Mitsuba reads curves from a file: one control point "x y z radius" per line,
        # curves separated by empty lines
        fd, path = tempfile.mkstemp(suffix=".txt", prefix="mcdenoise-curves-")
        with os.fdopen(fd, "w") as f:
            f.write("\n\n".join("\n".join(" ".join(repr(float(v)) for v in p) for p in st) for st in o["strands"]))
            f.write("\n")
        _TEMP_FILES.append(path)
        return {key: {"type": "linearcurve", "filename": path, "bsdf": bsdf}}
    if sh == "clutter":
        group = {"type": "shapegroup"}
        for i, g in enumerate(o["group"]):
            s = g["size"]
            b = _material(g["material"])
            off = [(i - 1) * 2.5 * s, 0, 0]
            if g["shape"] == "sphere":
                group[f"s{i}"] = {"type": "sphere", "center": [off[0], s, 0], "radius": s, "bsdf": b}
            elif g["shape"] == "cube":
                group[f"s{i}"] = {"type": "cube", "to_world": _affine(np.eye(3), [off[0], s, 0], [s, s, s]), "bsdf": b}
            else:
                group[f"s{i}"] = {"type": "cylinder", "p0": [off[0], 0, 0], "p1": [off[0], 3 * s, 0], "radius": s * 0.5, "bsdf": b}
        out = {f"{key}_group": group}
        for j, inst in enumerate(o["instances"]):
            out[f"{key}_i{j}"] = {"type": "instance", "shapegroup": {"type": "ref", "id": f"{key}_group"},
                                  "to_world": _affine(_rot_matrix([0, inst["rot"], 0]), inst["pos"], [inst["scale"]] * 3)}
        return out
    raise ValueError(f"unknown shape {sh!r}")


def _env_bitmap(e, w=512, h=256):
    """Lat-long environment: zenith/horizon/ground gradient with soft noise and an optional sun."""
    v = (np.arange(h) + 0.5) / h  # 0 = top
    el = (0.5 - v) * math.pi  # elevation
    u = (np.arange(w) + 0.5) / w
    zen, hor, gnd = (np.asarray(e[k], np.float64) for k in ("zenith", "horizon", "ground"))
    t = np.clip(np.sin(el), 0, 1)[:, None, None]
    sky = hor * (1 - t) ** 2 + zen * (1 - (1 - t) ** 2)
    below = (el < 0)[:, None, None]
    img = np.where(below, gnd * np.ones((1, 1, 3)) + hor * 0.2 * np.exp(el[:, None, None] * 8), sky)
    img = np.broadcast_to(img, (h, w, 3)).copy()
    rng = np.random.default_rng(e.get("seed", 0))
    img *= (0.85 + 0.3 * textures.value_noise_2d(rng, w, 6, 3)[: h])[..., None]
    if "sun" in e:
        s = e["sun"]
        se, sa = math.radians(s["elevation"]), math.radians(s["azimuth"])
        sd = np.array([math.cos(se) * math.sin(sa), math.sin(se), math.cos(se) * math.cos(sa)])
        # Mitsuba envmap: u -> phi, v -> theta, direction (sin th sin ph, cos th, -sin th cos ph)
        th = v * math.pi
        ph = u * 2 * math.pi
        d = np.stack([np.sin(th)[:, None] * np.sin(ph)[None, :], np.cos(th)[:, None] * np.ones((1, w)),
                      -np.sin(th)[:, None] * np.cos(ph)[None, :]], -1)
        ang = np.arccos(np.clip(d @ sd, -1, 1))
        img += (ang < math.radians(s["size_deg"] / 2))[..., None] * s["strength"] * np.array([1.0, 0.92, 0.8])
    return (img * e["scale"]).astype(np.float32)


def _emitter_dicts(e, key):
    import mitsuba as mi

    black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
    if e["type"] == "rect":
        R = _frame_for_normal(e["normal"])
        return {key: {"type": "rectangle", "to_world": _affine(R, e["center"], [e["half"][0], e["half"][1], 1]), "bsdf": black,
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": e["radiance"]}}}}
    if e["type"] == "sphere":
        return {key: {"type": "sphere", "center": e["center"], "radius": e["radius"], "bsdf": black,
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": e["radiance"]}}}}
    if e["type"] == "cube":
        return {key: {"type": "cube", "to_world": _affine(_rot_matrix(e.get("rot", [0, 0, 0])), e["center"], e["half"]),
                      "bsdf": black, "emitter": {"type": "area", "radiance": {"type": "rgb", "value": e["radiance"]}}}}
    if e["type"] == "cylinder":
        return {key: {"type": "cylinder", "p0": e["p0"], "p1": e["p1"], "radius": e["radius"], "bsdf": black,
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": e["radiance"]}}}}
    if e["type"] == "disk":
        R = _frame_for_normal(e["normal"])
        return {key: {"type": "disk", "to_world": _affine(R, e["center"], [e["radius"]] * 2 + [1]), "bsdf": black,
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": e["radiance"]}}}}
    if e["type"] == "env":
        return {key: {"type": "envmap", "bitmap": mi.Bitmap(_env_bitmap(e))}}
    raise ValueError(f"unknown emitter {e['type']!r}")


def build(spec: dict, width: int, height: int):
    """Load a spec as a mitsuba Scene with a box-filtered film of width x height."""
    import mitsuba as mi

    cam = spec["camera"]
    to_world = mi.ScalarTransform4f().look_at(origin=cam["origin"], target=cam["target"], up=cam["up"])
    film = {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"}, "pixel_format": "rgb"}
    if cam.get("aperture", 0) > 0:
        sensor = {"type": "thinlens", "fov": cam["fov"], "fov_axis": "x", "aperture_radius": cam["aperture"],
                  "focus_distance": cam["focus"], "to_world": to_world, "film": film}
    else:
        sensor = {"type": "perspective", "fov": cam["fov"], "fov_axis": "x", "to_world": to_world, "film": film}
    d = {"type": "scene", "sensor": sensor}
    for i, o in enumerate(spec["objects"]):
        d.update(_shape_dicts(o, f"o{i}"))
    for i, e in enumerate(spec["emitters"]):
        d.update(_emitter_dicts(e, f"e{i}"))
    try:
        return mi.load_dict(d)
    finally:
        while _TEMP_FILES:
            os.unlink(_TEMP_FILES.pop())


def camera_params(spec: dict, width: int) -> dict:
    """Pixel angle (radians per pixel at the image centre), focus distance and aperture."""
    cam = spec["camera"]
    pixel_angle = 2.0 * math.tan(math.radians(cam["fov"]) / 2.0) / width
    return {"pixel_angle": pixel_angle, "focus": float(cam.get("focus", 1.0)), "aperture": float(cam.get("aperture", 0.0))}


def spec_copy(spec: dict) -> dict:
    return copy.deepcopy(spec)

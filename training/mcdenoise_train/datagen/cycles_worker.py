"""Blender Cycles side of the data generator: builds a scene spec through bpy and renders it.

Runs in the Python that has `bpy` (Blender as a module, `bpy==5.0.1`, Python 3.11; it pins
numpy 1.26, so it lives in its own environment, see cycles.py):

    python -m mcdenoise_train.datagen.cycles_worker JOB.json

JOB.json: {"spec": ..., "width": W, "height": H, "max_depth": 6, "out": DIR,
"renders": [{"name": ..., "spp": n, "seed": s}, ...]}. The scene is built once; every
render is written to DIR/<name>.exr as Blender's multi-layer EXR with the passes the
frame needs (Combined, Diffuse/Glossy/Transmission Direct/Indirect/Color, Emission,
Environment, Denoising Albedo/Normal/Depth). Each render uses the sample subset
[1, n + 1): Cycles sends sample 0 of every pixel through the pixel centre whatever the
seed, so renders that include it are correlated; without it, renders with different seeds
are independent, which the variance estimate needs.

The spec's world is Y-up (Mitsuba); Blender's is Z-up: (x, y, z) -> (x, -z, y).
Materials map to Cycles nodes: diffuse -> Diffuse BSDF; plastics -> Principled (dielectric,
IOR 1.5, roughness sqrt(alpha)); conductors -> Principled metallic with the metal's
normal-incidence colour; dielectrics -> Glass BSDF; bump/normal maps -> Bump/Normal Map
nodes; emitters -> Emission shaders on their shapes; the environment -> an equirectangular
world texture resampled from the spec's lat-long map.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

from . import meshes, scenes, textures

#: Normal-incidence reflectance (linear RGB) of the conductors the specs use.
METAL_F0 = {"Au": (1.0, 0.766, 0.336), "Cu": (0.955, 0.638, 0.538), "Al": (0.913, 0.922, 0.924),
            "Ag": (0.972, 0.960, 0.915), "Cr": (0.550, 0.556, 0.554), "W": (0.504, 0.498, 0.478),
            "Ir": (0.75, 0.72, 0.70), "Rh": (0.80, 0.78, 0.77), "TiN": (0.80, 0.60, 0.25),
            "CuO": (0.27, 0.24, 0.22)}


def _b(p):
    """Mitsuba (Y-up) point/vector to Blender (Z-up)."""
    p = np.asarray(p, np.float64)
    return np.stack([p[..., 0], -p[..., 2], p[..., 1]], -1)


def _mesh_object(bpy, name, P, F, mat, smooth=False, uv=None, colors=None):
    me = bpy.data.meshes.new(name)
    me.from_pydata(_b(P).tolist(), [], np.asarray(F).tolist())
    if uv is not None:
        layer = me.uv_layers.new(name="UVMap")
        loops = np.array([v for poly in np.asarray(F) for v in poly])
        layer.data.foreach_set("uv", np.asarray(uv, np.float32)[loops].ravel())
    if colors is not None:
        attr = me.color_attributes.new("vertex_color", "FLOAT_COLOR", "POINT")
        rgba = np.concatenate([colors, np.ones((len(colors), 1))], 1).astype(np.float32)
        attr.data.foreach_set("color", rgba.ravel())
    me.update()
    if smooth:
        me.shade_smooth()
    ob = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(ob)
    if mat is not None:
        me.materials.append(mat)
    return ob


def _uv_sphere(center, radius, nu=48, nv=24):
    th = np.linspace(0, np.pi, nv + 1)
    ph = np.linspace(0, 2 * np.pi, nu + 1)
    T, Ph = np.meshgrid(th, ph, indexing="ij")
    P = np.stack([np.sin(T) * np.cos(Ph), np.cos(T), np.sin(T) * np.sin(Ph)], -1).reshape(-1, 3)
    uv = np.stack([Ph / (2 * np.pi), 1 - T / np.pi], -1).reshape(-1, 2)
    idx = np.arange((nv + 1) * (nu + 1)).reshape(nv + 1, nu + 1)
    # counter-clockwise seen from outside: normals point out (one-sided emitters need it)
    F = np.stack([idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()], 1)
    return P * radius + np.asarray(center), F, uv


def _rect(center, normal, half):
    R = scenes._frame_for_normal(normal)
    local = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64) * [half[0], half[1], 1]
    return local @ R.T + np.asarray(center), np.array([[0, 1, 2, 3]]), np.array([[0, 0], [1, 0], [1, 1], [0, 1]])


def _box(center, half, rot):
    R = scenes._rot_matrix(rot)
    c = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64) * np.asarray(half)
    F = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])
    return c @ R.T + np.asarray(center), F


def _tube(p0, p1, radius, n=32):
    p0, p1 = np.asarray(p0, np.float64), np.asarray(p1, np.float64)
    a = p1 - p0
    a /= np.linalg.norm(a)
    u = np.cross(a, [0, 1, 0] if abs(a[1]) < 0.9 else [1, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(a, u)
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.cos(t)[:, None] * u + np.sin(t)[:, None] * v
    P = np.concatenate([p0 + radius * ring, p1 + radius * ring])
    F = np.array([[i, (i + 1) % n, n + (i + 1) % n, n + i] for i in range(n)])
    return P, F


def _disk(center, normal, radius, n=48):
    R = scenes._frame_for_normal(normal)
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    P = np.concatenate([[[0, 0, 0]], np.stack([np.cos(t), np.sin(t), np.zeros(n)], 1)]) * radius
    F = np.array([[0, 1 + i, 1 + (i + 1) % n] for i in range(n)])
    return P @ R.T + np.asarray(center), F


class Builder:
    def __init__(self, bpy):
        self.bpy = bpy
        self.n = 0

    def _name(self, base):
        self.n += 1
        return f"{base}{self.n}"

    def _image(self, rgb, name):
        h, w = rgb.shape[:2]
        img = self.bpy.data.images.new(self._name(name), w, h, float_buffer=True)
        rgba = np.concatenate([rgb.reshape(h, w, -1)[..., :3] if rgb.ndim == 3 and rgb.shape[-1] >= 3
                               else np.repeat(rgb.reshape(h, w, 1), 3, -1), np.ones((h, w, 1))], -1)
        img.colorspace_settings.name = "Non-Color"  # before the pixels: setting it regenerates the image
        img.pixels.foreach_set(np.ascontiguousarray(rgba[::-1], np.float32).ravel())
        img.pack()
        return img

    def _tex_node(self, nt, rgb, scale, name):
        tex = nt.nodes.new("ShaderNodeTexImage")
        tex.image = self._image(rgb, name)
        tex.interpolation = "Linear"
        mp = nt.nodes.new("ShaderNodeMapping")
        mp.inputs["Scale"].default_value = (scale, scale, 1.0)
        uv = nt.nodes.new("ShaderNodeTexCoord")
        nt.links.new(uv.outputs["UV"], mp.inputs["Vector"])
        nt.links.new(mp.outputs["Vector"], tex.inputs["Vector"])
        return tex

    def material(self, m):
        bpy = self.bpy
        mat = bpy.data.materials.new(self._name("mat"))
        mat.use_nodes = True
        nt = mat.node_tree
        for node in list(nt.nodes):
            nt.nodes.remove(node)
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        t = m["type"]

        def color_socket(sock):
            if "vertex_pattern" in m:
                a = nt.nodes.new("ShaderNodeAttribute")
                a.attribute_name = "vertex_color"
                nt.links.new(a.outputs["Color"], sock)
            elif "texture" in m:
                tx = m["texture"]
                img = textures.colorize(textures.pattern_2d(tx["pattern"], tx["seed"], 256), tx["c0"], tx["c1"])
                nt.links.new(self._tex_node(nt, img, tx.get("scale", 1.0), "tex").outputs["Color"], sock)
            else:
                sock.default_value = (*m.get("color", [0.5, 0.5, 0.5]), 1.0)

        rough = math.sqrt(m.get("alpha", 0.0)) if t.startswith("rough") else 0.0
        if t == "diffuse":
            b = nt.nodes.new("ShaderNodeBsdfDiffuse")
            color_socket(b.inputs["Color"])
        elif t in ("plastic", "roughplastic"):
            b = nt.nodes.new("ShaderNodeBsdfPrincipled")
            color_socket(b.inputs["Base Color"])
            b.inputs["Roughness"].default_value = rough
            b.inputs["IOR"].default_value = 1.5
        elif t in ("conductor", "roughconductor"):
            b = nt.nodes.new("ShaderNodeBsdfPrincipled")
            b.inputs["Base Color"].default_value = (*METAL_F0[m["material"]], 1.0)
            b.inputs["Metallic"].default_value = 1.0
            b.inputs["Roughness"].default_value = rough
            if "alpha_texture" in m:
                at = m["alpha_texture"]
                a = at["lo"] + (at["hi"] - at["lo"]) * textures.pattern_2d(at["pattern"], at["seed"], 128)
                tx = self._tex_node(nt, np.sqrt(a), at.get("scale", 1.0), "rough")
                nt.links.new(tx.outputs["Color"], b.inputs["Roughness"])
        elif t in ("dielectric", "roughdielectric"):
            b = nt.nodes.new("ShaderNodeBsdfGlass")
            b.inputs["IOR"].default_value = m["ior"]
            b.inputs["Roughness"].default_value = rough
            b.distribution = "GGX"
        else:
            raise ValueError(f"unknown material {t!r}")
        if "bump" in m:
            bm = m["bump"]
            p = textures.pattern_2d(bm["pattern"], bm["seed"], 256)
            tx = self._tex_node(nt, p, bm.get("scale", 1.0), "bump")
            if bm.get("kind", "bump") == "normal":
                gy, gx = np.gradient(p)
                n = np.stack([-gx * bm["strength"] * 8, -gy * bm["strength"] * 8, np.ones_like(p)], -1)
                n /= np.linalg.norm(n, axis=-1, keepdims=True)
                tx.image = self._image(0.5 * n + 0.5, "nrm")
                nm = nt.nodes.new("ShaderNodeNormalMap")
                nt.links.new(tx.outputs["Color"], nm.inputs["Color"])
                nt.links.new(nm.outputs["Normal"], b.inputs["Normal"])
            else:
                bn = nt.nodes.new("ShaderNodeBump")
                bn.inputs["Strength"].default_value = min(1.0, float(bm["strength"]))
                bn.inputs["Distance"].default_value = 0.01
                nt.links.new(tx.outputs["Color"], bn.inputs["Height"])
                nt.links.new(bn.outputs["Normal"], b.inputs["Normal"])
        nt.links.new(b.outputs[0], out.inputs["Surface"])
        return mat

    def emission(self, radiance):
        mat = self.bpy.data.materials.new(self._name("emit"))
        mat.use_nodes = True
        nt = mat.node_tree
        for node in list(nt.nodes):
            nt.nodes.remove(node)
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        em = nt.nodes.new("ShaderNodeEmission")
        em.inputs["Color"].default_value = (*radiance, 1.0)
        em.inputs["Strength"].default_value = 1.0
        # one-sided like Mitsuba's area lights: the back face is black diffuse
        back = nt.nodes.new("ShaderNodeBsdfDiffuse")
        back.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
        geo = nt.nodes.new("ShaderNodeNewGeometry")
        mix = nt.nodes.new("ShaderNodeMixShader")
        nt.links.new(geo.outputs["Backfacing"], mix.inputs["Fac"])
        nt.links.new(em.outputs[0], mix.inputs[1])
        nt.links.new(back.outputs[0], mix.inputs[2])
        nt.links.new(mix.outputs[0], out.inputs["Surface"])
        return mat

    def shape(self, o, mat):
        sh = o["shape"]
        name = self._name(sh)
        if sh == "rect":
            P, F, uv = _rect(o["center"], o["normal"], o["half"])
            uvl = uv[np.asarray(F).ravel()]
            return [_mesh_object(self.bpy, name, P, F, mat, uv=uv if uvl is not None else None)]
        if sh == "disk":
            P, F = _disk(o["center"], o["normal"], o["radius"])
            return [_mesh_object(self.bpy, name, P, F, mat)]
        if sh == "sphere":
            P, F, uv = _uv_sphere(o["center"], o["radius"])
            return [_mesh_object(self.bpy, name, P, F, mat, smooth=True, uv=uv)]
        if sh == "cube":
            P, F = _box(o["center"], o["half"], o.get("rot", [0, 0, 0]))
            return [_mesh_object(self.bpy, name, P, F, mat)]
        if sh == "cylinder":
            P, F = _tube(o["p0"], o["p1"], o["radius"])
            return [_mesh_object(self.bpy, name, P, F, mat, smooth=True)]
        if sh in ("dsphere", "torus"):
            P, F = scenes.generated_mesh(o)
            vp = o["material"].get("vertex_pattern")
            colors = textures.colorize(textures.pattern_3d(vp["pattern"], P, vp["seed"]), vp["c0"], vp["c1"]) if vp else None
            return [_mesh_object(self.bpy, name, P, F, mat, smooth=True, colors=colors)]
        if sh == "heightfield":
            P, F = meshes.heightfield(o["seed"], o["half"], o["amplitude"], o["freq"])
            return [_mesh_object(self.bpy, name, P + np.asarray(o["center"]), F, mat, smooth=True)]
        if sh == "leaves":
            P, F = meshes.leaf_cards(np.random.default_rng(o["seed"]), o["center"], o["count"], o["size"], o["spread"])
            return [_mesh_object(self.bpy, name, P, F, mat)]
        if sh == "curves":
            cu = self.bpy.data.curves.new(name, "CURVE")
            cu.dimensions = "3D"
            cu.bevel_depth = 1.0
            cu.bevel_resolution = 1
            for st in o["strands"]:
                sp = cu.splines.new("POLY")
                sp.points.add(len(st) - 1)
                pts = np.asarray(st, np.float64)
                xyz = _b(pts[:, :3])
                sp.points.foreach_set("co", np.concatenate([xyz, np.ones((len(st), 1))], 1).astype(np.float32).ravel())
                sp.points.foreach_set("radius", pts[:, 3].astype(np.float32))
            ob = self.bpy.data.objects.new(name, cu)
            self.bpy.context.scene.collection.objects.link(ob)
            cu.materials.append(mat)
            return [ob]
        if sh == "clutter":
            out = []
            for inst in o["instances"]:
                R = scenes._rot_matrix([0, inst["rot"], 0]) * inst["scale"]
                for i, g in enumerate(o["group"]):
                    s = g["size"]
                    gm = self.material(g["material"])
                    off = np.array([(i - 1) * 2.5 * s, 0, 0])
                    if g["shape"] == "sphere":
                        P, F, _ = _uv_sphere(off + [0, s, 0], s, 16, 8)
                    elif g["shape"] == "cube":
                        P, F = _box(off + [0, s, 0], [s, s, s], [0, 0, 0])
                    else:
                        P, F = _tube(off, off + [0, 3 * s, 0], s * 0.5, 12)
                    out.append(_mesh_object(self.bpy, self._name("cl"), P @ R.T + np.asarray(inst["pos"]), F, gm,
                                            smooth=g["shape"] != "cube"))
            return out
        raise ValueError(f"unknown shape {sh!r}")

    def world(self, e):
        bpy = self.bpy
        world = bpy.data.worlds.new(self._name("world"))
        bpy.context.scene.world = world
        world.use_nodes = True
        nt = world.node_tree
        for node in list(nt.nodes):
            nt.nodes.remove(node)
        out = nt.nodes.new("ShaderNodeOutputWorld")
        bg = nt.nodes.new("ShaderNodeBackground")
        nt.links.new(bg.outputs[0], out.inputs["Surface"])
        if e is None:
            bg.inputs["Color"].default_value = (0, 0, 0, 1)
            return
        img = scenes._env_bitmap(e)  # Mitsuba lat-long: u -> phi, v -> theta (Y up)
        h, w = img.shape[:2]
        # resample into Blender's equirectangular convention (Z up):
        # u = atan2(d.y, -d.x) / 2pi + 0.5, v = atan2(d.z, hypot(d.x, d.y)) / pi + 0.5
        u = (np.arange(w) + 0.5) / w
        v = (np.arange(h) + 0.5) / h
        U, V = np.meshgrid(u, v)
        phi_b = (U - 0.5) * 2 * np.pi
        el = (V - 0.5) * np.pi
        dx, dy, dz = -np.cos(el) * np.cos(phi_b), np.cos(el) * np.sin(phi_b), np.sin(el)
        mx, my, mz = dx, dz, -dy  # Blender -> Mitsuba
        th = np.arccos(np.clip(my, -1, 1))
        ph = np.mod(np.arctan2(mx, -mz), 2 * np.pi)
        iu = np.clip((ph / (2 * np.pi) * w).astype(int), 0, w - 1)
        iv = np.clip((th / np.pi * h).astype(int), 0, h - 1)
        res = img[iv, iu]  # rows: v from bottom (Blender stores the bottom row first)
        tex = nt.nodes.new("ShaderNodeTexEnvironment")
        bimg = bpy.data.images.new(self._name("env"), w, h, float_buffer=True)
        rgba = np.concatenate([res, np.ones((h, w, 1))], -1).astype(np.float32)
        bimg.colorspace_settings.name = "Non-Color"
        bimg.pixels.foreach_set(rgba.ravel())
        bimg.pack()
        tex.image = bimg
        tex.interpolation = "Closest"
        nt.links.new(tex.outputs["Color"], bg.inputs["Color"])


def build(bpy, spec, width, height, max_depth):
    from mathutils import Matrix

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    cy = scene.cycles
    cy.device = "CPU"
    cy.use_denoising = False
    cy.use_adaptive_sampling = False
    cy.pixel_filter_type = "BOX"
    cy.filter_width = 1.0
    cy.sample_clamp_direct = 0.0
    cy.sample_clamp_indirect = 0.0
    bounces = max(1, max_depth - 1)
    cy.max_bounces = bounces
    cy.diffuse_bounces = cy.glossy_bounces = cy.transmission_bounces = cy.transparent_max_bounces = bounces
    cy.caustics_reflective = cy.caustics_refractive = True
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"
    vl = scene.view_layers[0]
    for p in ("use_pass_combined", "use_pass_diffuse_direct", "use_pass_diffuse_indirect", "use_pass_diffuse_color",
              "use_pass_glossy_direct", "use_pass_glossy_indirect", "use_pass_glossy_color",
              "use_pass_transmission_direct", "use_pass_transmission_indirect", "use_pass_transmission_color",
              "use_pass_emit", "use_pass_environment", "use_pass_z"):
        setattr(vl, p, True)
    vl.cycles.denoising_store_passes = True
    fmt = scene.render.image_settings
    fmt.media_type = "MULTI_LAYER_IMAGE"
    fmt.file_format = "OPEN_EXR_MULTILAYER"
    fmt.color_depth = "32"
    fmt.exr_codec = "ZIP"

    b = Builder(bpy)
    for o in spec["objects"]:
        b.shape(o, b.material(o["material"]) if o["shape"] != "clutter" else None)
    env = None
    for e in spec["emitters"]:
        if e["type"] == "env":
            env = e
            continue
        mat = b.emission(e["radiance"])
        if e["type"] == "rect":
            P, F, _ = _rect(e["center"], e["normal"], e["half"])
            _mesh_object(bpy, b._name("light"), P, F, mat)
        elif e["type"] == "sphere":
            P, F, _ = _uv_sphere(e["center"], e["radius"], 24, 12)
            _mesh_object(bpy, b._name("light"), P, F, mat, smooth=True)
        elif e["type"] == "cube":
            P, F = _box(e["center"], e["half"], e.get("rot", [0, 0, 0]))
            _mesh_object(bpy, b._name("light"), P, F, mat)
        elif e["type"] == "cylinder":
            P, F = _tube(e["p0"], e["p1"], e["radius"])
            _mesh_object(bpy, b._name("light"), P, F, mat, smooth=True)
        elif e["type"] == "disk":
            P, F = _disk(e["center"], e["normal"], e["radius"])
            _mesh_object(bpy, b._name("light"), P, F, mat)
        else:
            raise ValueError(f"unknown emitter {e['type']!r}")
    b.world(env)

    cam = spec["camera"]
    cd = bpy.data.cameras.new("camera")
    cd.sensor_fit = "HORIZONTAL"
    cd.sensor_width = 36.0
    cd.angle = math.radians(cam["fov"])
    cd.clip_start = 1e-3
    if cam.get("aperture", 0) > 0:
        cd.dof.use_dof = True
        cd.dof.focus_distance = cam["focus"]
        # Cycles' aperture radius = lens [mm] / (2 f-stop) * 1e-3 scene units
        cd.dof.aperture_fstop = cd.lens * 1e-3 / (2.0 * cam["aperture"])
    co = bpy.data.objects.new("camera", cd)
    scene.collection.objects.link(co)
    o, t, up = _b(cam["origin"]), _b(cam["target"]), _b(cam["up"])
    f = (t - o) / np.linalg.norm(t - o)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = r, u, -f, o
    co.matrix_world = Matrix(M.tolist())
    scene.camera = co
    return scene


def main(argv=None) -> int:
    import bpy

    job = json.loads(Path((argv or sys.argv[1:])[0]).read_text())
    scene = build(bpy, job["spec"], job["width"], job["height"], job.get("max_depth", 6))
    cy = scene.cycles
    out = Path(job["out"])
    out.mkdir(parents=True, exist_ok=True)
    for r in job["renders"]:
        cy.seed = int(r["seed"]) % (1 << 31)
        cy.samples = int(r["spp"]) + 1
        cy.use_sample_subset = True
        cy.sample_offset = 1
        cy.sample_subset_length = int(r["spp"])
        scene.render.filepath = str(out / f"{r['name']}.exr")
        bpy.ops.render.render(write_still=True)
        print(f"rendered {r['name']}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The path tracer: split radiance, first-hit features and the light transport covariance.

One call of `trace` traces one camera sample per lane (a Dr.Jit symbolic loop, so a whole
pass compiles to one kernel) and returns per-lane values:

- `color` = `diffuse` + `specular`, with the split below;
- `albedo`, `normal`, `depth` at the first hit;
- `cov`, the per-sample covariance feature l (see covariance.log_eta), and `cov_energy`,
  the luminance of the energy leaving the first hit towards the camera (next-event terms
  unshadowed) with which render.py weights l across samples, when enabled.

Unidirectional path tracing with next-event estimation and multiple importance sampling,
Russian roulette after `rr_depth` bounces, up to `max_depth` path segments.

# The diffuse/specular split

The split is decided at the first surface the camera ray hits, by lobe, for every
estimator that lands there (definition used by KPCN, made exact):

- `diffuse`: light scattered by the first hit's *diffuse* lobes (BSDFFlags.DiffuseReflection
  and DiffuseTransmission), whatever happens to it before (direct and indirect).
- `specular`: everything else: light scattered by glossy or delta lobes at the first hit
  (plastic coatings, metals, glass, rough or smooth), emission seen directly, and the
  environment seen directly.

For next-event estimation at the first hit the BSDF value is split as f = f_d + f_s with
f_d the BSDF evaluated with only the diffuse lobes enabled (`BSDFContext.type_mask`). For
the direction sampled at the first hit with weight w = f cos / pdf, the diffuse part is
w_d = f_d cos / pdf (0 when a delta lobe was sampled) and w_s = w - w_d; the path's later
contributions go to diffuse with throughput w_d * (...) and to specular with w_s * (...).
Both components are unbiased estimators of their own integrals, and diffuse + specular
equals the total radiance up to float rounding, for every sample.

# Covariance records

For the first `cov_depth` vertices of the path, the loop stores what covariance tracing
needs (geometry, local curvature, lobe roughness, the next-event light's covariance with
its occlusion term, and the energies of every contribution leaving the vertex). After the
loop, `_covariance_backward` propagates covariance from the deepest recorded vertex back
to the camera: light travels from the emitters towards the camera, in the order of
Belcour et al. 2013, while the path was generated from the camera (see training-data.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi

from . import covariance as cv
from .covariance import Cov

LUM = (0.2126, 0.7152, 0.0722)


def lum(c):
    return c[0] * LUM[0] + c[1] * LUM[1] + c[2] * LUM[2]


def mis_weight(a, b):
    a2 = a * a
    return dr.detach(dr.select(a > 0, a2 / (a2 + b * b), 0.0), True)


@dataclass
class Options:
    max_depth: int = 6
    rr_depth: int = 4
    covariance: bool = True
    cov_depth: int = 3  # full covariance vertices; one more record takes the emission found next
    probe_depth: int = 2  # vertices whose next-event rays are probed for occluder edges
    probe_offset: float = 1.5  # probe offset in pixel footprints
    cov_floor_px: float = 4.0  # eps = (1 / (2 pi cov_floor_px))^2 cycles^2 / pixel^2


@dataclass
class VertexRec:
    """What the backward covariance pass needs about one path vertex."""

    valid: mi.Bool = field(default_factory=mi.Bool)
    escaped: mi.Bool = field(default_factory=mi.Bool)
    t_in: mi.Float = field(default_factory=mi.Float)
    d_in: mi.Vector3f = field(default_factory=mi.Vector3f)
    n: mi.Vector3f = field(default_factory=mi.Vector3f)
    s: mi.Vector3f = field(default_factory=mi.Vector3f)
    t: mi.Vector3f = field(default_factory=mi.Vector3f)
    W: mi.Matrix2f = field(default_factory=mi.Matrix2f)
    e_em: mi.Float = field(default_factory=mi.Float)
    c_em: mi.Float = field(default_factory=mi.Float)
    nee: Cov = field(default_factory=Cov.zero)
    d_l: mi.Vector3f = field(default_factory=mi.Vector3f)
    e_nd: mi.Float = field(default_factory=mi.Float)
    e_ns: mi.Float = field(default_factory=mi.Float)
    e_bd: mi.Float = field(default_factory=mi.Float)
    e_bs: mi.Float = field(default_factory=mi.Float)
    b: mi.Float = field(default_factory=mi.Float)
    refract: mi.Bool = field(default_factory=mi.Bool)
    eta: mi.Float = field(default_factory=mi.Float)

    DRJIT_STRUCT = {
        "valid": mi.Bool, "escaped": mi.Bool, "t_in": mi.Float, "d_in": mi.Vector3f, "n": mi.Vector3f,
        "s": mi.Vector3f, "t": mi.Vector3f, "W": mi.Matrix2f, "e_em": mi.Float, "c_em": mi.Float,
        "nee": Cov, "d_l": mi.Vector3f, "e_nd": mi.Float, "e_ns": mi.Float, "e_bd": mi.Float,
        "e_bs": mi.Float, "b": mi.Float, "refract": mi.Bool, "eta": mi.Float,
    }

    @staticmethod
    def empty(n):
        z = dr.zeros(mi.Float, n)
        zb = dr.zeros(mi.Bool, n)
        v = dr.zeros(mi.Vector3f, n)
        m = mi.Matrix2f(z, z, z, z)
        return VertexRec(zb, zb, z, v, v, v, v, m, z, z, Cov(m, m, m), v, z, z, z, z, z, zb, z + 1.0)


def _select_rec(mask, new: VertexRec, old: VertexRec) -> VertexRec:
    out = {}
    for k in VertexRec.DRJIT_STRUCT:
        a, b = getattr(new, k), getattr(old, k)
        out[k] = a.select(mask, b) if isinstance(a, Cov) else dr.select(mask, a, b)
    return VertexRec(**out)


def _solid_angle_c(pdf, n_emitters, delta=None):
    """Angular frequency variance c = 1/(2 pi sigma)^2 of a light of apparent solid angle
    1/(pdf * n_emitters) (uniform emitter selection), sigma = sqrt(Omega / 12)."""
    omega = dr.minimum(dr.rcp(dr.maximum(pdf * n_emitters, 1e-12)), 4.0 * math.pi)
    if delta is not None:
        omega = dr.select(delta, 1e-8, omega)
    omega = dr.maximum(omega, 1e-8)
    return 12.0 / (4.0 * math.pi * math.pi * omega)


def _shape_operator(si, active):
    """W (2x2, in the shading frame s, t): from the normal and position partials for
    Mitsuba's analytic shapes, from the `vertex_curv` attribute (isotropic mean
    curvature) for our generated meshes."""
    fr = si.sh_frame
    J = cv.M2(dr.dot(si.dp_du, fr.s), dr.dot(si.dp_dv, fr.s), dr.dot(si.dp_du, fr.t), dr.dot(si.dp_dv, fr.t))
    N = cv.M2(dr.dot(si.dn_du, fr.s), dr.dot(si.dn_dv, fr.s), dr.dot(si.dn_du, fr.t), dr.dot(si.dn_dv, fr.t))
    detJ = cv.det2(J)
    ok = dr.abs(detJ) > 1e-10
    W = N @ cv.inv2(J, 1e-10)
    W = cv.sym(W)
    W = dr.select(ok, W, cv.zeros2())
    shape = si.shape
    has_k = shape.has_attribute("vertex_curv", active)
    k = shape.eval_attribute_1("vertex_curv", si, active & has_k)
    W = dr.select(has_k, cv.eye2(k), W)
    # clamp absurd curvatures (degenerate parametrisations)
    lim = 1e4
    return cv.M2(dr.clip(W[0][0], -lim, lim), dr.clip(W[0][1], -lim, lim), dr.clip(W[1][0], -lim, lim),
                 dr.clip(W[1][1], -lim, lim))


@dataclass
class Camera:
    """Per-scene values the kernel reads as opaque variables (not literals), so one
    compiled kernel serves every scene, seed and sample count with the same code."""

    width: mi.UInt32
    film_size: mi.Vector2f
    pixel_angle: mi.Float
    aperture: mi.Float
    focus: mi.Float
    n_emitters: mi.Float

    @staticmethod
    def of(scene, width, height, pixel_angle):
        aperture, focus = sensor_lens(scene.sensors()[0])
        return Camera(dr.opaque(mi.UInt32, width),
                      mi.Vector2f(dr.opaque(mi.Float, width), dr.opaque(mi.Float, height)),
                      dr.opaque(mi.Float, pixel_angle), dr.opaque(mi.Float, aperture),
                      dr.opaque(mi.Float, focus), dr.opaque(mi.Float, max(len(scene.emitters()), 1)))


def trace(scene, sensor, sampler, pix, cam: Camera, opts: Options):
    """Trace one camera sample per lane through pixel `pix` (row-major index) of the
    film. Returns a dict of per-lane arrays."""
    n_lanes = dr.width(pix)
    px = pix % cam.width
    py = pix // cam.width
    pos = mi.Vector2f(mi.Float(px) + sampler.next_1d(), mi.Float(py) + sampler.next_1d())
    ap = sampler.next_2d()
    ray, _ = sensor.sample_ray(0.0, 0.5, pos / cam.film_size, ap)
    pixel_angle = cam.pixel_angle

    n_emitters = cam.n_emitters
    ctx = mi.BSDFContext()
    ctx_d = mi.BSDFContext()
    ctx_d.type_mask = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.DiffuseTransmission
    D = opts.cov_depth if opts.covariance else 0
    flags = mi.RayFlags.All | mi.RayFlags.dNSdUV if opts.covariance else mi.RayFlags.All

    zero3 = dr.zeros(mi.Color3f, n_lanes)
    state = dict(
        ray=mi.Ray3f(ray), depth=dr.zeros(mi.UInt32, n_lanes), active=dr.full(mi.Bool, True, n_lanes),
        beta=dr.full(mi.Color3f, 1.0, n_lanes), beta_d=dr.zeros(mi.Color3f, n_lanes), beta_s=dr.zeros(mi.Color3f, n_lanes),
        L=zero3, Ld=zero3, Ls=zero3, albedo=zero3, normal=dr.zeros(mi.Vector3f, n_lanes), dist=dr.zeros(mi.Float, n_lanes),
        path_len=dr.zeros(mi.Float, n_lanes),
        prev_si=dr.zeros(mi.SurfaceInteraction3f, n_lanes), prev_pdf=dr.ones(mi.Float, n_lanes),
        prev_delta=dr.full(mi.Bool, True, n_lanes),
    )
    state["prev_si"].p = mi.Point3f(ray.o)
    # records 0..D-1 are full vertices, record D only brings the emission it hits
    recs = [VertexRec.empty(n_lanes) for _ in range(D + 1 if D > 0 else 0)]

    def body(sampler, st, recs):
        ray, depth, active = st["ray"], st["depth"], st["active"]
        first = depth == 0
        si = scene.ray_intersect(ray, ray_flags=flags, coherent=first, active=active)
        valid = si.is_valid()

        # -- emission (surface emitters and the environment) --
        prev_si = st["prev_si"]
        emitter = si.emitter(scene, active)
        has_em = active & (emitter != None)  # noqa: E711
        ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
        em_pdf = scene.pdf_emitter_direction(prev_si, ds, has_em)
        mis = dr.select(first | st["prev_delta"], 1.0, mis_weight(st["prev_pdf"], em_pdf))
        Le = dr.select(has_em, mis * emitter.eval(si, has_em), 0.0)
        st["L"] = st["L"] + st["beta"] * Le
        st["Ld"] = st["Ld"] + dr.select(first, 0.0, st["beta_d"] * Le)
        st["Ls"] = st["Ls"] + dr.select(first, Le, st["beta_s"] * Le)

        # -- first-hit features --
        bsdf = si.bsdf(ray)
        hit0 = first & valid
        a_d = bsdf.eval(ctx_d, si, mi.Vector3f(0, 0, 1), hit0) * math.pi
        n_sh = si.sh_frame.n
        n_sh = dr.select(dr.dot(n_sh, ray.d) > 0, -n_sh, n_sh)
        st["albedo"] = dr.select(hit0, a_d, st["albedo"])
        st["normal"] = dr.select(hit0, n_sh, st["normal"])
        st["dist"] = dr.select(hit0, si.t, st["dist"])
        path_len = st["path_len"] + dr.select(valid, si.t, 0.0)

        active_next = active & valid & (depth + 1 < opts.max_depth)

        # -- next-event estimation, unshadowed value, shadow ray --
        active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        ds_l, em_w = scene.sample_emitter_direction(si, sampler.next_2d(), False, active_em)
        active_em &= ds_l.pdf != 0.0
        wo_l = si.to_local(ds_l.d)
        f_l, pdf_b = bsdf.eval_pdf(ctx, si, wo_l, active_em)
        f_ld = bsdf.eval(ctx_d, si, wo_l, active_em)
        mis_em = dr.select(ds_l.delta, 1.0, mis_weight(ds_l.pdf, pdf_b))
        c_l = dr.select(active_em, mis_em * em_w, 0.0)
        sray = si.spawn_ray_to(ds_l.p)
        pi0 = scene.ray_intersect_preliminary(sray, coherent=False, active=active_em)
        vis = active_em & ~pi0.is_valid()
        cvis = dr.select(vis, c_l, 0.0)
        st["L"] = st["L"] + st["beta"] * f_l * cvis
        st["Ld"] = st["Ld"] + dr.select(first, f_ld, st["beta_d"] * f_l) * cvis
        st["Ls"] = st["Ls"] + dr.select(first, f_l - f_ld, st["beta_s"] * f_l) * cvis

        # -- BSDF sampling --
        bs, w = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)
        delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        f_sd = bsdf.eval(ctx_d, si, bs.wo, active_next & ~delta)
        w_d = dr.select(delta | (bs.pdf <= 0), 0.0, f_sd / dr.maximum(bs.pdf, 1e-20))
        w_d = dr.select(active_next, w_d, 0.0)
        w = dr.select(active_next, w, 0.0)
        w_s = w - w_d
        st["beta_d"] = dr.select(first, w_d, st["beta_d"] * w)
        st["beta_s"] = dr.select(first, w_s, st["beta_s"] * w)
        st["beta"] = st["beta"] * w

        # -- covariance record of this vertex --
        if D > 0:
            n_g = si.n
            rec = VertexRec.empty(1)
            rec.valid = valid
            rec.escaped = active & ~valid
            rec.t_in = dr.select(valid, si.t, dr.inf)
            rec.d_in = ray.d
            rec.n, rec.s, rec.t = si.sh_frame.n, si.sh_frame.s, si.sh_frame.t
            rec.W = _shape_operator(si, active & valid)
            rec.e_em = dr.maximum(lum(Le), 0.0)
            rec.c_em = _solid_angle_c(em_pdf, n_emitters)
            # next-event light covariance, with the occluder-edge probes
            t_l = ds_l.dist
            O = cv.zeros2()
            d_occ = dr.zeros(mi.Float, 1)
            if opts.probe_depth > 0:
                probe_on = active_em & (depth < opts.probe_depth)
                delta_len = opts.probe_offset * path_len * pixel_angle
                la, lb = cv.basis(ds_l.d)
                side = dr.select(dr.dot(n_g, ds_l.d) >= 0, 1.0, -1.0)
                off = n_g * (side * 1e-4 * (1.0 + dr.max(dr.abs(si.p))))
                dl, hits, docc = [], [], []
                signs = sampler.next_2d(probe_on)
                for j, tan in enumerate((si.sh_frame.s, si.sh_frame.t)):
                    tan = tan * dr.select(signs[j] < 0.5, -1.0, 1.0)
                    # the offset point must be reachable along the surface (no probe from
                    # behind a wall meeting this one at a concave corner)
                    vr = mi.Ray3f(si.p + off, tan)
                    vr.maxt = delta_len
                    reach = ~scene.ray_intersect_preliminary(vr, coherent=False, active=probe_on).is_valid()
                    o = si.p + tan * delta_len + off
                    dv = ds_l.p - o
                    dd = dr.norm(dv)
                    pr = mi.Ray3f(o, dv / dd)
                    pr.maxt = dd * (1.0 - 1e-4)
                    pj = scene.ray_intersect_preliminary(pr, coherent=False, active=probe_on)
                    vj = ~pj.is_valid()
                    edge = probe_on & reach & (vj != vis)
                    dj = dr.select(vis, pj.t, pi0.t)
                    r = dr.clip(1.0 - dj * dr.rcp(dr.maximum(t_l, 1e-6)), 0.0, 1.0)
                    v3 = tan * (delta_len * r)
                    dl.append(mi.Vector2f(dr.dot(v3, la), dr.dot(v3, lb)))
                    hits.append(edge)
                    docc.append(dj)
                O = cv.occlusion_term(dl[0], dl[1], hits[0], hits[1])
                d_occ = dr.select(hits[0], docc[0], dr.select(hits[1], docc[1], 0.0))
            c_light = _solid_angle_c(ds_l.pdf, n_emitters, ds_l.delta)
            rec.nee = cv.light_at_receiver(c_light, t_l, d_occ, O)
            rec.d_l = ds_l.d
            f_ls = f_l - f_ld
            rec.e_nd = dr.select(active_em, dr.maximum(lum(f_ld * c_l), 0.0), 0.0)
            rec.e_ns = dr.select(active_em, dr.maximum(lum(f_ls * c_l), 0.0), 0.0)
            rec.e_bd = dr.maximum(lum(w_d), 0.0)
            rec.e_bs = dr.maximum(lum(w_s), 0.0)
            alpha = bsdf.eval_attribute_1("alpha", si, active_next)
            rec.b = cv.lobe_bandlimit(alpha)
            rec.refract = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Transmission)
            rec.eta = dr.select(rec.refract, dr.rcp(dr.maximum(bs.eta, 1e-4)), 1.0)
            recs = [_select_rec(active & (depth == k), rec, recs[k]) for k in range(D + 1)]

        # -- continue --
        st["ray"] = si.spawn_ray(si.to_world(bs.wo))
        st["prev_si"] = si
        st["prev_pdf"] = bs.pdf
        st["prev_delta"] = delta
        st["path_len"] = path_len
        rr = depth + 1 >= opts.rr_depth
        q = dr.minimum(dr.max(st["beta"]), 0.95)
        survive = ~rr | (sampler.next_1d() < q)
        inv_q = dr.select(rr, dr.rcp(dr.maximum(q, 1e-6)), 1.0)
        st["beta"] *= inv_q
        st["beta_d"] *= inv_q
        st["beta_s"] *= inv_q
        st["depth"] = depth + 1
        st["active"] = active_next & survive & (dr.max(st["beta"]) > 0)
        return sampler, st, recs

    sampler, state, recs = dr.while_loop(
        state=(sampler, state, recs),
        cond=lambda sampler, st, recs: st["active"],
        body=body,
        labels=("sampler", "state", "recs"),
        label="mcdenoise_path",
    )

    out = {"color": state["L"], "diffuse": state["Ld"], "specular": state["Ls"], "albedo": state["albedo"],
           "normal": state["normal"], "depth": state["dist"]}
    if D > 0:
        eps = (1.0 / (2.0 * math.pi * opts.cov_floor_px)) ** 2
        ell, energy = _covariance_backward(recs, pixel_angle, (cam.aperture, cam.focus), eps)
        out["cov"] = ell
        out["cov_energy"] = energy
    return out


def sensor_lens(sensor):
    p = mi.traverse(sensor)
    if "aperture_radius" in p.keys():
        return float(dr.ravel(p["aperture_radius"])[0]), float(dr.ravel(p["focus_distance"])[0])
    return 0.0, 1.0


def _covariance_backward(recs, pixel_angle, lens, eps):
    """Propagate covariance from the deepest recorded vertex to the camera (light order).
    The last record only contributes the emission it hit (an emitter or the environment
    reached from the last full vertex)."""
    D = len(recs) - 1
    # E_next, S_next: energy and covariance leaving vertex k+1 towards k (in the basis of
    # recs[k+1].d_in); esc_next, c_next: vertex k+1 is the environment, its frequency.
    for k in reversed(range(D + 1)):
        r = recs[k]
        if k == D:
            a_em = r.c_em * dr.rcp(dr.maximum(r.t_in * r.t_in, 1e-12))
            E_next = dr.select(r.valid | r.escaped, r.e_em, 0.0)
            S_next = Cov(cv.eye2(a_em), cv.zeros2(), cv.zeros2()).select(r.valid, Cov.zero())
            esc_next, c_next, t_next, d_next = r.escaped, r.c_em, r.t_in, r.d_in
            continue
        geo = cv.SurfaceGeo(r.n, r.s, r.t, r.W)
        bo = cv.basis(r.d_in)
        wo = -r.d_in
        # light arriving from the sampled direction (from vertex k+1, or the environment)
        arrive = cv.travel(S_next, dr.select(esc_next, 0.0, t_next))
        env = Cov(cv.zeros2(), cv.zeros2(), cv.eye2(c_next))
        arrive = env.select(esc_next, arrive)
        E_in = E_next
        bi = cv.basis(d_next)
        wi = -d_next
        # light arriving from the next-event sample
        bl = cv.basis(r.d_l)
        wl = -r.d_l
        parts = [
            (r.e_nd, cv.diffuse_transfer(r.nee, geo, bl, bo)),
            (r.e_ns, cv.specular_transfer(r.nee, geo, wl, bl, wo, bo, mi.Bool(False), mi.Float(1.0), r.b)),
            (r.e_bd * E_in, cv.diffuse_transfer(arrive, geo, bi, bo)),
            (r.e_bs * E_in, cv.specular_transfer(arrive, geo, wi, bi, wo, bo, r.refract, r.eta, r.b)),
        ]
        a_em = r.c_em * dr.rcp(dr.maximum(r.t_in * r.t_in, 1e-12))
        parts.append((r.e_em, Cov(cv.eye2(a_em), cv.zeros2(), cv.zeros2())))
        E = mi.Float(0.0)
        S = Cov.zero()
        for wgt, c in parts:
            wgt = dr.select(dr.isfinite(wgt), wgt, 0.0)
            E = E + wgt
            S = S.plus(c.scaled(wgt))
        inv = dr.select(E > 0, dr.rcp(E), 0.0)
        S = S.scaled(inv)
        # escaped records carry only the environment's energy; invalid ones nothing
        E_next = dr.select(r.valid, E, dr.select(r.escaped, r.e_em, 0.0))
        S_next = S.select(r.valid, Cov.zero())
        esc_next = r.escaped
        c_next = r.c_em
        t_next = r.t_in
        d_next = r.d_in
    r0 = recs[0]
    S_cam = cv.travel(S_next, dr.select(r0.valid, r0.t_in, 0.0))
    aperture, focus = lens
    S_cam = cv.lens(S_cam, focus, aperture).select(aperture > 0, S_cam)
    ell = cv.log_eta(S_cam, r0.t_in * pixel_angle, pixel_angle, eps)
    ok = r0.valid & dr.isfinite(ell) & dr.isfinite(E_next)
    ell = dr.select(ok, ell, 0.0)
    return ell, dr.select(ok, E_next, 0.0)

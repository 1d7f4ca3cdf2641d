"""Light transport covariance tracing (Belcour et al. 2013, after Durand et al. 2005).

The local light field around a ray is a 4-D function of two transverse positions
x = (x0, x1) and two direction perturbations theta = (t0, t1), both measured along an
orthonormal basis (a, b) perpendicular to the ray (`basis(d)`); theta is the change of
the *propagation* direction projected on (a, b). Sigma is the 4x4 covariance of the
local light field's Fourier spectrum, stored as three 2x2 blocks

    Sigma = [[A, B], [B^T, C]]    A: spatial, C: angular, B: spatial-angular.

Units: cycles per metre (spatial) and cycles per radian (angular).

Every linear change of the primal coordinates, q' = G q, changes the spectrum covariance
to Sigma' = G^-T Sigma G^-1. The operators of covariance tracing are built that way:

- `travel`: free-space transport by d is the primal shear x' = x + d theta.
- `specular_transfer`: projection of the incoming light field onto the surface, reflection
  or refraction of the central ray about the local (curved) normal, projection onto the
  outgoing ray. Curvature enters through the derivative of the normal, dn = W u.
- `bandlimit_angular`: a BRDF lobe of angular width s convolves the outgoing angle, which
  multiplies the spectrum by a Gaussian of covariance b = 1/(2 pi s)^2:
  Sigma' = (Sigma^-1 + P b^-1 P^T)^-1, evaluated with the Woodbury identity so that
  singular Sigma (the common case) needs no inverse.
- `diffuse_transfer`: a Lambertian lobe integrates the incoming angles: the outgoing
  spatial covariance is the Schur complement A - B (b I + C)^-1 B^T, the outgoing light
  field is constant in angle.
- occlusion adds spatial frequency at the occluder (`occlusion_term`), see integrator.py
  for how occluders are detected.
- `light_at_receiver`: the covariance of an emitter of apparent solid angle Omega seen
  from distance t, i.e. a spatial window of width sigma_x = sqrt(Omega / 12) t at the
  emitter, travelled to the receiver.
- `lens`: thin-lens refocusing (an angular shear by 1/F) followed by the aperture
  integral (a spatial band limit).

`log_eta` maps a covariance at the camera to the per-sample feature
l = 1/2 log det(I + Sigma_n / eps) = log(eta_eps / eps^2), with Sigma_n in pixel units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi

TWO_PI = 2.0 * math.pi
#: Angular band limit used for "no band limit" (delta lobes).
B_INFINITE = 1.0e10
#: Angular width (radians, one standard deviation) of a Lambertian lobe.
LAMBERT_WIDTH = 0.7
B_LAMBERT = 1.0 / (TWO_PI * LAMBERT_WIDTH) ** 2


def M2(a00, a01, a10, a11):
    return mi.Matrix2f(a00, a01, a10, a11)


def zeros2():
    return M2(0.0, 0.0, 0.0, 0.0)


def eye2(s=1.0):
    return M2(s, 0.0, 0.0, s)


def T(m):
    return M2(m[0][0], m[1][0], m[0][1], m[1][1])


def inv2(m, min_det=1e-12):
    """Inverse of a 2x2 matrix; the determinant is clamped away from 0 (sign kept)."""
    det = m[0][0] * m[1][1] - m[0][1] * m[1][0]
    det = dr.select(dr.abs(det) < min_det, dr.select(det < 0, -min_det, min_det), det)
    r = dr.rcp(det)
    return M2(m[1][1] * r, -m[0][1] * r, -m[1][0] * r, m[0][0] * r)


def det2(m):
    return m[0][0] * m[1][1] - m[0][1] * m[1][0]


def sym(m):
    return (m + T(m)) * 0.5


@dataclass
class Cov:
    """Spectrum covariance of a 4-D local light field as 2x2 blocks (see module doc)."""

    A: mi.Matrix2f = field(default_factory=mi.Matrix2f)
    B: mi.Matrix2f = field(default_factory=mi.Matrix2f)
    C: mi.Matrix2f = field(default_factory=mi.Matrix2f)

    DRJIT_STRUCT = {"A": mi.Matrix2f, "B": mi.Matrix2f, "C": mi.Matrix2f}

    @staticmethod
    def zero():
        return Cov(zeros2(), zeros2(), zeros2())

    def scaled(self, w):
        return Cov(self.A * w, self.B * w, self.C * w)

    def plus(self, other):
        return Cov(self.A + other.A, self.B + other.B, self.C + other.C)

    def select(self, mask, other):
        """`self` where mask, else `other`."""
        return Cov(dr.select(mask, self.A, other.A), dr.select(mask, self.B, other.B),
                   dr.select(mask, self.C, other.C))


def basis(d):
    """The transverse basis (a, b) used for the light field around a ray of direction +-d."""
    f = mi.Frame3f(d)
    return f.s, f.t


def travel(S: Cov, d) -> Cov:
    """Free-space transport over distance d: primal shear x' = x + d theta."""
    Bd = S.B - S.A * d
    return Cov(S.A, Bd, S.C - (S.B + T(S.B)) * d + S.A * (d * d))


def add_spatial(S: Cov, O) -> Cov:
    return Cov(S.A + O, S.B, S.C)


def transform(S: Cov, H11, H12, H22) -> Cov:
    """Sigma' = H Sigma H^T for H = [[H11, H12], [0, H22]]."""
    top = H11 @ S.A + H12 @ T(S.B)  # first block row of H Sigma (left block)
    topr = H11 @ S.B + H12 @ S.C  # (right block)
    A = top @ T(H11) + topr @ T(H12)
    B = topr @ T(H22)
    C = H22 @ S.C @ T(H22)
    return Cov(sym(A), B, sym(C))


def bandlimit_angular(S: Cov, b) -> Cov:
    """Product of the spectrum with an angular Gaussian of covariance b I (BRDF lobe)."""
    K = inv2(S.C + eye2(b))
    BK = S.B @ K
    CK = S.C @ K
    return Cov(sym(S.A - BK @ T(S.B)), S.B - BK @ S.C, sym(S.C - CK @ S.C))


def bandlimit_spatial(S: Cov, b) -> Cov:
    """Product of the spectrum with a spatial Gaussian of covariance b I (aperture)."""
    K = inv2(S.A + eye2(b))
    AK = S.A @ K
    return Cov(sym(S.A - AK @ S.A), S.B - AK @ S.B, sym(S.C - T(S.B) @ K @ S.B))


def occlusion_term(delta0, delta1, hit0, hit1):
    """Spatial covariance added by an occluder edge found within the transverse offsets
    delta_j (2-D vectors at the occluder) of the ray; hit_j says whether an edge was found
    along delta_j. An edge within |delta| of the ray has frequency ~ 1/(2 pi |delta|) across
    the edge: the term is delta delta^T / ((2 pi)^2 |delta|^4)."""
    O = zeros2()
    for dlt, hit in ((delta0, hit0), (delta1, hit1)):
        l2 = dr.maximum(dr.squared_norm(dlt), 1e-20)
        w = dr.select(hit, dr.rcp(TWO_PI * TWO_PI * l2 * l2), 0.0)
        O += M2(dlt.x * dlt.x * w, dlt.x * dlt.y * w, dlt.y * dlt.x * w, dlt.y * dlt.y * w)
    return O


def light_at_receiver(c, t_light, d_occ, O) -> Cov:
    """Covariance, at a receiver, of the light of an emitter seen under angular frequency
    variance c = 1/(2 pi sigma_theta)^2 at distance t_light (may be inf), with an occluder
    term O added at distance d_occ from the receiver (O = 0: no occluder; d_occ is then
    irrelevant). The emitter is a diffuse spatial window of width sigma_theta * t_light."""
    t_light = dr.maximum(t_light, 1e-6)
    inv_t = dr.rcp(t_light)  # 0 for lights at infinity
    r = dr.clip(1.0 - d_occ * inv_t, 0.0, 1.0)  # (distance light -> occluder) / t_light
    a = c * inv_t * inv_t
    S = Cov(eye2(a), eye2(-c * r * inv_t), eye2(c * r * r))
    S = add_spatial(S, O)
    return travel(S, d_occ)


def _dot(u, v):
    return dr.dot(u, v)


def _rotate_min(x, u, v):
    """Apply to x the minimal rotation taking unit vector u to unit vector v."""
    w = dr.cross(u, v)
    c = dr.dot(u, v)
    k = dr.rcp(dr.maximum(1.0 + c, 1e-3))
    return x * c + dr.cross(w, x) + w * (dr.dot(w, x) * k)


@dataclass
class SurfaceGeo:
    """Local geometry at a path vertex: shading normal n, tangents s, t, and the shape
    operator W (2x2 in the (s, t) basis): dn = (W u)_0 s + (W u)_1 t for a surface offset
    u = u_0 s + u_1 t. Convex surfaces have a positive W."""

    n: mi.Vector3f
    s: mi.Vector3f
    t: mi.Vector3f
    W: mi.Matrix2f


def _proj_matrix(geo: SurfaceGeo, a, b):
    """P with x = P u: surface offset (s, t coordinates) -> transverse coordinates on (a, b)."""
    return M2(_dot(geo.s, a), _dot(geo.t, a), _dot(geo.s, b), _dot(geo.t, b))


def _clamp_det(P, min_abs):
    """Scale the second row of P (the foreshortened axis) so that |det P| >= min_abs."""
    d = det2(P)
    scale = dr.select(dr.abs(d) < min_abs, min_abs / dr.maximum(dr.abs(d), 1e-8), 1.0)
    return M2(P[0][0], P[0][1], P[1][0] * scale, P[1][1] * scale)


MIN_COS = 0.05


def diffuse_transfer(S: Cov, geo: SurfaceGeo, bi, bo) -> Cov:
    """Lambertian reflection of an incoming light field (basis bi) into the outgoing
    transverse basis bo: Schur complement over the angles, re-projection of the spatial part."""
    Ps = S.A - S.B @ inv2(S.C + eye2(B_LAMBERT)) @ T(S.B)
    Pi = _proj_matrix(geo, bi[0], bi[1])
    Po = _clamp_det(_proj_matrix(geo, bo[0], bo[1]), MIN_COS)
    H11 = T(inv2(Po)) @ T(Pi)
    return Cov(sym(H11 @ Ps @ T(H11)), zeros2(), zeros2())


def specular_transfer(S: Cov, geo: SurfaceGeo, wi, bi, wo, bo, refract, eta, b) -> Cov:
    """Reflection (or refraction with relative index eta = n_out / n_in along the light's
    way) of the light field propagating along wi (basis bi) about the curved surface,
    re-expressed around the actual outgoing propagation direction wo (basis bo), then
    band-limited in angle by the lobe (b = B_INFINITE for delta lobes)."""
    sgn = dr.select(_dot(wi, geo.n) > 0, -1.0, 1.0)
    n = geo.n * sgn  # oriented towards the incoming side
    W = geo.W * sgn
    ci = dr.maximum(-_dot(wi, n), 1e-4)
    # Reflection: wc = wi + 2 ci n. Refraction: wc = wi/eta + (ci/eta - ct) n.
    inv_eta = dr.rcp(eta)
    k = 1.0 - (1.0 - ci * ci) * inv_eta * inv_eta
    ct = dr.sqrt(dr.maximum(k, 1e-6))
    alpha = dr.select(refract, inv_eta, 1.0)
    gamma = dr.select(refract, inv_eta - ci * inv_eta * inv_eta / ct, 2.0)
    mu = dr.select(refract, ci * inv_eta - ct, 2.0 * ci)
    wc = dr.normalize(wi * alpha + n * mu)
    # Angular output basis: the actual outgoing basis rotated onto the central direction.
    ac = _rotate_min(bo[0], wo, wc)
    bc = _rotate_min(bo[1], wo, wc)
    Ns = geo.s * W[0][0] + geo.t * W[1][0]  # dn per unit offset along s
    Nt = geo.s * W[0][1] + geo.t * W[1][1]
    an, bn = _dot(ac, n), _dot(bc, n)
    na, nb = _dot(n, bi[0]), _dot(n, bi[1])
    Q = M2(alpha * _dot(ac, bi[0]) - gamma * an * na, alpha * _dot(ac, bi[1]) - gamma * an * nb,
           alpha * _dot(bc, bi[0]) - gamma * bn * na, alpha * _dot(bc, bi[1]) - gamma * bn * nb)
    wNs, wNt = _dot(wi, Ns), _dot(wi, Nt)
    Cm = M2(mu * _dot(ac, Ns) - gamma * an * wNs, mu * _dot(ac, Nt) - gamma * an * wNt,
            mu * _dot(bc, Ns) - gamma * bn * wNs, mu * _dot(bc, Nt) - gamma * bn * wNt)
    Pi = _proj_matrix(geo, bi[0], bi[1])
    Po = _clamp_det(_proj_matrix(geo, bo[0], bo[1]), MIN_COS)
    PoiT = T(inv2(Po))
    QiT = T(inv2(Q, 1e-6))
    H11 = PoiT @ T(Pi)
    H12 = -(PoiT @ T(Cm) @ QiT)
    out = transform(S, H11, H12, QiT)
    return bandlimit_angular(out, b)


def lobe_bandlimit(alpha):
    """Angular band limit of a microfacet lobe of roughness alpha (0: delta lobe): the
    outgoing lobe's angular std is ~ sqrt(2) alpha."""
    s = 1.4142135 * alpha
    return dr.select(alpha <= 1e-4, B_INFINITE, dr.rcp(TWO_PI * TWO_PI * s * s))


def lens(S: Cov, focus_dist, aperture_radius) -> Cov:
    """Thin lens focused at focus_dist with the given aperture radius (0: pinhole)."""
    f = dr.rcp(focus_dist)
    S = Cov(sym(S.A + (S.B + T(S.B)) * f + S.C * (f * f)), S.B + S.C * f, S.C)
    b_ap = dr.rcp(dr.maximum((math.pi * aperture_radius) ** 2, 1e-20))
    return bandlimit_spatial(S, b_ap)


def log_eta(S: Cov, footprint, pixel_angle, eps):
    """l = 1/2 log det(I + D Sigma D / eps), D = diag(footprint, footprint, pixel_angle,
    pixel_angle): the covariance in cycles per pixel (angular axes) and cycles per pixel
    footprint (spatial axes), floored at eps (cycles^2 per pixel^2)."""
    fa = footprint * footprint / eps
    fc = pixel_angle * pixel_angle / eps
    fb = footprint * pixel_angle / eps
    M11 = S.A * fa + eye2(1.0)
    M12 = S.B * fb
    M22 = S.C * fc + eye2(1.0)
    schur = M22 - T(M12) @ inv2(M11) @ M12
    det = det2(M11) * det2(schur)
    return 0.5 * dr.log(dr.maximum(det, 1.0))

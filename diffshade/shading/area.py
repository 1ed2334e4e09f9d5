"""Lighting by area and extended lights: rectangles and disks (one-sided planar emitters),
spheres. The lights themselves are built by diffshade.scene.area_lights.

Radiometric convention (docs/area-lights.md). A light's colour C is a radiant intensity,
so that a small light matches a point light whose attenuation is 1/d^2:
- rectangle and disk (area A, emitting towards n_L): radiance C / A. At a point p with
  normal n, per unit colour,
      E = (1 / A) integral over the light of max(n.w, 0) max(-n_L.w, 0) / r^2 dA
  (w the unit direction from p to the light point, r its distance); as A -> 0,
  E -> cos(theta) cos(theta') / d^2: a point light of intensity C cos(theta'), i.e. a spot
  light of exponent 1 and cutoff 90 pointing along n_L, with attenuation (0, 0, 1).
- sphere (radius R): radiance C / (pi R^2), intensity C in every direction; while the
  sphere is above p's horizon E = cos(theta) / d^2 exactly, for every R.
diffuse = kd Id E; specular = ks Is times the same integral with the Blinn-Phong (or
Phong) lobe in it; ambient = ka Ia, unattenuated. The colour's total power is pi C for a
rectangle or a disk, 4 pi C for a sphere.

Where a closed form exists it is used: the rectangle's diffuse term is Lambert's formula
for the projected solid angle of a polygon (Arvo 1995, "Applications of irradiance
tensors"), Omega_p = -1/2 sum_i Theta_i n.Gamma_i, after clipping the polygon to p's
horizon; E = Omega_p / A. Everything else sums a fixed stratified sample pattern (seed
SEED, the light's static `samples` count): sample j acts as a point light with direction
L_j and weight w_j, its share of the integral.

Shadows (shadows=True, docs/shadows.md): the light's `samples` fixed points
(`sample_points`: the rectangle's and the disk's own sample pattern, stratified points
over a sphere's whole surface) each get a shadow map (diffshade.shading.shadows.sampled_visibility);
at a point p the light's diffuse and specular terms are multiplied by
V(p) = sum_j c_j vis_j / sum_j c_j, c_j = max(N.L_j, 0) max(-n_j.L_j, 0) / r_j^2 the
unshadowed diffuse contribution of sample point j (n_j its emitting normal). For a disk
this makes the diffuse term exactly the average over samples of visibility times
contribution; for a rectangle it is the closed form times the contribution-weighted
visibility, for a sphere its (cone-sampled) irradiance times the same, and for
specular terms the same factor applied to the unshadowed sum.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.numerics import (
    dot,
    safe_div,
    safe_norm,
    safe_normalize,
    safe_sqrt,
    tiny,
)

KINDS = ("rect", "disk", "sphere")
SEED = 1995


# ----------------------------------------------------------------- sample patterns


def stratified_square(count):
    """[count, 2] points in the unit square, one per cell of an m x n grid (m n = count, m
    the largest divisor <= sqrt(count)), jittered with the fixed seed SEED."""
    m = max(d for d in range(1, math.isqrt(count) + 1) if count % d == 0)
    n = count // m
    rows, cols = np.divmod(np.arange(count), n)
    jitter = np.random.default_rng(SEED).uniform(size=(count, 2))
    return np.stack([(cols + jitter[:, 0]) / n, (rows + jitter[:, 1]) / m], -1)


def concentric_disk(square):
    """Shirley & Chiu's area-preserving map of [N, 2] unit-square points to the unit disk."""
    a, b = 2.0 * square[:, 0] - 1.0, 2.0 * square[:, 1] - 1.0
    wide = np.abs(a) > np.abs(b)
    r = np.where(wide, a, b)
    phi = np.where(wide, np.pi / 4 * b / np.where(a == 0, 1, a),
                   np.pi / 2 - np.pi / 4 * a / np.where(b == 0, 1, b))
    return np.stack([r * np.cos(phi), r * np.sin(phi)], -1)


def uniform_sphere(square):
    """The area-preserving map of [N, 2] unit-square points to the unit sphere (z = 1 - 2u,
    azimuth 2 pi v): [N, 3]."""
    z = 1.0 - 2.0 * square[:, 0]
    r, phi = np.sqrt(np.maximum(1.0 - z * z, 0.0)), 2.0 * np.pi * square[:, 1]
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


def orthonormal_frame(n):
    """Two unit tangents [..., 3] completing unit n [..., 3] to an orthonormal frame
    (Duff et al. 2017, branchless)."""
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    sign = jnp.where(z >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    t1 = jnp.stack([1.0 + sign * x * x * a, sign * b, -sign * x], -1)
    t2 = jnp.stack([b, sign + y * y * a, -y], -1)
    return t1, t2


# ------------------------------------------------------ per-sample incidence (samples)


def from_point(points, q, emit_normal):
    """Incidence at points [..., 3] of light point q [3] emitting towards emit_normal [3]:
    (unit direction to q [..., 3], max(-n_L.L, 0) / r^2 [..., 1])."""
    to_light = q - points
    light_dir = safe_normalize(to_light)
    facing = jnp.maximum(-dot(emit_normal, light_dir, keepdims=True), 0.0)
    return light_dir, safe_div(facing, dot(to_light, to_light, keepdims=True))


def _planar(points, emit_normal, count):
    """Incidence of a sample at light point q: (unit direction to q, weight [..., 1]) =
    max(-n_L.L, 0) / r^2 / count."""
    def at(q):
        light_dir, weight = from_point(points, q, emit_normal)
        return light_dir, weight / count
    return at


def _rect_incidence(light, points):
    at = _planar(points, safe_normalize(jnp.cross(light.edge_u, light.edge_v)), light.samples)
    return stratified_square(light.samples), lambda st: at(
        light.center + (st[0] - 0.5) * light.edge_u + (st[1] - 0.5) * light.edge_v)


def _disk_incidence(light, points):
    normal = safe_normalize(light.normal)
    t1, t2 = orthonormal_frame(normal)
    at = _planar(points, normal, light.samples)
    disk = concentric_disk(stratified_square(light.samples))
    return disk, lambda xy: at(light.center + light.radius * (xy[0] * t1 + xy[1] * t2))


def _sphere_incidence(light, points):
    """Directions uniform in solid angle over the cone the sphere subtends (half-angle a,
    sin a = R / d): weight = radiance * cone solid angle / count * ... = 2 / (d^2 (1 +
    cos a)) / count, written without dividing by R (R = 0 is a point light)."""
    to_centre = light.position - points
    dist2 = dot(to_centre, to_centre, keepdims=True)
    sin2 = jnp.minimum(safe_div(light.radius * light.radius, dist2), 1.0)
    cos_a = safe_sqrt(1.0 - sin2)
    one_minus = sin2 / (1.0 + cos_a)  # 1 - cos(a), without cancellation
    weight = safe_div(jnp.full_like(dist2, 2.0), dist2 * (1.0 + cos_a)) / light.samples
    axis = safe_normalize(to_centre)
    t1, t2 = orthonormal_frame(axis)

    def at(uv):
        drop = uv[0] * one_minus  # 1 - cos(theta), theta from the axis
        sin_t = safe_sqrt(drop * (2.0 - drop))
        phi = 2.0 * jnp.pi * uv[1]
        return (sin_t * jnp.cos(phi) * t1 + sin_t * jnp.sin(phi) * t2 + (1.0 - drop) * axis,
                weight)
    return stratified_square(light.samples), at


_INCIDENCE = {"rect": _rect_incidence, "disk": _disk_incidence, "sphere": _sphere_incidence}


def sample_incidence(kind, light, points):
    """(pattern [S, 2] NumPy, at): at(pattern[j]) -> (unit direction to sample j [..., 3],
    its weight [..., 1]) at points [..., 3]; sum_j weight_j max(N.L_j, 0) estimates E."""
    return _INCIDENCE[kind](light, points)


def sample_points(kind, light):
    """The light's fixed sample points [S, 3] and their emitting normals [S, 3], the points
    its shadow maps are rendered from: a rectangle's and a disk's are the points of its
    sampled terms; a sphere's (whose sampled terms use directions that follow the shading
    point) are stratified over its whole surface, emitting outwards (so about half of
    them face any given point)."""
    pattern = stratified_square(light.samples)
    if kind == "sphere":
        outward = jnp.asarray(uniform_sphere(pattern), light.position.dtype)
        return light.position + light.radius * outward, outward
    if kind == "rect":
        st = jnp.asarray(pattern - 0.5, light.center.dtype)
        normal = safe_normalize(jnp.cross(light.edge_u, light.edge_v))
        points = light.center + st[:, :1] * light.edge_u + st[:, 1:] * light.edge_v
    else:
        normal = safe_normalize(light.normal)
        t1, t2 = orthonormal_frame(normal)
        xy = jnp.asarray(concentric_disk(pattern), light.center.dtype)
        points = light.center + light.radius * (xy[:, :1] * t1 + xy[:, 1:] * t2)
    return points, jnp.broadcast_to(normal, points.shape)


# ------------------------------------------------------- the rectangle's closed form


# Written on (x, y, z) component arrays: per-fragment [..., 3] vectors with jnp.cross
# compile to chains of slices and concatenations (pads in the backward pass), several
# times slower to compile and to run than this.


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _where(cond, a, b):
    return tuple(jnp.where(cond, x, y) for x, y in zip(a, b, strict=True))


def _edge_term(a, b, n):
    """Theta n.Gamma of Lambert's formula for the edge a -> b (relative to the shading
    point): (n . (a x b)) atan2(|a x b|, a.b) / |a x b|, finite and smooth at a = b."""
    c = _cross(a, b)
    s2, d = _dot(c, c), _dot(a, b)
    ok = s2 > tiny(d.dtype) ** 2
    s = jnp.sqrt(jnp.where(ok, s2, 1.0))
    d_ok = jnp.where(ok, d, 1.0)  # atan2(0, 0) has no gradient
    ratio = jnp.where(ok, jnp.arctan2(s, d_ok) / s, safe_div(jnp.ones_like(d), d))
    return _dot(n, c) * ratio


def _clipped_polygon_sum(corners, n):
    """sum_i Theta_i n.Gamma_i over the polygon `corners` (relative to the point; each
    component [..., C], the corners along the last axis) clipped to the half-space
    n.x > 0: each edge is clipped, and the closing edge runs along the horizon from where
    the polygon leaves it to where it comes back. n: components [..., 1]."""
    nexts = tuple(jnp.roll(x, -1, axis=-1) for x in corners)
    heights = _dot(n, corners)
    next_heights = jnp.roll(heights, -1, axis=-1)
    t = safe_div(heights, heights - next_heights)
    crossing = tuple(a + t * (b - a) for a, b in zip(corners, nexts, strict=True))
    a_in, b_in = heights > 0.0, next_heights > 0.0
    exit_point = tuple(jnp.sum(jnp.where(a_in & ~b_in, x, 0.0), -1, keepdims=True)
                       for x in crossing)
    entry_point = tuple(jnp.sum(jnp.where(~a_in & b_in, x, 0.0), -1, keepdims=True)
                        for x in crossing)
    # the clipped edges and the closing edge, as one batch of C + 1 edges
    starts = tuple(jnp.concatenate(pair, -1) for pair in
                   zip(_where(a_in, corners, crossing), exit_point, strict=True))
    ends = tuple(jnp.concatenate(pair, -1) for pair in
                 zip(_where(b_in, nexts, crossing), entry_point, strict=True))
    return jnp.sum(_edge_term(starts, ends, n), -1)


def rect_irradiance(light, points, normals):
    """E per unit colour [..., 1] of a rectangle light at points with unit normals [..., 3]
    (module docstring): Lambert's formula over the area; for a light too small for the
    formula's rounding (A / d^2 below eps^(2/3)) its point limit cos cos' / d^2."""
    p = tuple(points[..., i] for i in range(3))
    n = tuple(normals[..., i] for i in range(3))
    centre = tuple(light.center[i] - p[i] for i in range(3))
    u, v = light.edge_u, light.edge_v
    su, sv = jnp.array([-0.5, 0.5, 0.5, -0.5]), jnp.array([-0.5, -0.5, 0.5, 0.5])
    rel = tuple(centre[i][..., None] + su * u[i] + sv * v[i] for i in range(3))
    omega = -0.5 * _clipped_polygon_sum(rel, tuple(x[..., None] for x in n))
    emit = jnp.cross(u, v)
    area = safe_norm(emit)
    emit_normal = tuple(safe_normalize(emit))
    dist2 = _dot(centre, centre)
    facing = -_dot(emit_normal, centre)  # |to centre| cos(theta') from the light's side
    point = safe_div(jnp.maximum(_dot(n, centre), 0.0) * jnp.maximum(facing, 0.0),
                     dist2 * dist2)
    small = area < jnp.finfo(points.dtype).eps ** (2.0 / 3.0) * dist2
    out = jnp.where(facing > 0.0,
                    jnp.where(small, point, safe_div(jnp.maximum(omega, 0.0), area)), 0.0)
    return out[..., None]


# --------------------------------------------------------------------- the terms


def _sampled(kind, light, material, points, normals, view_dirs, settings, light_terms,
             diffuse):
    """(diffuse or None, specular or None) summed over the light's samples by a scan (the
    sample count is static; each step is rematerialized in the backward pass)."""
    pattern, at = sample_incidence(kind, light, points)
    shape = jnp.broadcast_shapes(points.shape, normals.shape, jnp.shape(material.kd))
    zeros = jnp.zeros(shape, points.dtype)

    def step(sums, sample):
        light_dir, weight = at(sample)
        _, d, s = light_terms(material, light, light_dir, weight, normals, view_dirs, settings)
        return (sums[0] + d if diffuse else sums[0], sums[1] if s is None else sums[1] + s), None

    (d, s), _ = jax.lax.scan(jax.checkpoint(step), (zeros, zeros),
                             jnp.asarray(pattern, points.dtype))
    return (d if diffuse else None), (None if material.ks is None else s)


def _unshadowed(kind, light, material, points, normals, view_dirs, settings, light_terms):
    """(diffuse, specular or None) of one area or sphere light without shadows."""
    if kind != "rect":
        return _sampled(kind, light, material, points, normals, view_dirs, settings,
                        light_terms, diffuse=True)
    diffuse = material.kd * light.diffuse * rect_irradiance(light, points, normals)
    if material.ks is None:
        return diffuse, None
    _, s = _sampled(kind, light, material, points, normals, view_dirs, settings, light_terms,
                    diffuse=False)
    return diffuse, s


def terms(kind, light, material, points, normals, view_dirs, settings, light_terms,
          seen=None):
    """(ambient, diffuse, specular or None) of one area or sphere light, [..., 3] each.
    light_terms: shading._light_terms (one point-like light at one direction and scale);
    seen: None, or the light's visibility V [..., 1] (diffshade.shading.shadows.sampled_visibility),
    which scales its diffuse and specular terms (module docstring)."""
    d, s = _unshadowed(kind, light, material, points, normals, view_dirs, settings,
                       light_terms)
    if seen is not None:
        d, s = seen * d, None if s is None else seen * s
    return material.ka * light.ambient, d, s

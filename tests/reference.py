"""Independent reference implementations for the renderer tests, plain numpy float64.

- OpenGL matrices written out from the man pages (gluLookAt, gluPerspective).
- OpenGL 1.x fixed-function lighting (spec section 2.14.1, equation 2.1) at one point:
      c = e + ka*a_global + sum_i att_i spot_i (ka*a_i + kd*d_i (n.L)+ + f_i ks*s_i (n.h)+^n)
  with (u.v)+ = max(u.v, 0) and f_i = 1 where n.L > 0, else 0.
- A naive rasterizer: for each pixel centre (half-integers, row 0 at the top), for each face:
  vertices projected with the matrices above, inside test by 2D edge functions on the
  projected triangle, perspective-correct barycentrics b_i/w_i / sum_j b_j/w_j (lecture
  notes, "depth distortion"), clipped per pixel by the interpolated eye depth (near <= depth
  <= far), z-buffered on NDC z. A face with a vertex at or behind the eye (w <= 0) cannot
  be projected; for it the pixel's eye ray is intersected with the triangle
  (Moller-Trumbore), which gives the same quantities.
- Reference renders for the four shading modes of diffshade ('phong', 'gouraud', 'flat',
  'flat_last'), OpenGL's two-sided rule and clamping.

Nothing here imports diffshade: scenes, cameras, materials and lights are read as plain
arrays through their attributes (duck typing), and every computation is redone here.
"""

import dataclasses
import math

import numpy as np

#: the depth test's tie width in NDC depth, as documented (docs/rendering.md)
DEPTH_TIE = 2.0 ** -18

#: light type -> fields it has (the stacked arrays of one light group)
LIGHT_FIELDS = {
    "ambient": ("ambient",),
    "directional": ("direction", "ambient", "diffuse", "specular"),
    "point": ("position", "ambient", "diffuse", "specular", "attenuation"),
    "spot": ("position", "direction", "ambient", "diffuse", "specular", "attenuation",
             "cutoff", "exponent"),
}


def unit(v):
    """v / |v| for v: [..., 3]."""
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def look_at_matrix(eye, target, up):
    """gluLookAt: world -> eye [4, 4]."""
    eye = np.asarray(eye, np.float64)
    f = unit(np.asarray(target, np.float64) - eye)
    s = unit(np.cross(f, np.asarray(up, np.float64)))
    u = np.cross(s, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = s, u, -f
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def perspective_matrix(fov_y_deg, aspect, near, far):
    """gluPerspective: eye -> clip [4, 4]."""
    f = 1.0 / math.tan(math.radians(fov_y_deg) / 2.0)
    return np.array([[f / aspect, 0.0, 0.0, 0.0],
                     [0.0, f, 0.0, 0.0],
                     [0.0, 0.0, (far + near) / (near - far), 2.0 * far * near / (near - far)],
                     [0.0, 0.0, -1.0, 0.0]])


@dataclasses.dataclass
class RefCamera:
    """A perspective camera as plain numbers; `of` reads any object with these fields."""

    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov_y: float
    near: float
    far: float
    width: int
    height: int

    @classmethod
    def of(cls, cam):
        if getattr(cam, "projection", "perspective") != "perspective":
            raise ValueError(f"cam.projection: got {cam.projection!r}; expected 'perspective'")
        vec = [np.asarray(getattr(cam, n), np.float64) for n in ("eye", "target", "up")]
        num = [float(getattr(cam, n)) for n in ("fov_y", "near", "far")]
        return cls(*vec, *num, int(cam.width), int(cam.height))

    @property
    def view(self):
        return look_at_matrix(self.eye, self.target, self.up)

    @property
    def proj(self):
        return perspective_matrix(self.fov_y, self.width / self.height, self.near, self.far)

    def pixel_ndc(self, row, col):
        """NDC (x, y) of the centre of pixel (row, col); row 0 is the top (y = +1)."""
        return 2.0 * (col + 0.5) / self.width - 1.0, 1.0 - 2.0 * (row + 0.5) / self.height

    def eye_ray(self, row, col):
        """Eye-space direction through the pixel centre, with z = -1: [3]."""
        x, y = self.pixel_ndc(row, col)
        tan = math.tan(math.radians(self.fov_y) / 2.0)
        return np.array([x * tan * self.width / self.height, y * tan, -1.0])

    def world_ray(self, row, col):
        """(origin [3], direction [3]) of the pixel's ray in world space (not unit)."""
        return self.eye.copy(), self.view[:3, :3].T @ self.eye_ray(row, col)

    def view_dir_infinite(self):
        """OpenGL's infinite viewer: eye-space +z in world space."""
        return self.view[2, :3].copy()


# ----------------------------------------------------------------------------- lighting


def light_list(groups):
    """Stacked light groups (attributes ambient/directional/point/spot, each None or an
    object with stacked [n, ...] fields) -> list of dicts with a 'kind' key."""
    lights = []
    for kind, fields in LIGHT_FIELDS.items():
        group = getattr(groups, kind)
        if group is None:
            continue
        arrays = {f: np.asarray(getattr(group, f), np.float64) for f in fields}
        for i in range(arrays[fields[0]].shape[0]):
            lights.append({"kind": kind, **{f: a[i] for f, a in arrays.items()}})
    return lights


def material_dict(mat):
    """A material object (ka, kd, ks or None, shininess, emission or None) -> plain dict."""
    def rgb(v):
        return None if v is None else np.broadcast_to(np.asarray(v, np.float64), (3,))
    return {"ka": rgb(mat.ka), "kd": rgb(mat.kd), "ks": rgb(mat.ks),
            "shininess": float(mat.shininess),
            "emission": rgb(np.zeros(3) if mat.emission is None else mat.emission)}


def _incidence(light, point):
    """(unit direction to the light [3], attenuation * spot factor) for one light."""
    if light["kind"] == "directional":
        return unit(-light["direction"]), 1.0
    to_light = light["position"] - point
    dist = float(np.linalg.norm(to_light))
    a, b, c = light["attenuation"]
    att = 1.0 / (a + b * dist + c * dist * dist)
    light_dir = to_light / dist
    if light["kind"] == "spot" and light["cutoff"] != 180.0:
        cos_angle = float(-light_dir @ unit(light["direction"]))
        inside = cos_angle >= math.cos(math.radians(light["cutoff"]))
        att *= max(cos_angle, 0.0) ** light["exponent"] if inside else 0.0
    return light_dir, att


def _specular_base(normal, light_dir, view_dir, model):
    if model == "blinn":
        return float(normal @ unit(light_dir + view_dir))
    reflected = 2.0 * float(normal @ light_dir) * normal - light_dir
    return float(reflected @ view_dir)


def lighting(mat, lights, global_ambient, point, normal, view_dir, specular="blinn"):
    """OpenGL 1.x lighting of one point. mat: material_dict; lights: light_list; point,
    normal (unit), view_dir (unit, towards the viewer): [3]. Returns a dict of the
    unclamped parts 'ambient', 'diffuse', 'specular', 'emission' ([3] each)."""
    point, normal, view_dir = (np.asarray(v, np.float64) for v in (point, normal, view_dir))
    ambient = mat["ka"] * np.asarray(global_ambient, np.float64)
    diffuse, spec = np.zeros(3), np.zeros(3)
    for light in lights:
        if light["kind"] == "ambient":
            ambient = ambient + mat["ka"] * light["ambient"]
            continue
        light_dir, scale = _incidence(light, point)
        n_dot_l = float(normal @ light_dir)
        ambient = ambient + scale * mat["ka"] * light["ambient"]
        diffuse = diffuse + scale * mat["kd"] * light["diffuse"] * max(n_dot_l, 0.0)
        if mat["ks"] is not None and n_dot_l > 0.0:
            base = _specular_base(normal, light_dir, view_dir, specular)
            power = base ** mat["shininess"] if base > 0.0 else 0.0
            spec = spec + scale * mat["ks"] * light["specular"] * power
    return {"ambient": ambient, "diffuse": diffuse, "specular": spec,
            "emission": mat["emission"].copy()}


def total(parts):
    return parts["ambient"] + parts["diffuse"] + parts["specular"] + parts["emission"]


# ---------------------------------------------------------------------------- rasterizer


@dataclasses.dataclass
class RefFragments:
    """face_ids: [H, W] int (-1 empty); bary: [H, W, 3] perspective-correct; depth: [H, W]
    eye depth; front: [H, W] bool; edge_dist: [H, W] pixel distance from the centre to the
    nearest edge line (or near/far clip line) of any face that (nearly) covers it."""

    face_ids: np.ndarray
    bary: np.ndarray
    depth: np.ndarray
    front: np.ndarray
    edge_dist: np.ndarray


@dataclasses.dataclass
class _Face:
    eye: np.ndarray      # [3, 3] eye-space corners
    clip: np.ndarray     # [3, 4]
    screen: np.ndarray   # [3, 2] pixel coordinates (x right, y down), only if all w > 0
    front: bool


def _faces(cam, world, faces):
    view, proj = cam.view, cam.proj
    out = []
    for tri in np.asarray(faces):
        corners = np.concatenate([world[tri], np.ones((3, 1))], 1)
        eye = corners @ view.T
        clip = eye @ proj.T
        screen = None
        if np.all(clip[:, 3] > 0.0):
            ndc = clip[:, :2] / clip[:, 3:]
            screen = np.stack([(ndc[:, 0] + 1.0) * cam.width / 2.0,
                               (1.0 - ndc[:, 1]) * cam.height / 2.0], 1)
        # front: the eye lies on the side the counter-clockwise normal points to, which for
        # a perspective view is exactly "counter-clockwise on screen" (OpenGL)
        normal = np.cross(eye[1, :3] - eye[0, :3], eye[2, :3] - eye[0, :3])
        out.append(_Face(eye[:, :3], clip, screen, bool(normal @ -eye[0, :3] > 0.0)))
    return out


def _clip_distance(depth, grad_px, cam):
    """Pixel distance to the near/far clip line, given d(depth)/d(pixel) magnitude."""
    gap = min(abs(depth - cam.near), abs(depth - cam.far))
    return gap / grad_px if grad_px > 0 else math.inf


def _hit_projected(face, px, py, cam):
    """2D edge functions on the projected triangle: (covered, bary, depth, ndc_z, dist)."""
    p = face.screen
    area2 = (p[1, 0] - p[0, 0]) * (p[2, 1] - p[0, 1]) - (p[1, 1] - p[0, 1]) * (p[2, 0] - p[0, 0])
    if area2 == 0.0:
        return None
    edge, dist = np.empty(3), np.empty(3)
    for i, (j, k) in enumerate(((1, 2), (2, 0), (0, 1))):
        ex, ey = p[k, 0] - p[j, 0], p[k, 1] - p[j, 1]
        edge[i] = ex * (py - p[j, 1]) - ey * (px - p[j, 0])
        dist[i] = abs(edge[i]) / math.hypot(ex, ey)
    screen_bary = edge / area2
    w = face.clip[:, 3]
    q = screen_bary / w
    bary = q / q.sum()
    depth = float(bary @ w)
    ndc_z = float(screen_bary @ (face.clip[:, 2] / w))
    # 1/depth is affine in screen space; its pixel gradient gives the clip-line distance
    grad_b = np.array([[p[j, 1] - p[k, 1], p[k, 0] - p[j, 0]]
                       for j, k in ((1, 2), (2, 0), (0, 1))]) / area2
    grad_px = float(np.linalg.norm((1.0 / w) @ grad_b)) * depth * depth
    near_inside = bool(np.all(screen_bary >= -1e-3))
    dist = min(dist.min(), _clip_distance(depth, grad_px, cam)) if near_inside else math.inf
    covered = bool(np.all(screen_bary >= 0.0)) and cam.near <= depth <= cam.far
    return covered, bary, depth, ndc_z, dist


def _hit_ray(face, ray, cam):
    """Moller-Trumbore intersection of the eye ray (origin 0, direction `ray` with z = -1)
    with the eye-space triangle: (covered, bary, depth, ndc_z, dist)."""
    v0, v1, v2 = face.eye
    e1, e2 = v1 - v0, v2 - v0
    pvec = np.cross(ray, e2)
    det = float(e1 @ pvec)
    if det == 0.0:
        return None
    tvec = -v0
    u = float(tvec @ pvec) / det
    qvec = np.cross(tvec, e1)
    v = float(ray @ qvec) / det
    depth = float(e2 @ qvec) / det  # the ray parameter equals the eye depth (ray z = -1)
    bary = np.array([1.0 - u - v, u, v])
    proj = cam.proj
    ndc_z = (proj[2, 2] * -depth + proj[2, 3]) / depth
    # an edge projects to the line where the plane through the eye and the edge meets the
    # image plane z = -1, whose pixels are 2 tan(fov/2) / H units wide
    px_size = 2.0 * math.tan(math.radians(cam.fov_y) / 2.0) / cam.height
    dist = math.inf
    if np.all(bary >= -1e-3):
        planes = [np.cross(face.eye[j], face.eye[k]) for j, k in ((1, 2), (2, 0), (0, 1))]
        dist = min(abs(m @ ray) / math.hypot(m[0], m[1]) / px_size for m in planes)
        normal = np.cross(e1, e2)
        grad_px = depth * depth * px_size * math.hypot(normal[0], normal[1]) / abs(normal @ v0)
        dist = min(dist, _clip_distance(depth, grad_px, cam))
    covered = bool(np.all(bary >= 0.0)) and cam.near <= depth <= cam.far
    return covered, bary, depth, ndc_z, dist


def _in_box(face, px, py):
    lo, hi = face.screen.min(0) - 1e-3, face.screen.max(0) + 1e-3
    return lo[0] <= px <= hi[0] and lo[1] <= py <= hi[1]


def rasterize(cam, world, faces, cull_backfaces=False):
    """Naive z-buffer: cam: RefCamera; world: [V, 3] world positions; faces: [F, 3] int.
    The nearest (smallest NDC z) covering face wins; NDC depths within DEPTH_TIE of each
    other are a tie, which the first face wins (docs/rendering.md#coplanar-faces)."""
    h, w = cam.height, cam.width
    frags = RefFragments(np.full((h, w), -1), np.zeros((h, w, 3)), np.zeros((h, w)),
                         np.zeros((h, w), bool), np.full((h, w), math.inf))
    setups = _faces(cam, np.asarray(world, np.float64), faces)
    for row in range(h):
        for col in range(w):
            px, py = col + 0.5, row + 0.5
            best = math.inf
            for f, face in enumerate(setups):
                if cull_backfaces and not face.front:
                    continue
                if face.screen is not None:
                    if not _in_box(face, px, py):
                        continue
                    hit = _hit_projected(face, px, py, cam)
                else:
                    hit = _hit_ray(face, cam.eye_ray(row, col), cam)
                if hit is None:
                    continue
                covered, bary, depth, ndc_z, dist = hit
                frags.edge_dist[row, col] = min(frags.edge_dist[row, col], dist)
                if covered and ndc_z < best - DEPTH_TIE:  # faces come in index order
                    best = ndc_z
                    frags.face_ids[row, col] = f
                    frags.bary[row, col] = bary
                    frags.depth[row, col] = depth
                    frags.front[row, col] = face.front
    return frags


# -------------------------------------------------------------------------------- render


def world_geometry(scene):
    """(world positions [V, 3], unit world normals [V, 3]) under scene.model: points by M,
    normals by the inverse transpose of its 3x3 block."""
    model = np.asarray(scene.model, np.float64)
    verts = np.asarray(scene.mesh.vertices, np.float64)
    normals = np.asarray(scene.mesh.normals, np.float64)
    world = verts @ model[:3, :3].T + model[:3, 3]
    # n' = inv(A)^T n  <=>  n'^T = n^T inv(A)
    return world, unit(normals @ np.linalg.inv(model[:3, :3]))


class RefScene:
    """A diffshade-like scene read into plain arrays, with OpenGL's lighting-model rules."""

    def __init__(self, scene, specular="blinn"):
        self.cam = RefCamera.of(scene.camera)
        self.faces = np.asarray(scene.mesh.faces)
        self.world, self.normals = world_geometry(scene)
        self.lights = light_list(scene.lights)
        self.front_mat = material_dict(scene.material)
        back = scene.back_material if scene.back_material is not None else scene.material
        self.back_mat = material_dict(back)
        self.global_ambient = np.asarray(scene.global_ambient, np.float64)
        self.background = np.asarray(scene.background, np.float64)
        self.local_viewer, self.two_sided = bool(scene.local_viewer), bool(scene.two_sided)
        self.specular = specular

    def light(self, point, normal, front=True):
        """Lit parts at a point with OpenGL's two-sided rule (flip n, back material)."""
        mat = self.front_mat
        if self.two_sided and not front:
            normal, mat = -normal, self.back_mat
        view = (unit(self.cam.eye - point) if self.local_viewer
                else self.cam.view_dir_infinite())
        return lighting(mat, self.lights, self.global_ambient, point, normal, view,
                        self.specular)


def _finish(colour, clamp):
    return np.clip(colour, 0.0, 1.0) if clamp else colour


def _pixel_colour(ref, face, bary, front, shading, clamp):
    corners = ref.faces[face]
    if shading == "phong":
        point = bary @ ref.world[corners]
        parts = ref.light(point, unit(bary @ ref.normals[corners]), front)
        return _finish(total(parts), clamp)
    if shading == "gouraud":
        colours = [_finish(total(ref.light(ref.world[v], ref.normals[v], front)), clamp)
                   for v in corners]
        return bary @ np.array(colours)
    if shading == "flat":
        tri = ref.world[corners]
        normal = unit(np.cross(tri[1] - tri[0], tri[2] - tri[0]))
        return _finish(total(ref.light(tri.mean(0), normal, front)), clamp)
    if shading == "flat_last":
        last = corners[2]
        return _finish(total(ref.light(ref.world[last], ref.normals[last], front)), clamp)
    raise ValueError(f"shading: got {shading!r}; expected phong, gouraud, flat or flat_last")


def render(scene, shading="phong", specular="blinn", clamp=True, cull_backfaces=False):
    """Reference image of a diffshade-like scene: (rgba [H, W, 4], RefFragments)."""
    ref = RefScene(scene, specular)
    frags = rasterize(ref.cam, ref.world, ref.faces, cull_backfaces)
    rgba = np.zeros((ref.cam.height, ref.cam.width, 4))
    rgba[..., :3] = ref.background
    for row, col in zip(*np.nonzero(frags.face_ids >= 0), strict=True):
        rgba[row, col, :3] = _pixel_colour(ref, frags.face_ids[row, col], frags.bary[row, col],
                                           frags.front[row, col], shading, clamp)
        rgba[row, col, 3] = 1.0
    return rgba, frags

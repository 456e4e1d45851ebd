"""The simulated camera: OpenGL (moderngl, headless EGL) rendering RGB and ground-truth depth.

One draw call renders the world's mesh (:func:`world_mesh`) into two colour attachments: the
lit, textured colour (RGBA8) and the camera-frame z of every fragment (R32F), which is the
z-depth along the optical axis, exact up to float32 rounding, instead of the non-linear window
depth. Pixels no surface covers (open sky, beyond the far plane) keep the clear value NaN.

Projection (OpenCV pinhole, pixel centres at integer coordinates): with clip coordinates
``(x_c, y_c, z_c, w_c) = P @ (x, y, z, 1)`` of an optical-frame point,

    x_c = 2 fx / W x + (2 (cx + 0.5) / W - 1) z     so the window x of pixel u's centre is u + 0.5
    y_c = 2 fy / H y + (2 (cy + 0.5) / H - 1) z     rows counted from the top, as read back
    z_c = (f + n) / (f - n) z - 2 f n / (f - n),    w_c = z

(n, f the near and far planes). OpenGL's window rows run bottom-up, and so does glReadPixels,
so mapping image row v to window row v makes the read-back buffer's first row the image's top.

Mesa's llvmpipe renders it on the CPU where there is no GPU (the system packages libegl1 and
libgl1-mesa-dri).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import math

import numpy as np

from autonomy.geometry import PinholeCamera, invert_pose
from drivers.sim.textures import SIZE, TILE_METRES, make_texture
from drivers.sim.world import Box, Cylinder, Rod, World

SKY_RGB = (0.62, 0.75, 0.92)
"""Colour of the open sky in outdoor worlds."""

CYLINDER_SEGMENTS = 16
"""Facets of a trunk, pole or rod. Its corners lie at radius ``R_v = 2 R / (1 + cos(pi / n))``,
so the facets (from ``R_v cos(pi / n)`` at their middles to ``R_v`` at their edges) stray at most
``R (1 - cos(pi / n)) / (1 + cos(pi / n))`` = 0.97 % of R (3.4 mm on a 0.35 m trunk, 0.5 mm on a
5 cm pole) from the true cylinder, inside and outside alike. Triangles are what llvmpipe pays
for, so few."""

_VERTEX_SHADER = """
#version 330
uniform mat4 clip_from_world;
uniform mat4 camera_from_world;
in vec3 in_position;
in vec3 in_normal;
in vec3 in_uv_layer;
out vec3 position_c;
out vec3 normal_c;
out vec3 uv_layer;
void main() {
    position_c = (camera_from_world * vec4(in_position, 1.0)).xyz;
    normal_c = mat3(camera_from_world) * in_normal;
    uv_layer = in_uv_layer;
    gl_Position = clip_from_world * vec4(in_position, 1.0);
}
"""

# Lighting: ambient plus Lambertian diffuse from either the sun (a direction fixed in the
# world) or a head lamp at the camera whose irradiance falls off as 1 / (1 + (d / d0)^2).
_FRAGMENT_SHADER = """
#version 330
uniform sampler2DArray textures;
uniform vec3 sun_c;
uniform float head_lamp_range;
uniform float ambient;
in vec3 position_c;
in vec3 normal_c;
in vec3 uv_layer;
layout(location = 0) out vec4 colour;
layout(location = 1) out float depth;
void main() {
    float distance = length(position_c);
    vec3 to_camera = -position_c / distance;
    vec3 normal = normalize(normal_c);
    float diffuse;
    if (head_lamp_range > 0.0) {
        float d = distance / head_lamp_range;
        diffuse = max(dot(normal, to_camera), 0.0) / (1.0 + d * d);
    } else {
        diffuse = max(dot(normal, sun_c), 0.0);
    }
    vec3 albedo = texture(textures, uv_layer).rgb;
    colour = vec4(albedo * (ambient + (1.0 - ambient) * diffuse), 1.0);
    depth = position_c.z;
}
"""


# A hazy world's variant (World.visibility): the surface's colour is blended towards the haze
# colour by the share of light a participating medium of that visibility scatters in over the
# distance to the camera (Koschmieder's law). The depth output stays the surface's z.
_HAZY_FRAGMENT_SHADER = _FRAGMENT_SHADER.replace(
    "uniform float ambient;\n",
    "uniform float ambient;\nuniform float visibility;\nuniform vec3 haze_rgb;\n",
).replace(
    "    colour = vec4(albedo * (ambient + (1.0 - ambient) * diffuse), 1.0);\n",
    "    vec3 surface = albedo * (ambient + (1.0 - ambient) * diffuse);\n"
    "    colour = vec4(mix(surface, haze_rgb, 1.0 - exp(-distance / visibility)), 1.0);\n",
)
assert _HAZY_FRAGMENT_SHADER.count("visibility") == 2


class RenderError(RuntimeError):
    """OpenGL rendering is unavailable; the message names what is missing."""


# ---- mesh ----------------------------------------------------------------------------------


def _quad(corner, edge_u, edge_v, normal, uvs, layer):
    """Four vertices (position, normal, uv, layer) and six indices of the parallelogram
    ``corner + [0, edge_u, edge_u + edge_v, edge_v]`` with the given ``(4, 2)`` uvs, its
    triangles wound counter-clockwise seen from the side ``normal`` points to (the front face;
    the renderer culls back faces)."""
    corners = np.array([corner, corner + edge_u, corner + edge_u + edge_v, corner + edge_v])
    rows = np.column_stack([corners, np.tile(normal, (4, 1)), uvs, np.full(4, layer)])
    if np.dot(np.cross(edge_u, edge_v), normal) > 0:
        return rows, np.array([0, 1, 2, 0, 2, 3])
    return rows, np.array([0, 2, 1, 0, 3, 2])


def _box_faces(box: Box, layer: int):
    """One quad for a panel (zero thickness along an axis), else the box's faces except the
    one on the floor. UVs are world coordinates in texture repeats (walls: along-wall, z)."""
    lo, hi = box.lo, box.hi
    for axis in range(3):
        tangents = [0, 1] if axis == 2 else [1 - axis, 2]  # walls: horizontal, then vertical
        edge_u, edge_v = np.zeros(3), np.zeros(3)
        edge_u[tangents[0]] = hi[tangents[0]] - lo[tangents[0]]
        edge_v[tangents[1]] = hi[tangents[1]] - lo[tangents[1]]
        if not (edge_u.any() and edge_v.any()):
            continue  # degenerate along a second axis: no area
        panel = lo[axis] == hi[axis]
        for side, outward in ((lo[axis], -1.0), (hi[axis], 1.0)):
            if panel and outward != box.facing:
                continue  # a panel has one face, on its open side
            if axis == 2 and side <= 0.0 and not panel:
                continue  # the bottom of a box standing on the floor is never seen
            corner = lo.copy()
            corner[axis] = side
            normal = np.zeros(3)
            normal[axis] = outward
            corners = corner + np.array([0 * edge_u, edge_u, edge_u + edge_v, edge_v])
            yield _quad(corner, edge_u, edge_v, normal, corners[:, tangents] / TILE_METRES,
                        layer)


def _cylinder_faces(cylinder: Cylinder, layer: int):
    """Side facets (an integer number of texture repeats round the trunk, so no seam) and a
    top cap fan."""
    n = CYLINDER_SEGMENTS
    angles = np.linspace(0.0, 2 * math.pi, n + 1)
    repeats = max(1, round(2 * math.pi * cylinder.radius / TILE_METRES))
    corner_radius = 2 * cylinder.radius / (1 + math.cos(math.pi / n))
    ring = np.column_stack([cylinder.centre[0] + corner_radius * np.cos(angles),
                            cylinder.centre[1] + corner_radius * np.sin(angles),
                            np.zeros(n + 1)])
    up = np.array([0.0, 0.0, cylinder.height])
    v_top = cylinder.height / TILE_METRES
    for k in range(n):
        middle = (angles[k] + angles[k + 1]) / 2
        normal = np.array([math.cos(middle), math.sin(middle), 0.0])
        u0, u1 = repeats * k / n, repeats * (k + 1) / n
        uvs = np.array([[u0, 0.0], [u1, 0.0], [u1, v_top], [u0, v_top]])
        yield _quad(ring[k], ring[k + 1] - ring[k], up, normal, uvs, layer)
    cap = np.vstack([[*cylinder.centre, 0.0], ring[:-1]]) + up
    cap_vertices = np.column_stack([cap, np.tile([0.0, 0.0, 1.0], (n + 1, 1)),
                                    cap[:, :2] / TILE_METRES, np.full(n + 1, layer)])
    fan = np.array([[0, 1 + k, 1 + (k + 1) % n] for k in range(n)]).ravel()
    yield cap_vertices, fan


def _rod_faces(rod: Rod, layer: int):
    """Side facets round the axis from ``a`` to ``b`` (as a trunk's, with the same corner
    radius) and a fan on each flat end."""
    n = CYLINDER_SEGMENTS
    axis = rod.b - rod.a
    length = float(np.linalg.norm(axis))
    u = axis / length
    helper = np.array([0.0, 0.0, 1.0]) if abs(u[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(helper, u)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)  # (e1, e2, u) right-handed
    angles = np.linspace(0.0, 2 * math.pi, n + 1)
    repeats = max(1, round(2 * math.pi * rod.radius / TILE_METRES))
    corner_radius = 2 * rod.radius / (1 + math.cos(math.pi / n))
    ring = rod.a + corner_radius * (np.cos(angles)[:, None] * e1 + np.sin(angles)[:, None] * e2)
    v_top = length / TILE_METRES
    for k in range(n):
        middle = (angles[k] + angles[k + 1]) / 2
        normal = math.cos(middle) * e1 + math.sin(middle) * e2
        u0, u1 = repeats * k / n, repeats * (k + 1) / n
        uvs = np.array([[u0, 0.0], [u1, 0.0], [u1, v_top], [u0, v_top]])
        yield _quad(ring[k], ring[k + 1] - ring[k], axis, normal, uvs, layer)
    for centre, normal, order in ((rod.b, u, 1), (rod.a, -u, -1)):
        cap = np.vstack([centre, ring[:-1] + (centre - rod.a)])
        local = (cap - centre) @ np.column_stack([e1, e2]) / TILE_METRES
        vertices = np.column_stack([cap, np.tile(normal, (n + 1, 1)), local,
                                    np.full(n + 1, layer)])
        # counter-clockwise seen from outside: (e1, e2) turns round +u, so reverse at the a end
        fan = np.array([[0, 1 + k, 1 + (k + 1) % n][::order] for k in range(n)]).ravel()
        yield vertices, fan


def world_mesh(world: World) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (V, 9) float32: position, normal, u, v, texture layer; indices (I,) int32)``
    of every surface of ``world`` (floor, panels, boxes, trunks and poles, rods); layer k is the
    texture of ``world.materials[k]``."""
    layer = {name: k for k, name in enumerate(world.materials)}
    faces = [*_box_faces(world.floor, layer[world.floor.material])]
    for box in world.boxes:
        faces += _box_faces(box, layer[box.material])
    for cylinder in world.cylinders:
        faces += _cylinder_faces(cylinder, layer[cylinder.material])
    for rod in world.rods:
        faces += _rod_faces(rod, layer[rod.material])
    vertices, indices, offset = [], [], 0
    for v, i in faces:
        vertices.append(v)
        indices.append(i + offset)
        offset += len(v)
    return np.concatenate(vertices).astype(np.float32), np.concatenate(indices).astype(np.int32)


# ---- renderer ------------------------------------------------------------------------------


def projection_matrix(camera: PinholeCamera, near: float, far: float) -> np.ndarray:
    """The 4x4 clip-from-optical-frame matrix of the module docstring."""
    w, h = camera.width, camera.height
    return np.array([
        [2 * camera.fx / w, 0.0, 2 * (camera.cx + 0.5) / w - 1, 0.0],
        [0.0, 2 * camera.fy / h, 2 * (camera.cy + 0.5) / h - 1, 0.0],
        [0.0, 0.0, (far + near) / (far - near), -2 * far * near / (far - near)],
        [0.0, 0.0, 1.0, 0.0],
    ])


def _load(library: str, what: str, packages: str) -> None:
    try:
        ctypes.CDLL(library)
    except OSError as error:
        raise RenderError(f"{what} is unavailable (could not load {library}): install the "
                          f"system package(s) {packages} [{error}]") from error


def create_context(libegl: str | None = None, libgl: str | None = None):
    """A headless OpenGL >= 3.3 context on EGL, or RenderError naming the missing library."""
    import moderngl  # imported here so the worlds work without OpenGL installed

    libegl = libegl or ctypes.util.find_library("EGL") or "libEGL.so.1"
    libgl = libgl or ctypes.util.find_library("GL") or "libGL.so.1"
    _load(libegl, "EGL", "libegl1 and libgl1-mesa-dri")
    _load(libgl, "OpenGL", "libgl1 and libgl1-mesa-dri")
    try:
        return moderngl.create_standalone_context(backend="egl", libegl=libegl, libgl=libgl,
                                                  require=330)
    except Exception as error:  # glcontext raises bare Exception
        raise RenderError(
            f"could not create a headless EGL OpenGL 3.3 context ({error}); without a GPU, "
            "Mesa's software rasteriser needs the system package libgl1-mesa-dri") from error


def _checked_pose(T_W_C) -> np.ndarray:
    T = np.asarray(T_W_C, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"T_W_C must be a 4x4 pose, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError("T_W_C must be finite")
    R = T[:3, :3]
    if not (np.allclose(R.T @ R, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0
            and np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0])):
        raise ValueError("T_W_C must be a rigid pose: a rotation block and last row (0, 0, 0, 1)")
    return T


class Renderer:
    """Renders ``world`` as seen by ``camera`` from optical-frame poses ``T_W_C``.

    ``near``/``far`` bound the rendered depth, metres. Lighting: outdoors the sun (from
    ``sun_W``, a direction towards the sun in the world frame) and sky; underground a head lamp
    at the camera with range ``head_lamp_range`` metres. A world with a ``visibility`` is hazy:
    each colour is ``lerp(surface, world.haze_rgb, 1 - exp(-distance / visibility))`` with the
    distance from the camera's centre (what no surface covers is the haze's colour); the depth
    is unchanged. ``libegl``/``libgl`` name the system libraries to load (default: found as the
    dynamic linker would).
    """

    def __init__(self, world: World, camera: PinholeCamera, *, near: float = 0.05,
                 far: float = 100.0, head_lamp_range: float = 20.0,
                 sun_W=(0.4, -0.3, 0.85), libegl: str | None = None, libgl: str | None = None):
        if not 0.0 < near < far or not math.isfinite(far):
            raise ValueError(f"need 0 < near < far < inf, got near={near}, far={far}")
        self.world, self.camera, self.near, self.far = world, camera, near, far
        self._projection = projection_matrix(camera, near, far)
        self._ctx = create_context(libegl, libgl)
        ctx = self._ctx
        try:
            hazy = world.visibility is not None
            self._program = ctx.program(
                vertex_shader=_VERTEX_SHADER,
                fragment_shader=_HAZY_FRAGMENT_SHADER if hazy else _FRAGMENT_SHADER)
            vertices, indices = world_mesh(world)
            self._vao = ctx.vertex_array(
                self._program,
                [(ctx.buffer(vertices.tobytes()), "3f 3f 3f", "in_position", "in_normal",
                  "in_uv_layer")],
                index_buffer=ctx.buffer(indices.tobytes()), index_element_size=4)
            layers = np.stack([make_texture(m, world.seed) for m in world.materials])
            self._textures = ctx.texture_array((SIZE, SIZE, len(layers)), 3, layers.tobytes())
            self._textures.build_mipmaps()
            self._textures.filter = (ctx.LINEAR_MIPMAP_NEAREST, ctx.LINEAR)  # bilinear: cheaper
            size = (camera.width, camera.height)
            colour, depth = ctx.renderbuffer(size, 4), ctx.renderbuffer(size, 1, dtype="f4")
            z_buffer = ctx.depth_renderbuffer(size)
            self._fbo = ctx.framebuffer([colour, depth], z_buffer)
            self._colour_fbo = ctx.framebuffer([colour], z_buffer)
            self._depth_fbo = ctx.framebuffer([depth])
            self._program["ambient"] = 0.55 if world.outdoor else 0.4
            self._program["head_lamp_range"] = 0.0 if world.outdoor else head_lamp_range
            self._sun_W = np.asarray(sun_W, dtype=float) / np.linalg.norm(sun_W)
            self._background = SKY_RGB if world.outdoor else (0.0, 0.0, 0.0)
            if hazy:
                self._program["visibility"] = float(world.visibility)
                self._program["haze_rgb"] = tuple(float(c) for c in world.haze_rgb)
                self._background = tuple(world.haze_rgb)
        except Exception:
            ctx.release()
            raise

    def render(self, T_W_C, alpha: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """``(rgb (H, W, 3) uint8, depth (H, W) float32)`` seen from ``T_W_C``: depth is the
        z-coordinate in the optical frame, metres, NaN where no surface lies within ``far``.
        Row 0 is the top of the image. With ``alpha`` the colour is ``(H, W, 4)``, alpha
        opaque (255): the framebuffer's own layout, read without a conversion, for a consumer
        that works on four channels."""
        T_W_C = _checked_pose(T_W_C)
        with self._ctx:  # this renderer's context current, whichever other one was made last
            return self._render(T_W_C, 4 if alpha else 3)

    def _render(self, T_W_C: np.ndarray, channels: int) -> tuple[np.ndarray, np.ndarray]:
        T_C_W = invert_pose(T_W_C)
        self._program["camera_from_world"].write(T_C_W.T.astype("f4").tobytes())
        self._program["clip_from_world"].write((self._projection @ T_C_W).T.astype("f4")
                                               .tobytes())
        self._program["sun_c"] = tuple(T_C_W[:3, :3] @ self._sun_W)
        # Image rows run down the window's y, a mirror, so counter-clockwise front faces
        # appear clockwise.
        self._ctx.front_face = "cw"
        self._ctx.enable_only(self._ctx.DEPTH_TEST | self._ctx.CULL_FACE)
        self._colour_fbo.clear(*self._background, 1.0, depth=1.0)
        self._depth_fbo.clear(math.nan, 0.0, 0.0, 0.0)
        self._fbo.use()
        self._textures.use(0)
        self._vao.render()
        h, w = self.camera.height, self.camera.width
        rgb = np.empty((h, w, channels), np.uint8)
        depth = np.empty((h, w), np.float32)
        self._fbo.read_into(rgb, components=channels, attachment=0)
        self._fbo.read_into(depth, components=1, attachment=1, dtype="f4")
        return rgb, depth

    def close(self) -> None:
        """Release the OpenGL context and everything in it (idempotent)."""
        if self._ctx is not None:
            self._ctx.release()
            self._ctx = None

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

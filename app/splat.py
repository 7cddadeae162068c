"""Compute-shader point splatting for the 3-D viewer: every point, every frame, on software GL.

Why: llvmpipe (Mesa's software OpenGL) runs the fixed-function vertex path and point setup on
one thread, ~10 M points/s on this 2-core machine, so 2 M points cannot be redrawn 20 times a
second that way. Its compute shaders, though, run on all cores and 8 SIMD lanes. So when the
context has GL 4.3 compute shaders (llvmpipe offers a 4.5 compatibility profile), the viewer
draws points in two passes instead of ``glDrawArrays(GL_POINTS)``:

1. **Splat** (compute): each invocation transforms a point with projection x modelview as
   read back from the fixed-function GL state -- the very matrices the viewer loads and the
   pick reads back, multiplied in float32 the way Mesa forms its own MVP -- and keeps the
   smallest ``window depth (24 bits) << 8 | colour index (8 bits)`` per pixel (``atomicMin``
   into a ``(width + 1) x (height + 1)`` uint buffer): the nearest point, as GL_LESS would.
   Clipping, the 1/256-pixel snap, the pixel a point lands on and the 24-bit depth follow
   llvmpipe's own rules for ``GL_POINTS``.
2. **Resolve** (fragment, one full-screen quad): looks the colour up in a 256-entry palette and
   writes ``gl_FragDepth = D / (2^24 - 1)``, which the 24-bit depth buffer stores as D again.
   So the default framebuffer's depth buffer holds the window depth the fixed-function path
   would have written for that point -- on llvmpipe bit for bit, except where two points tie
   (tests/test_viewer.py) -- and picking (``glReadPixels`` + ``gluUnProject`` with the
   matrices read back from GL) works unchanged. Points wider than one pixel: the resolve takes
   the nearest point whose GL point square (legacy, non-sprite rules) covers the pixel. Pixels
   without a point get the background colour and depth 1, so the frame needs no glClear.

Colours are an 8-bit index into a palette: the white frame's grey level (exact for grey
cameras), the depth colour map's level (exact), or for a colour camera's white frame a
256-colour median-cut palette of the cloud's colours (close, not exact).

Anything missing (no GL 4.3, a shader that does not compile) raises :class:`SplatUnavailable`
and the viewer keeps the classic fixed-function path.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from OpenGL import GL

DEPTH_BITS = 24
DEPTH_MAX = (1 << DEPTH_BITS) - 1
EMPTY = 0xFFFFFFFF
MAX_POINT_SIZE = 16  # px; the viewer offers 1-6 (auto 1-5)
LOCAL_SIZE = 64      # invocations per work group
UNROLL = 4           # points per invocation per loop step: hides memory latency, amortises masks
BATCHES = 8          # loop steps per invocation: one work group covers 64 * 4 * 8 = 2048 points
POINTS_PER_GROUP = LOCAL_SIZE * UNROLL * BATCHES

# What chose this layout (2 M shuffled points, 1000x750, llvmpipe 256-bit on 2 shared cores;
# one interleaved run, so the ratios hold, not the absolute ms): 8 points per invocation in a
# plain loop 32 ms, the same 4-way unrolled 23 ms (independent points hide memory latency and
# amortise llvmpipe's per-lane masking), unrolled without the test before the atomic 32 ms.
# One point per invocation (no loop) was ~40 ms. Positions come through a buffer texture
# (vectorised gather) rather than an SSBO (llvmpipe loads SSBOs lane by lane); the image is an
# SSBO (its atomics beat imageAtomicMin ~2x) read through a buffer texture for the test.
# On an idle machine the whole splat pass is ~12 ms, the resolve ~5 ms.
SPLAT_CS = f"""
#version 430 compatibility
layout(local_size_x = {LOCAL_SIZE}) in;
uniform samplerBuffer points;        // xyz, w = colour index (uint bits)
uniform mat4 mvp;                    // GL_PROJECTION_MATRIX x GL_MODELVIEW_MATRIX
layout(std430, binding = 0) buffer Image {{ uint image[]; }};  // (w + 1) x (h + 1)
uniform ivec2 size;                  // viewport w, h (device pixels)
uniform uint count;
uniform usamplerBuffer current;     // the image again, for a cheap test before the atomic
uniform float anchor;                // 0 for odd point sizes, 0.5 for even ones
uniform vec2 depth_range;            // glDepthRange: near, far - near

void splat(uint i) {{
    vec4 q = texelFetch(points, int(i));
    vec4 c = mvp * vec4(q.xyz, 1.0);
    // What llvmpipe does to a GL_POINTS vertex, so that both paths agree to the bit (checked
    // by tests/test_viewer.py): perspective divide by multiplying with 1/w, the viewport
    // transform glViewport(0, 0, w, h) as scale + translate, x/y snapped to 1/256 pixel, the
    // pixel = floor of that (legacy GL point rule), depth = round-to-nearest-even of
    // window z * (2^24 - 1) in float32.
    vec3 ndc = c.xyz * (1.0 / c.w);
    vec2 win = ndc.xy * (0.5 * vec2(size)) + 0.5 * vec2(size);
    vec2 m = floor(roundEven(win * 256.0) / 256.0 + anchor);  // 0 ... w or h (even sizes)
    // GL clips a point by its centre: inside the clip volume or not drawn at all
    bool inside = i < count && c.w > 0.0 && all(lessThanEqual(abs(c.xyz), vec3(c.w)));
    uint depth = uint(roundEven((depth_range.x + depth_range.y * (ndc.z * 0.5 + 0.5)) * {DEPTH_MAX}.0));
    uint value = (depth << 8) | (floatBitsToUint(q.w) & 255u);
    int k = inside ? int(m.y) * (size.x + 1) + int(m.x) : 0;
    // Most points are behind one already splatted: skip their atomic. The texture read may be
    // stale, but the image only ever decreases, so a stale value can only cost an atomic.
    if (inside && value < texelFetch(current, k).x)
        atomicMin(image[k], value);
}}

void main() {{
    uint base = gl_WorkGroupID.x * {POINTS_PER_GROUP}u + gl_LocalInvocationID.x;
    for (uint j = 0u; j < {POINTS_PER_GROUP}u; j += {LOCAL_SIZE * UNROLL}u) {{
        uint i = base + j;
        splat(i);
        splat(i + {LOCAL_SIZE}u);
        splat(i + {2 * LOCAL_SIZE}u);
        splat(i + {3 * LOCAL_SIZE}u);
    }}
}}
"""

RESOLVE_VS = """
#version 430 compatibility
void main() { gl_Position = vec4(gl_Vertex.xy, 0.0, 1.0); }
"""

# A pixel shows the nearest point whose GL point square covers it. The splat stores a point of
# size s at pixel m = floor(window xy + anchor); its square then spans m - s/2 ... m - s/2 + s - 1
# (integer division), so pixel p looks at m in p + [LO, HI] = p + [s/2 - s + 1, s/2]. The image
# has one extra column and row: an even-sized point centred in the last half pixel has m = w.
RESOLVE_FS = """
#version 430 compatibility
uniform usamplerBuffer image;
uniform sampler2D palette;           // 256 x 1 RGBA8
uniform ivec2 size;
uniform vec4 background;
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    uint v = 0xFFFFFFFFu;
    for (int dy = LO; dy <= HI; ++dy) {
        int y = p.y + dy;
        for (int dx = LO; dx <= HI; ++dx) {
            int x = p.x + dx;
            if (x >= 0 && y >= 0 && x <= size.x && y <= size.y)
                v = min(v, texelFetch(image, y * (size.x + 1) + x).x);
        }
    }
    if (v == 0xFFFFFFFFu) {           // no point: what glClear would leave
        gl_FragColor = background;
        gl_FragDepth = 1.0;
    } else {
        gl_FragColor = texelFetch(palette, ivec2(int(v & 255u), 0), 0);
        gl_FragDepth = float(v >> 8u) / DEPTH_MAX;
    }
}
""".replace("DEPTH_MAX", f"{DEPTH_MAX}.0")


class SplatUnavailable(RuntimeError):
    """The current context cannot run the splat path (the reason is the message)."""


def resolve_window(size: int) -> tuple[int, int]:
    """Offsets (LO, HI) of the anchors whose GL point square of ``size`` px covers a pixel."""
    return size // 2 - size + 1, size // 2


def anchor_of(size: int) -> float:
    return 0.0 if size % 2 else 0.5


def gl_point_size(size: float) -> int:
    """The width GL rasterises for an aliased point of ``size``: the nearest integer (llvmpipe
    rounds halves down), at least 1, here at most MAX_POINT_SIZE."""
    return int(min(max(np.ceil(size - 0.5), 1), MAX_POINT_SIZE))


def gl_mvp() -> np.ndarray:
    """Projection x modelview as the fixed-function pipeline forms it: from the float32
    matrices GL holds, multiplied in float32 term by term (Mesa's matmul4). Column-major."""
    p = np.array(GL.glGetFloatv(GL.GL_PROJECTION_MATRIX), np.float32).reshape(4, 4).T  # maths convention
    m = np.array(GL.glGetFloatv(GL.GL_MODELVIEW_MATRIX), np.float32).reshape(4, 4).T
    out = p[:, 0:1] * m[0:1, :]
    for k in range(1, 4):
        out = out + p[:, k:k + 1] * m[k:k + 1, :]
    return np.ascontiguousarray(out.T, np.float32)


def _text(log: object) -> str:
    return log.decode(errors="replace").strip() if isinstance(log, bytes) else str(log)


def _checked(obj: int, ok: int, log: Callable[[int], object], delete: Callable[[int], object], what: str) -> int:
    """``obj`` if its status ``ok`` holds, else delete it and raise with its info log."""
    if not ok:
        text = _text(log(obj))
        delete(obj)
        raise SplatUnavailable(f"{what}: {text}")
    return obj


def _compile(kind: int, source: str) -> int:
    shader = GL.glCreateShader(kind)
    GL.glShaderSource(shader, source)
    GL.glCompileShader(shader)
    return _checked(shader, GL.glGetShaderiv(shader, GL.GL_COMPILE_STATUS), GL.glGetShaderInfoLog,
                    GL.glDeleteShader, "shader does not compile")


def _link(*shaders: int) -> int:
    program = GL.glCreateProgram()
    for s in shaders:
        GL.glAttachShader(program, s)
    GL.glLinkProgram(program)
    for s in shaders:
        GL.glDeleteShader(s)
    return _checked(program, GL.glGetProgramiv(program, GL.GL_LINK_STATUS), GL.glGetProgramInfoLog,
                    GL.glDeleteProgram, "program does not link")


def context_version() -> tuple[int, int]:
    try:
        return int(GL.glGetIntegerv(GL.GL_MAJOR_VERSION)), int(GL.glGetIntegerv(GL.GL_MINOR_VERSION))
    except Exception:  # a GL 2.x context does not know GL_MAJOR_VERSION
        GL.glGetError()
        text = GL.glGetString(GL.GL_VERSION).decode().split()[0]
        major, minor = text.split(".")[:2]
        return int(major), int(minor)


class _ResolveProgram(NamedTuple):
    """A linked resolve program (one per point size) and its uniforms' locations by name."""

    program: int
    uniforms: dict[str, int]


class SplatRenderer:
    """GL objects of the splat path. Create, use and delete with the viewer's context current."""

    def __init__(self) -> None:
        version = context_version()
        if version < (4, 3):
            raise SplatUnavailable(f"OpenGL {version[0]}.{version[1]} context, compute shaders need 4.3")
        self.version = version
        self._programs: dict[int, _ResolveProgram] = {}
        self._buffers: list[int] = []
        self._textures: list[int] = []
        try:
            self.splat = _link(_compile(GL.GL_COMPUTE_SHADER, SPLAT_CS))
            self._resolve_program(1)
        except Exception:
            self.delete()
            raise
        self.points_buffer = self._new_buffer()
        self.points_texture = self._new_texture()
        self.image_buffer = self._new_buffer()
        self.image_texture = self._new_texture()
        self.palette_texture = self._new_texture()
        self.count = 0
        self.image_size = (0, 0)
        self._uniforms = {name: GL.glGetUniformLocation(self.splat, name)
                          for name in ("points", "current", "mvp", "size", "count", "anchor", "depth_range")}

    def _new_buffer(self) -> int:
        b = int(GL.glGenBuffers(1))
        self._buffers.append(b)
        return b

    def _new_texture(self) -> int:
        t = int(GL.glGenTextures(1))
        self._textures.append(t)
        return t

    def _resolve_program(self, size: int) -> _ResolveProgram:
        if size not in self._programs:
            lo, hi = resolve_window(size)
            fs = RESOLVE_FS.replace("LO", str(lo)).replace("HI", str(hi))
            program = _link(_compile(GL.GL_VERTEX_SHADER, RESOLVE_VS), _compile(GL.GL_FRAGMENT_SHADER, fs))
            self._programs[size] = _ResolveProgram(program, {name: GL.glGetUniformLocation(program, name)
                                                             for name in ("image", "palette", "size", "background")})
        return self._programs[size]

    def delete(self) -> None:
        for program, _ in self._programs.values():
            GL.glDeleteProgram(program)
        if getattr(self, "splat", None):
            GL.glDeleteProgram(self.splat)
            self.splat = 0
        if self._buffers:
            GL.glDeleteBuffers(len(self._buffers), self._buffers)
        if self._textures:
            GL.glDeleteTextures(len(self._textures), self._textures)
        self._programs, self._buffers, self._textures = {}, [], []

    # ---- data ----------------------------------------------------------------------------
    def upload(self, points: np.ndarray, index: np.ndarray) -> None:
        """Points (N, 3) float32 and their colour index (N,) uint8 into one RGBA32F buffer."""
        n = len(points)
        packed = np.empty((n, 4), np.float32)
        packed[:, :3] = points
        packed[:, 3].view(np.uint32)[:] = index
        GL.glBindBuffer(GL.GL_TEXTURE_BUFFER, self.points_buffer)
        GL.glBufferData(GL.GL_TEXTURE_BUFFER, packed.nbytes, packed if n else None, GL.GL_STATIC_DRAW)
        GL.glBindTexture(GL.GL_TEXTURE_BUFFER, self.points_texture)
        GL.glTexBuffer(GL.GL_TEXTURE_BUFFER, GL.GL_RGBA32F, self.points_buffer)
        GL.glBindTexture(GL.GL_TEXTURE_BUFFER, 0)
        GL.glBindBuffer(GL.GL_TEXTURE_BUFFER, 0)
        self.count = n

    def set_palette(self, palette: np.ndarray) -> None:
        """(256, 4) uint8 RGBA."""
        GL.glBindTexture(GL.GL_TEXTURE_2D, self.palette_texture)
        GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_NEAREST)
        GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, GL.GL_NEAREST)
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
        GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, GL.GL_RGBA8, 256, 1, 0, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE,
                        np.ascontiguousarray(palette, np.uint8))
        GL.glBindTexture(GL.GL_TEXTURE_2D, 0)

    def _ensure_image(self, w: int, h: int) -> None:
        if self.image_size == (w, h):
            return
        GL.glBindBuffer(GL.GL_SHADER_STORAGE_BUFFER, self.image_buffer)
        GL.glBufferData(GL.GL_SHADER_STORAGE_BUFFER, (w + 1) * (h + 1) * 4, None, GL.GL_DYNAMIC_COPY)
        GL.glBindBuffer(GL.GL_SHADER_STORAGE_BUFFER, 0)
        GL.glBindTexture(GL.GL_TEXTURE_BUFFER, self.image_texture)
        GL.glTexBuffer(GL.GL_TEXTURE_BUFFER, GL.GL_R32UI, self.image_buffer)
        GL.glBindTexture(GL.GL_TEXTURE_BUFFER, 0)
        self.image_size = (w, h)

    # ---- drawing -------------------------------------------------------------------------
    def draw(self, w: int, h: int, point_size: float, background: tuple[float, float, float]) -> None:
        """Splat + resolve into the bound framebuffer. Expects glViewport(0, 0, w, h) and the
        fixed-function projection/modelview of the frame already loaded; leaves the depth
        test on with GL_LESS, depth writes on, no program bound."""
        size = gl_point_size(point_size)
        resolve, uniforms = self._resolve_program(size)
        self._ensure_image(w, h)
        GL.glBindBuffer(GL.GL_SHADER_STORAGE_BUFFER, self.image_buffer)
        GL.glClearBufferData(GL.GL_SHADER_STORAGE_BUFFER, GL.GL_R32UI, GL.GL_RED_INTEGER, GL.GL_UNSIGNED_INT,
                             np.array([EMPTY], np.uint32))
        GL.glBindBuffer(GL.GL_SHADER_STORAGE_BUFFER, 0)
        GL.glBindBufferBase(GL.GL_SHADER_STORAGE_BUFFER, 0, self.image_buffer)

        GL.glUseProgram(self.splat)
        u = self._uniforms
        GL.glActiveTexture(GL.GL_TEXTURE0)
        GL.glBindTexture(GL.GL_TEXTURE_BUFFER, self.points_texture)
        GL.glUniform1i(u["points"], 0)
        GL.glActiveTexture(GL.GL_TEXTURE1)
        GL.glBindTexture(GL.GL_TEXTURE_BUFFER, self.image_texture)
        GL.glUniform1i(u["current"], 1)
        GL.glActiveTexture(GL.GL_TEXTURE0)
        # Not the built-in gl_ModelViewProjectionMatrix: Mesa 22 does not refresh it for compute
        # shaders when the matrices change (the splat drew the first frame's view ever after).
        GL.glUniformMatrix4fv(u["mvp"], 1, GL.GL_FALSE, gl_mvp())
        GL.glUniform2i(u["size"], w, h)
        GL.glUniform1ui(u["count"], self.count)
        GL.glUniform1f(u["anchor"], anchor_of(size))
        near, far = (float(v) for v in GL.glGetFloatv(GL.GL_DEPTH_RANGE))
        GL.glUniform2f(u["depth_range"], near, far - near)
        if self.count:
            GL.glDispatchCompute((self.count + POINTS_PER_GROUP - 1) // POINTS_PER_GROUP, 1, 1)
        GL.glMemoryBarrier(GL.GL_TEXTURE_FETCH_BARRIER_BIT | GL.GL_SHADER_STORAGE_BARRIER_BIT)

        GL.glUseProgram(resolve)
        GL.glBindTexture(GL.GL_TEXTURE_BUFFER, self.image_texture)
        GL.glUniform1i(uniforms["image"], 0)
        GL.glActiveTexture(GL.GL_TEXTURE1)
        GL.glBindTexture(GL.GL_TEXTURE_2D, self.palette_texture)
        GL.glUniform1i(uniforms["palette"], 1)
        GL.glUniform2i(uniforms["size"], w, h)
        GL.glUniform4f(uniforms["background"], *background, 1.0)
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthFunc(GL.GL_ALWAYS)  # every pixel is written: the resolve replaces the clear
        GL.glDepthMask(GL.GL_TRUE)
        GL.glBegin(GL.GL_QUADS)
        for x, y in ((-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)):
            GL.glVertex2f(x, y)
        GL.glEnd()
        GL.glDepthFunc(GL.GL_LESS)
        GL.glUseProgram(0)
        GL.glBindTexture(GL.GL_TEXTURE_2D, 0)
        GL.glBindTexture(GL.GL_TEXTURE_BUFFER, 0)
        GL.glActiveTexture(GL.GL_TEXTURE0)
        GL.glBindTexture(GL.GL_TEXTURE_BUFFER, 0)
        GL.glBindBufferBase(GL.GL_SHADER_STORAGE_BUFFER, 0, 0)


# ---------------------------------------------------------------------------- colours

def grey_palette() -> np.ndarray:
    ramp = np.arange(256, dtype=np.uint8)
    out: np.ndarray = np.c_[ramp, ramp, ramp, np.full(256, 255, np.uint8)]
    return out


def indexed_colours(rgba: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """(N, 4) uint8 colours as an 8-bit index, a (256, 4) palette and whether it is exact.
    Grey colours (a monochrome camera's white frame) index a grey ramp exactly; others get a
    256-colour median-cut palette."""
    rgb = rgba[:, :3]
    if len(rgb) == 0:
        return np.zeros(0, np.uint8), grey_palette(), True
    if np.array_equal(rgb[:, 0], rgb[:, 1]) and np.array_equal(rgb[:, 0], rgb[:, 2]):
        grey: np.ndarray = np.ascontiguousarray(rgb[:, 0])
        return grey, grey_palette(), True
    palette = median_cut(rgb[:: max(1, len(rgb) // 32768)], 256)
    # every 5-bit-per-channel colour cell to its nearest palette entry, then a table lookup
    cells = (np.indices((32, 32, 32)).reshape(3, -1).T * 8 + 4).astype(np.float32)
    pal = palette[:, :3].astype(np.float32)
    lut = np.empty(len(cells), np.uint8)
    for s in range(0, len(cells), 4096):
        c = cells[s:s + 4096]
        d = (c * c).sum(1)[:, None] - 2 * c @ pal.T + (pal * pal).sum(1)[None, :]
        lut[s:s + 4096] = d.argmin(1)
    q = rgb >> 3
    index = lut[(q[:, 0].astype(np.int32) << 10) | (q[:, 1].astype(np.int32) << 5) | q[:, 2]]
    return index, palette, False


def median_cut(rgb: np.ndarray, n: int) -> np.ndarray:
    """Up to ``n`` representative colours (RGBA uint8, padded to ``n`` rows) of ``rgb``:
    repeatedly split the box with the widest channel range at its median."""
    def spread(b: np.ndarray) -> np.ndarray:
        out: np.ndarray = (b.max(0) - b.min(0)) if len(b) > 1 else np.zeros(3, np.int16)
        return out

    boxes = [np.asarray(rgb, np.int16)]
    spreads = [spread(boxes[0])]
    while len(boxes) < n:
        k = int(np.argmax([s.max() for s in spreads]))
        if spreads[k].max() <= 0:
            break
        b, channel = boxes.pop(k), int(np.argmax(spreads.pop(k)))
        b = b[np.argsort(b[:, channel], kind="stable")]
        for half in (b[:len(b) // 2], b[len(b) // 2:]):
            boxes.append(half)
            spreads.append(spread(half))
    palette = np.zeros((n, 4), np.uint8)
    palette[:, 3] = 255
    for i, b in enumerate(boxes):
        palette[i, :3] = np.round(b.mean(0)).astype(np.uint8)
    return palette


__all__ = ["SplatRenderer", "SplatUnavailable", "indexed_colours", "grey_palette", "median_cut",
           "gl_point_size", "resolve_window", "anchor_of", "DEPTH_MAX"]

"""Render GLSL on the CPU (Mesa llvmpipe through EGL, via moderngl): the check that generated shader code runs and
matches our numpy evaluation, without a GPU.

A fragment shader is drawn over a full-screen quad into a float32 W x H target; the vertex stage feeds
``i_position`` (clip space) and ``i_texcoord_0`` (0..1, v up, as MaterialX's generated shaders expect). Rows of the
returned array go top to bottom like our maps: row 0 is v = 1.
"""
from __future__ import annotations

import functools
import logging

import numpy as np

from ..errors import InputError

logger = logging.getLogger(__name__)

#: a vertex stage for hand-written fragment shaders: passes the texture coordinate on as ``texcoord``
PLAIN_VERTEX = """#version 400
in vec3 i_position;
in vec2 i_texcoord_0;
out vec2 texcoord;
void main() { texcoord = i_texcoord_0; gl_Position = vec4(i_position, 1.0); }
"""


class GlslUnavailable(InputError):
    """No OpenGL 4 context can be made here (moderngl or EGL/Mesa missing)."""


@functools.lru_cache(maxsize=1)
def context():
    """One standalone headless OpenGL context per process (EGL; Mesa's llvmpipe on a machine without a GPU)."""
    try:
        import moderngl
    except ImportError as exc:
        raise GlslUnavailable("the GLSL check needs the Python package moderngl (pip install moderngl)") from exc
    try:
        ctx = moderngl.create_context(standalone=True, backend="egl")
    except Exception as exc:  # noqa: BLE001 - any failure to get a context means: cannot check here
        raise GlslUnavailable(f"no headless OpenGL context (EGL; Debian packages libegl1 libegl-mesa0 "
                              f"libgl1-mesa-dri): {exc}") from exc
    logger.info("GLSL context: %s, OpenGL %s", ctx.info.get("GL_RENDERER"), ctx.info.get("GL_VERSION"))
    return ctx


def available() -> bool:
    """Whether an OpenGL 4 context can be made here (what the GLSL checks need)."""
    try:
        context()
        return True
    except GlslUnavailable:
        return False


def renderer() -> str:
    """The OpenGL renderer's name (e.g. 'llvmpipe (LLVM 15.0.6, 256 bits)')."""
    return str(context().info.get("GL_RENDERER"))


def compile_program(fragment: str, vertex: str = PLAIN_VERTEX):
    """Compile and link a program; a compile error raises with the driver's log (which names the line)."""
    ctx = context()
    try:
        return ctx.program(vertex_shader=vertex, fragment_shader=fragment)
    except Exception as exc:  # moderngl.Error carries the compiler log
        raise InputError(f"GLSL does not compile: {exc}") from exc


def render(fragment: str, width: int, height: int, *, vertex: str = PLAIN_VERTEX,
           uniforms: dict | None = None, textures: dict[str, np.ndarray] | None = None,
           nearest: frozenset = frozenset(), tile_rows: int = 0) -> np.ndarray:
    """Draw `fragment` over a width x height image and return its RGBA output, float32 (height, width, 4).

    ``uniforms`` sets values by name (names the program does not use are ignored); ``textures`` binds sampler
    uniforms to float images (HxWx4, row 0 = the top, read at v = 1; periodic, linear filtering, or the closest
    texel for the names in ``nearest``: the sampler state is the renderer's, as MaterialX's filtertype says);
    ``tile_rows`` > 0 draws the image in bands of that many rows (a long draw call can trip the driver's watchdog
    on real GPUs)."""
    import moderngl

    if width < 1 or height < 1:
        raise InputError(f"render size must be positive, got {width}x{height}")
    ctx = context()
    prog = compile_program(fragment, vertex)
    for name, value in (uniforms or {}).items():
        if name in prog:
            try:
                prog[name].value = value
            except Exception as exc:  # noqa: BLE001 - a uniform the compiler shrank (unused elements)
                logger.debug("uniform %s not set: %s", name, exc)
    bound = []
    for unit, (name, img) in enumerate((textures or {}).items()):
        if name not in prog:
            continue
        a = np.ascontiguousarray(np.asarray(img, dtype=np.float32)[::-1])   # GL rows go bottom to top
        t = ctx.texture((a.shape[1], a.shape[0]), a.shape[2], a.tobytes(), dtype="f4")
        t.repeat_x = t.repeat_y = True
        t.filter = (moderngl.NEAREST, moderngl.NEAREST) if name in nearest else (moderngl.LINEAR, moderngl.LINEAR)
        t.use(location=unit)
        prog[name].value = unit
        bound.append(t)
    quad = np.array([-1, -1, 0, 0, 0, 1, -1, 0, 1, 0, -1, 1, 0, 0, 1, 1, 1, 0, 1, 1], dtype="f4")
    vbo = ctx.buffer(quad.tobytes())
    names = [n for n in ("i_position", "i_texcoord_0") if n in prog]
    fmt = {"i_position": "3f", "i_texcoord_0": "2f"}
    layout = " ".join(fmt[n] if n in names else fmt[n].replace("f", "x4") for n in ("i_position", "i_texcoord_0"))
    vao = ctx.vertex_array(prog, [(vbo, layout, *names)])
    tex = ctx.texture((width, height), 4, dtype="f4")
    fbo = ctx.framebuffer(color_attachments=[tex])
    try:
        fbo.use()
        band = tile_rows if tile_rows > 0 else height
        for y0 in range(0, height, band):
            ctx.scissor = (0, y0, width, min(band, height - y0))
            vao.render(moderngl.TRIANGLE_STRIP)
            ctx.finish()
        ctx.scissor = None
        data = np.frombuffer(fbo.read(components=4, dtype="f4"), dtype=np.float32).reshape(height, width, 4)
    finally:
        for obj in (fbo, tex, vao, vbo, prog, *bound):
            obj.release()
    return data[::-1].copy()   # OpenGL rows go bottom to top

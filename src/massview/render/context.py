"""Headless OpenGL through EGL: Mesa llvmpipe on CPU-only machines, the vendor driver on GPU nodes.

The only module that creates GL contexts. ``create_context`` returns a moderngl context and
raises :class:`GLUnavailableError` naming the system packages to install when EGL or a driver
is missing.
"""

from __future__ import annotations

import ctypes
import importlib.resources

import moderngl

from ..core.errors import GLUnavailableError

__all__ = ["create_context", "release_gl", "renderer_string", "load_shader", "finish", "max_frame_size", "check_frame_size"]

_INSTALL_HINT = (
    "massview renders headless through EGL. Install the EGL loader and an OpenGL driver: "
    "on Debian/Ubuntu `apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri` (Mesa llvmpipe, CPU), "
    "or the NVIDIA driver's EGL libraries (libnvidia-gl) on GPU nodes."
)


def create_context(device_index: int | None = None) -> moderngl.Context:
    """A standalone OpenGL 3.3+ core context through EGL (no window, no display server).

    ``device_index`` picks an EGL device on multi-GPU nodes (e.g. the local rank)."""
    kw = {"backend": "egl", "require": 330}
    if device_index is not None:
        kw["device_index"] = int(device_index)
    try:
        ctx = moderngl.create_standalone_context(**kw)
    except Exception as e:  # glcontext raises plain Exceptions with driver messages
        raise GLUnavailableError(f"could not create a headless OpenGL context ({e}). {_INSTALL_HINT}") from None
    return ctx


def release_gl(owner) -> None:
    """Release ``owner._gl``'s context (its first item) and with it every GL object made on it
    (the block or mesh pool of ``--gpu-mb``, targets, programs): a system's ``close()``. The
    owner makes them anew on next use (``_gl`` is set to None)."""
    gl = getattr(owner, "_gl", None)
    if gl is not None:
        owner._gl = None
        gl[0].release()


def renderer_string(ctx: moderngl.Context) -> str:
    info = ctx.info
    return f"{info.get('GL_RENDERER', '?')} / {info.get('GL_VERSION', '?')}"


def max_frame_size(ctx: moderngl.Context) -> int:
    """The largest width and height of a render target this context takes: the least of its
    renderbuffer, texture and viewport limits (16384 on llvmpipe, 32768 on recent NVIDIA)."""
    info = ctx.info
    dims = info.get("GL_MAX_VIEWPORT_DIMS", (1 << 30, 1 << 30))
    return int(min(info.get("GL_MAX_RENDERBUFFER_SIZE", 1 << 30), info.get("GL_MAX_TEXTURE_SIZE", 1 << 30), *dims))


def check_frame_size(ctx: moderngl.Context, width: int, height: int) -> None:
    """A ConfigError naming ``--size`` and this renderer's limit when a ``width × height``
    target is larger than it can make (instead of GL's "framebuffer is not complete")."""
    from ..core.errors import ConfigError

    limit = max_frame_size(ctx)
    if width > limit or height > limit:
        raise ConfigError(f"--size {width}x{height}: this renderer ({renderer_string(ctx)}) draws frames of at most "
                          f"{limit}x{limit}; give a smaller --size")


def load_shader(name: str) -> str:
    """GLSL source shipped in ``massview/render/shaders``."""
    return importlib.resources.files("massview.render").joinpath("shaders").joinpath(name).read_text()


def _gl_finish():
    """``glFinish`` through ctypes from the GL dispatch library the context's calls go through
    (glvnd's libGL, or libOpenGL), or None. ctypes releases the GIL for the call; moderngl's
    ``ctx.finish()`` keeps it while llvmpipe's raster threads draw the frame, which stops every
    other Python thread of the rank (the pipelined loop's compositing thread) for most of a
    frame (issue 20: a compositing thread ran at 0.05–0.07× its speed during draws)."""
    for name in ("libGL.so.1", "libOpenGL.so.0"):
        try:
            fn = ctypes.CDLL(name).glFinish
        except (OSError, AttributeError):
            continue
        fn.restype, fn.argtypes = None, []
        return fn
    return None


_FINISH: list = []


def finish(ctx: moderngl.Context) -> None:
    """Wait until ``ctx`` (the current context) has executed every GL command, letting other
    Python threads run meanwhile; falls back to ``ctx.finish()``."""
    if not _FINISH:
        _FINISH.append(_gl_finish())
    fn = _FINISH[0]
    if fn is None:
        ctx.finish()
    else:
        fn()

"""The process's headless OpenGL context (moderngl over EGL), created lazily.

A GL context does not survive ``fork``: the context is tied to the process id, and a child process that
asks for it gets a fresh one.
"""

from __future__ import annotations

import os

import moderngl


class RenderError(RuntimeError):
    """Headless OpenGL is unavailable or a render failed."""


_CTX: moderngl.Context | None = None
_PID: int | None = None
EGL_HINT = ("headless OpenGL needs EGL: install the system packages libegl1 libegl-mesa0 libgl1-mesa-dri "
            "libgbm1 (Debian/Ubuntu), or the NVIDIA driver's EGL library on a GPU machine")


def gl_context() -> moderngl.Context:
    """The process-wide moderngl context (OpenGL >= 3.3 through EGL, no display needed)."""
    global _CTX, _PID
    if _CTX is None or _PID != os.getpid():
        try:
            _CTX = moderngl.create_context(standalone=True, backend="egl", require=330)
        except Exception as e:  # moderngl/glcontext raise bare Exceptions for a missing libEGL
            raise RenderError(f"cannot create an EGL OpenGL context ({e}); {EGL_HINT}") from None
        _PID = os.getpid()
    return _CTX


def gl_info() -> dict[str, str]:
    """Vendor, renderer and version strings of the context, for logs and benchmark reports."""
    info = gl_context().info
    return {k: str(info[k]) for k in ("GL_VENDOR", "GL_RENDERER", "GL_VERSION")}

"""The process's headless OpenGL context (moderngl over EGL), created lazily.

A GL context does not survive ``fork``, and a forked child of a process that already made one cannot
make its own either (Mesa's EGL state is copied half-initialised and the call hangs). Worker pools that
render must therefore start their workers with the ``spawn`` method (:func:`worker_context`); a forked
child that asks for a context gets a :class:`RenderError` instead of a hang.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.context
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
    if _CTX is not None and _PID != os.getpid():
        raise RenderError("this process was forked from one that holds an OpenGL context; start rendering "
                          "workers with multiprocessing's 'spawn' method (surftrack.render.worker_context())")
    if _CTX is None:
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


def worker_context() -> multiprocessing.context.BaseContext:
    """The multiprocessing context for worker processes that render: ``spawn``, never ``fork``."""
    return multiprocessing.get_context("spawn")

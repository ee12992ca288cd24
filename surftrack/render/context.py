"""The process's headless OpenGL context (moderngl over EGL), created lazily.

A GL context does not survive ``fork``, and a forked child of a process that already made one cannot
make its own either (Mesa's EGL state is copied half-initialised and the call hangs). Worker pools that
render must therefore start their workers from a process without one (:func:`worker_context`: a fork
server, else ``spawn``); a forked child that asks for a context gets a :class:`RenderError` instead of a
hang.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.context
import os
from collections.abc import Sequence

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
                          "workers with surftrack.render.worker_context() (a fork server or 'spawn', never 'fork')")
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


def worker_context(preload: Sequence[str] = ()) -> multiprocessing.context.BaseContext:
    """The multiprocessing context for worker processes that render, never ``fork``: ``forkserver`` where
    the platform has it (Linux, macOS), else ``spawn``. ``preload``: modules the fork server imports once
    (the process-wide server is started by the first pool or loader; later lists do not change it).

    Why not plain ``spawn``: a spawned worker imports torch and the rest while its parent, blocked writing
    the worker's task (the pickled dataset, larger than a pipe's buffer) into its pipe, cannot start the
    next one, so N workers start one after another (15 training-loader workers: about 90 s on a 16-core
    GPU machine, again every epoch). Workers forked from a server that imported those modules once start
    in well under a second each, side by side; the server holds no GL context, so they can make their own."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        if preload:
            ctx.set_forkserver_preload(list(preload))
        return ctx
    return multiprocessing.get_context("spawn")

"""Headless OpenGL rendering of instrument parts and tissue: RGB, depth, ids, masks, coordinates, normals."""

from surftrack.render.context import RenderError, gl_context, gl_info, worker_context
from surftrack.render.lights import Light, endoscope_light
from surftrack.render.meshdata import corner_normals
from surftrack.render.projection import gl_projection
from surftrack.render.renderer import MODALITIES, Renderer, RenderResult
from surftrack.render.scene import InstrumentInstances, add_instrument

__all__ = ["InstrumentInstances", "Light", "MODALITIES", "RenderError", "RenderResult", "Renderer", "corner_normals",
           "add_instrument", "endoscope_light", "gl_context", "gl_info", "gl_projection",
           "worker_context"]

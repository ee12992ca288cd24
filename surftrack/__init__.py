"""surftrack: 6-DoF pose tracks of the rigid parts of surgical instruments from endoscope video.

Stages, each a sub-package importing only the ones before it:
geometry -> instruments -> render -> synth -> data -> model -> pose -> track -> io.
Units are millimetres and OpenCV camera axes (x right, y down, z forward); poses are model-to-camera.
"""

__version__ = "0.1.0"

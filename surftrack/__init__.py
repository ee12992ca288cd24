"""surftrack: 6-DoF pose tracks of the rigid parts of surgical instruments from endoscope video.

Stages, each a sub-package importing only the ones before it:
geometry -> instruments -> render -> synth -> data -> model -> eval -> pose -> track -> io; the command line
(cli, annotate, demo) sits on top. The one exception is :mod:`surftrack.io.video`, a leaf module that imports
nothing from surftrack, with which synthesis writes its clips.
Units are millimetres and OpenCV camera axes (x right, y down, z forward); poses are model-to-camera.
"""

__version__ = "0.1.0"

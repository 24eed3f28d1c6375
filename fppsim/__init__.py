"""fppsim: a calibrated virtual fringe projection profilometry (FPP) rig.

Renders meshes off-screen (pyrender on OSMesa) under an OpenCV-pinhole camera and projector and
writes single-shot fringe images, phase-shifting stacks and exact height ground truth.
Units: millimetres and radians everywhere.
"""

__version__ = "0.1.0"

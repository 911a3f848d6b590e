"""rtsplat: RT-Splatting reconstruction pipeline (joint reflection/transmission Gaussian surfels).

Importing the package is cheap: heavy stage dependencies (pycolmap, mitsuba, onnxruntime, ...)
are imported inside the stage modules that need them.
"""

__version__ = "0.1.0"

"""contact-viz: a visual debugger for tool-tissue contact detection from stereo depth.

Importing the package is cheap: heavy libraries (rerun, torch, open3d) are imported only by
the modules that need them.
"""

__version__ = "0.1.0"

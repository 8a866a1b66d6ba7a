"""contact-viz: a visual debugger for tool-tissue contact detection from stereo depth.

The public API (docs/api.md) is the names in ``__all__``; everything else may change. Importing the package
is cheap: each name is imported on first use, and heavy libraries (rerun, torch, open3d) only by the modules
that need them.

    import contact_viz as cv
    path = cv.make_synthetic_session("/tmp/s1", frames=30)
    session = cv.open_session(path)
    table = cv.run_session(session)      # distance_m, signal, force_n, label, ... per frame
"""

from importlib import import_module

__version__ = "0.1.0"

# public name -> the module that defines it
_EXPORTS = {
    "open_session": "contact_viz.api",
    "run_frame": "contact_viz.api",
    "run_session": "contact_viz.api",
    "FrameReadout": "contact_viz.api",
    "fit": "contact_viz.api",
    "evaluate": "contact_viz.api",
    "check": "contact_viz.api",
    "make_synthetic_session": "contact_viz.api",
    "log_session": "contact_viz.api",
    "log_frame": "contact_viz.api",
    "default_blueprint": "contact_viz.api",
    "load_model": "contact_viz.model.model_file",
    "save_model": "contact_viz.model.model_file",
    "PatchParams": "contact_viz.params",
    "LabelParams": "contact_viz.params",
    "DebuggerOptions": "contact_viz.viz.options",
    "SynthParams": "contact_viz.synth.params",
}
__all__ = ["__version__", *_EXPORTS]


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'contact_viz' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))

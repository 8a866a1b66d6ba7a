"""The names of the contact model's kinds (their emissions: :mod:`contact_viz.model.emission`), without
NumPy, so that the command line can offer them before importing anything heavy."""

PAPER_KIND = "paper"  # the paper's six-parameter Gaussian HMM (model files without "model_kind" hold it)
MODEL_KINDS = (PAPER_KIND, "flat", "tied", "isotonic", "clip")  # every kind, the paper's first
MONOTONE_KINDS = ("flat", "tied", "isotonic", "clip")  # the posterior never falls as the signal rises
FIT_DEFAULT_KIND = "clip"  # what `contact-viz fit` fits without --model-kind: the transfer study's choice (docs/method.md)

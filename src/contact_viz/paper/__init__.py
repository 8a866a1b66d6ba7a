"""The paper's study protocol as library steps; ``recipes/reproduce_paper.py`` is the script that runs them.

Steps: the split and its sessions (:mod:`.study`, :mod:`.synthetic` for the generated study),
feature extraction (the minimum-distance patch of every frame, cached), optionally the grid search
of N1, N2, tau_tool and tau_patch on the training sessions (:mod:`.grid_search`), the
leave-one-session-out HMM ensemble and the RGB EfficientNet baseline under the same LOSO protocol
(:mod:`.protocol`; ``contact_viz.baseline``, fold checkpoints resume), held-out evaluation of
both, Table 1 and config.json (:mod:`.results`, :mod:`.tables`), and the figures (:mod:`.figures`).

Split file (JSON), session names relative to the sessions folder, test sessions in table order:

    {"train": ["cup_1", "cup_2", "cup_3", "cup_4", "cup_5", "cup_6"],
     "test": [{"session": "cup_7",    "category": "same phantom and task"},
              {"session": "kidney_1", "category": "new phantom"},
              {"session": "liver_1",  "category": "new phantom"},
              {"session": "glove_1",  "category": "new phantom and task"}]}

"train" needs at least two sessions (leave-one-session-out); "category" is one of
:data:`.study.CATEGORIES` (:func:`.study.read_split` reads and checks the file).

Without sessions and split the synthetic study of scripts/demo.sh is generated and run: six
``cup`` training sessions (seeds 0-5) and one test session each on ``cup``, ``kidney``, ``liver``
and ``glove`` (seeds 100-103); sessions already there with the same generator settings are reused.

Configurations (:mod:`.profiles`): the default is the paper's (EfficientNet-B3, 234 px crops, 10
epochs; with an efficientnet-pytorch ImageNet state dict as weights, without it the net trains
from scratch and every output says so; about a day of CPU time on the paper's data). ``quick``
runs a tiny baseline (EfficientNet-B0 at a quarter of its width and depth, 64 px crops, 2 epochs)
on a smaller synthetic study; ``tiny`` is smaller still (for tests). Neither is the paper's
configuration, and table1.*, the timelines figure and config.json say so.

Outputs, each written atomically:
    table1.md, table1.tex, table1.csv  Table 1: both methods side by side, per session and Macro
                                       (the CSV has one row per session and method)
    timelines.png / .pdf               contact probabilities of both methods against ground truth
    pipeline.png / .pdf                (a) tool mask, (b) layers over depth, (c) the selected patch
    per_frame_hmm.csv, per_frame_rgb.csv  every test frame: posterior, decision, label
    config.json                        the resolved configuration, thresholds, versions, timings
    model.json                         the HMM ensemble (contact-viz evaluate / view can use it)
    grid_search.json                   with the grid search: every grid point's out-of-fold scores
    baseline/<key>/                    the baseline's fold checkpoints and ensemble.json
"""

"""The debugger shows why the posterior moves (issue 34): each instrument's evidence for contact, the emission
log-likelihood ratio of its signal, as a series beside the posterior (series/contact_evidence), read back from the
.rrd and compared with the model's own log_likelihood_ratio of the signals computed independently of the debugger.
With the paper's kind a tool at 0.1 mm reads as evidence *against* contact there; with the flat kind it does not."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

rr = pytest.importorskip("rerun")

from test_viewer import N_FRAMES, Recording, expected_patches, run, write_session  # noqa: E402
from test_viewer_instruments import ABSENT, BAD, expected, view, write_two_instrument_session  # noqa: E402

from contact_viz.model.hmm import HMMParams, LosoEnsemble  # noqa: E402
from contact_viz.model.model_file import ContactModel  # noqa: E402
from contact_viz.params import LabelParams, PatchParams  # noqa: E402
from contact_viz.viz import rerun_log  # noqa: E402
from contact_viz.viz.debugger import DebuggerOptions  # noqa: E402
from contact_viz.viz.entities import tool_entity  # noqa: E402
from contact_viz.viz.style import instrument_style  # noqa: E402

CAP = 4.0  # the signal at |d| <= 0.1 mm


def model_of(kind: str) -> ContactModel:
    """An ensemble of ``kind`` fitted on three random sequences: contact reads 3.0 dec (1 mm) with a small
    spread, no contact 2.0 dec (10 mm) with a larger one (the paper's kind then calls 0.1 mm unlikely contact)."""
    rng = np.random.default_rng(5)
    signals, labels = [], []
    for _ in range(3):
        y = (np.sin(np.arange(300) / 15.0) > 0.3).astype(np.int64)
        signals.append(rng.normal(np.where(y == 1, 3.0, 2.0), np.where(y == 1, 0.12, 0.35)))
        labels.append(y)
    ensemble = LosoEnsemble(HMMParams(model_kind=kind)).fit(signals, labels)
    return ContactModel(ensemble=ensemble, patch_params=PatchParams(), label_params=LabelParams(),
                        training_sessions=())


@pytest.fixture(scope="module")
def one_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("evidence") / "one"
    write_session(root)
    return root


@pytest.mark.parametrize("kind", ["paper", "flat"])
def test_the_evidence_series_is_the_models_log_likelihood_ratio(one_dir, tmp_path, kind):
    model = model_of(kind)
    session, _, rec = run(one_dir, tmp_path / f"{kind}.rrd", DebuggerOptions(points=False, images="jpeg"),
                          model=model)
    indices = list(range(N_FRAMES))
    patches = expected_patches(session, indices)
    signal = np.array([patches[i][1].signal for i in indices])
    want = model.ensemble.log_likelihood_ratio(signal)
    got = rec.scalars(rerun_log.ENTITY_SERIES_EVIDENCE)
    assert sorted(got) == indices
    np.testing.assert_allclose([got[i] for i in indices], want, rtol=1e-12, atol=1e-12)
    # beside the posterior, from the same filter: the posterior moves the way the evidence says
    posterior = rec.scalars(rerun_log.ENTITY_SERIES_POSTERIOR)
    np.testing.assert_allclose([posterior[i] for i in indices], model.ensemble.predict_proba(signal), atol=1e-15)
    at_cap = [i for i in indices if signal[i] == CAP]
    assert at_cap, "the session's tool reaches 0.1 mm"
    if kind == "paper":  # "this frame reads 0.1 mm but the model calls it unlikely"
        assert all(got[i] < 0 for i in at_cap)
    else:
        assert all(got[i] > 5 for i in at_cap)
    style = rec.static[(rerun_log.ENTITY_SERIES_EVIDENCE, "SeriesLines:colors")].as_py()
    r, g, b, a = instrument_style(1).line
    assert style == [(r << 24) | (g << 16) | (b << 8) | a]
    texts = rec.values(rerun_log.ENTITY_CONTACT, "TextDocument:text")
    assert f"evidence {want[at_cap[0]]:+.1f}" in texts[at_cap[0]].as_py()[0]


def test_without_a_model_there_is_no_evidence_series(one_dir, tmp_path):
    _, _, rec = run(one_dir, tmp_path / "none.rrd", DebuggerOptions(points=False, images="jpeg"))
    assert rec.scalars(rerun_log.ENTITY_SERIES_EVIDENCE) == {}


def test_each_instrument_has_its_evidence_in_its_colour_broken_where_absent(tmp_path_factory):
    root = tmp_path_factory.mktemp("evidence") / "two"
    write_two_instrument_session(root)
    model = model_of("flat")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        session, _, rec = view(root, tmp_path_factory.mktemp("rrd") / "two.rrd", model=model, images="jpeg",
                               points=False)
    want = expected(session)
    for tool in (1, 2):
        entity = rerun_log.ENTITY_SERIES_EVIDENCE if tool == 1 else tool_entity(rerun_log.ENTITY_SERIES_EVIDENCE, 2)
        got = rec.scalars(entity)
        here = [i for i in range(N_FRAMES) if tool in want[i]]
        signal = np.array([want[i][tool].signal for i in here])
        np.testing.assert_allclose([got[i] for i in here], model.ensemble.log_likelihood_ratio(signal),
                                   rtol=1e-12, atol=1e-12)
        gone = [i for i in range(N_FRAMES) if i not in here]
        assert gone and all(np.isnan(got[i]) for i in gone if i in got)  # a break where it is absent
        assert BAD in gone and BAD in got  # the bad frame breaks every line
        if tool == 2:
            assert ABSENT[0] in got and np.isnan(got[ABSENT[0]])
        colours = rec.static[(entity, "SeriesLines:colors")].as_py()
        r, g, b, a = instrument_style(tool).line
        assert colours == [(r << 24) | (g << 16) | (b << 8) | a]
        names = rec.static[(entity, "SeriesLines:names")].as_py()
        assert names == [f"evidence (log LR), instrument {tool}"]


def test_the_layout_has_the_evidence_plot_with_a_model_only():
    def views(blueprint) -> list[str]:
        out = []

        def walk(node):
            origin = getattr(node, "origin", None)
            if origin is not None:
                out.append(str(origin))
            for child in getattr(node, "contents", None) or []:
                if not isinstance(child, str):
                    walk(child)

        walk(blueprint.root_container)
        return out

    with_model = rerun_log.default_blueprint(with_model=True)
    without = rerun_log.default_blueprint(with_model=False)
    assert rerun_log.ENTITY_SERIES_EVIDENCE in views(with_model)
    assert rerun_log.ENTITY_SERIES_EVIDENCE not in views(without)

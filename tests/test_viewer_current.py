"""Every layer of a recording is current or absent: read back frame by frame, what an entity holds at frame t was
logged at t (or cleared at t), never left over from an earlier frame (unless it is static: cameras, classes).

The viewer ignores rr.Clear on encoded (JPEG) images (rerun-io/rerun#12793), so for those only an image logged at
t counts (the debugger logs an empty one where there is none). Sessions: two instruments, a mask failure injected
on a few frames (the checks fire and the evidence picture shows), an unreadable depth file, a missing right image,
instrument 2 absent on some frames; logged with JPEG images and with video."""

from __future__ import annotations

import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

rr = pytest.importorskip("rerun")

from rerun.chunk import RrdReader  # noqa: E402

from contact_viz.io.session import open_session  # noqa: E402
from contact_viz.synth import SynthParams, generate_session  # noqa: E402
from contact_viz.synth.faults import inject_fault  # noqa: E402
from contact_viz.viz import rerun_log  # noqa: E402
from contact_viz.viz.debugger import DebuggerOptions, run_debugger  # noqa: E402

FRAMES = 24
FAULTY = (6, 7, 8)  # frames whose mask bleeds onto the tissue (checks fire, with evidence)
BAD = 14  # a frame whose depth file cannot be read
NO_RIGHT = 17  # a frame without its right image
# per-frame entities that keep nothing from an earlier frame (series, logs and static data are not these)
SKIPPED_ROOTS = ("series/", "log", "config")


@pytest.fixture(scope="module")
def session_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("current")
    clean = generate_session(root / "clean", SynthParams(phantom="cup", seed=3, frames=FRAMES, width=320,
                                                         height=180, tools=2))
    faulty = root / "faulty"
    inject_fault(clean, faulty, "mask_bleed", FAULTY, severity=9.0, seed=1)
    (faulty / "depth" / f"{BAD:06d}.npy").unlink()  # (a hard link: replaced, not written through)
    (faulty / "depth" / f"{BAD:06d}.npy").write_bytes(b"not a numpy file")
    (faulty / "right" / f"{NO_RIGHT:06d}.jpg").unlink()
    return faulty


class Timeline:
    """Per entity: the frames at which it got data (per component) or a Clear (also of an ancestor, recursive)."""

    def __init__(self, path: Path) -> None:
        self.data: dict[str, dict[str, set[int]]] = defaultdict(lambda: defaultdict(set))
        self.clears: dict[str, list[tuple[int, bool]]] = defaultdict(list)  # entity -> (frame, recursive)
        self.frames: set[int] = set()
        for chunk in RrdReader(path).stream():
            if chunk.is_static:
                continue
            batch = chunk.to_record_batch()
            entity = chunk.entity_path.strip("/")
            frames = batch.column("frame").to_pylist()
            self.frames.update(frames)
            for name in batch.schema.names:
                if ":" not in name:
                    continue
                column = batch.column(name)
                for i, frame in enumerate(frames):
                    if not column[i].is_valid:
                        continue
                    if name == "Clear:is_recursive":
                        self.clears[entity].append((frame, bool(column[i].as_py()[0])))
                    else:
                        self.data[entity][name.split(":")[0]].add(frame)

    def cleared_between(self, entity: str, after: int, upto: int) -> bool:
        """A Clear of ``entity`` (or a recursive one of an ancestor) at a frame in (after, upto]."""
        parts = entity.split("/")
        for k in range(len(parts), 0, -1):
            ancestor = "/".join(parts[:k])
            for f, recursive in self.clears.get(ancestor, []):
                if after < f <= upto and (recursive or ancestor == entity):
                    return True
        return False

    def stale(self, entity: str) -> list[tuple[int, int]]:
        """(frame, the earlier frame whose data it would show) wherever ``entity`` shows an earlier frame's data."""
        out = []
        archetypes = self.data[entity]
        encoded = "EncodedImage" in archetypes
        logged = sorted(set().union(*archetypes.values()))
        for frame in sorted(self.frames):
            before = [f for f in logged if f <= frame]
            if not before or before[-1] == frame:
                continue  # nothing yet, or data of this frame
            if not encoded and self.cleared_between(entity, before[-1], frame):
                continue  # cleared since (honoured for everything but encoded images)
            out.append((frame, before[-1]))
        return out


def view(session_dir: Path, out: Path, **options) -> tuple[object, Timeline]:
    rr.set_strict_mode(True)
    session = open_session(session_dir)
    opened = rerun_log.open_recording(save=out, blueprint=rerun_log.default_blueprint())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the bad frame's and the missing image's warnings
        summary = run_debugger(session, opened.rec, DebuggerOptions(**options))
    opened.close()
    return summary, Timeline(out)


@pytest.mark.parametrize("images", ["jpeg", "video"])
def test_no_entity_shows_an_earlier_frame(session_dir, tmp_path, images):
    summary, timeline = view(session_dir, tmp_path / f"{images}.rrd", images=images)
    assert summary.bad_frames == 1 and summary.frames == FRAMES
    fired = {code for code, n in summary.diagnostic_counts.items() if n}
    assert fired, "the injected mask bleed makes checks fire"
    evidence = timeline.data[rerun_log.ENTITY_EVIDENCE_RESIDUAL]
    assert any(f in evidence["EncodedImage"] for f in FAULTY)  # the evidence picture was shown
    entities = [e for e in timeline.data if not e.startswith(SKIPPED_ROOTS)]
    assert rerun_log.ENTITY_LEFT_IMAGE in entities and rerun_log.ENTITY_EVIDENCE_RESIDUAL in entities
    stale = {e: timeline.stale(e) for e in entities}
    assert {e: s for e, s in stale.items() if s} == {}
    # the images: the frame's own, or (unreadable) a stand-in of that frame, on every frame
    for side in (rerun_log.ENTITY_LEFT_IMAGE, rerun_log.ENTITY_RIGHT_IMAGE):
        archetype = "VideoStream" if images == "video" else "EncodedImage"
        assert timeline.data[side][archetype] == set(range(FRAMES)), side


def test_the_check_can_fail(tmp_path):
    """A Timeline in which an encoded image is only cleared (as the viewer would keep showing it) is stale."""
    path = tmp_path / "stale.rrd"
    rec = rr.RecordingStream("contact_viz_test")
    rec.save(path)
    jpeg = rerun_log.EMPTY_PNG
    for frame in range(3):
        rec.set_time("frame", sequence=frame)
        if frame == 0:
            rec.log("world/camera/left/evidence/residual", rr.EncodedImage(contents=jpeg, media_type="image/png"))
            rec.log("world/camera/left/layers", rr.SegmentationImage(np.zeros((4, 4), np.uint8)))
        else:
            rec.log("world/camera/left/evidence", rr.Clear(recursive=True))
            rec.log("world/camera/left/layers", rr.Clear(recursive=False))
        rec.log("series/distance", rr.Scalars(1.0))
    rec.flush()
    del rec
    timeline = Timeline(path)
    assert timeline.stale("world/camera/left/evidence/residual") == [(1, 0), (2, 0)]
    assert timeline.stale("world/camera/left/layers") == []  # cleared at 1, and so still at 2

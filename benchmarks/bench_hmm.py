"""Benchmark: the HMM's causal forward filter, batch (forward_filter) and streaming (StreamingFilter).

Prints the median wall-clock time of forward_filter over a 100,000-frame signal (about an hour of
video at 30 fps) and of StreamingFilter.update per frame, over --repeats runs each. The target the
test suite used to assert inline: forward_filter on 100,000 frames in under 1 s.
Run: .venv/bin/python benchmarks/bench_hmm.py [--frames 100000 --repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from contact_viz.model.hmm import StreamingFilter, SupervisedGaussianHMM, forward_filter

TRANSMAT = np.array([[0.95, 0.05], [0.1, 0.9]])  # P(s_t = j | s_t-1 = i), as in tests/test_hmm.py
MEANS, VARS, STARTPROB = [0.5, 2.5], [0.3, 0.15], [2 / 3, 1 / 3]  # dec, dec^2, - (as in tests/test_hmm.py)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100_000, help="signal length, frames")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs of each filter")
    args = parser.parse_args()
    rng = np.random.default_rng(6)
    states = np.zeros(args.frames, dtype=np.int8)  # a Markov chain of TRANSMAT
    for t in range(1, args.frames):
        states[t] = rng.random() < TRANSMAT[states[t - 1], 1]
    signal = rng.normal(np.take(MEANS, states), np.sqrt(np.take(VARS, states)))
    signal[rng.random(args.frames) < 0.05] = np.nan  # frames without a patch

    batch = []
    for _ in range(args.repeats):
        start = time.perf_counter()
        forward_filter(signal, MEANS, VARS, TRANSMAT, STARTPROB)
        batch.append(time.perf_counter() - start)

    model = SupervisedGaussianHMM().fit([signal], [states])
    stream = []
    frames = signal[: min(args.frames, 20_000)]
    for _ in range(args.repeats):
        filt = StreamingFilter(model)
        start = time.perf_counter()
        for x in frames:
            filt.update(x)
        stream.append((time.perf_counter() - start) / len(frames))

    print(f"forward_filter, {args.frames} frames: median {statistics.median(batch):.3f} s "
          f"(min {min(batch):.3f}, max {max(batch):.3f}; target < 1 s)")
    print(f"StreamingFilter.update, one model: median {1e6 * statistics.median(stream):.1f} us per frame "
          f"(over {len(frames)} frames)")


if __name__ == "__main__":
    main()

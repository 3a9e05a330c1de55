"""The cost of filming a trial's final evaluation episode, against the trial's own time.

Runs quickstart trials (studies/quickstart.yaml, config 0, seed 0) with the spec's video
setting (the last evaluation) and a ``record`` callback, as a sweep worker does, and prints
per method the trial's wall time, the time spent filming and encoding the video
(``TrialResult.video_seconds``, measured inside the trial: frame collection, rendering for
the state oracle, the latent reward of every frame, layout and encoding), its share of the
trial, and the video's size. Target: under 2% of a quickstart trial's time, a few hundred
kB per video. The curve itself is checked equal to a trial without filming in
tests/test_video.py.

Measured on the 2-core development machine (nice 10, other jobs running), quickstart
config 0, 4000 steps, MP4 (imageio-ffmpeg 0.8.1):

    method        trial s  video s   share     kB  file
    pixel           198.8    0.203   0.10%   11.7  episode-step4000.mp4
    state            35.6    0.206   0.58%   11.2  episode-step4000.mp4

The cost is fixed per video (~0.2 s: 51 frames, their latent rewards, one ffmpeg run),
so it is 0.1% of an image trial; the state oracle's trial is the cheapest there is and
the video still costs under 1% of it. Target met (< 2%, a few hundred kB).

Run: ``.venv/bin/python benchmarks/bench_video.py [--methods pixel,state] [--steps 4000]``
(``--steps`` shortens the trials: the video's cost stays, its share grows).
"""

from __future__ import annotations

import argparse
import dataclasses

import agent
from sweeper.plan._entries import build_plan
from sweeper.spec._models import load_spec


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spec", default="studies/quickstart.yaml")
    parser.add_argument("--methods", default="pixel,state")
    parser.add_argument("--steps", type=int, default=None, help="default: the spec's budget")
    args = parser.parse_args()
    spec = load_spec(args.spec)
    plan = build_plan(spec)
    print(f"{'method':<12} {'trial s':>8} {'video s':>8} {'share':>7} {'kB':>6}  file")
    for method in args.methods.split(","):
        entry = next(e for e in plan.entries if e.method == method and e.config_id == 0)
        config = dataclasses.replace(entry.trial_config, checkpoint_dir=None)
        if args.steps is not None:
            config = dataclasses.replace(config, total_steps=args.steps, video_steps=(args.steps,))
        files: dict[str, bytes] = {}
        result = agent.train(config, record=files.__setitem__)
        (name, data), share = files.popitem(), result.video_seconds / result.seconds
        print(
            f"{method:<12} {result.seconds:8.1f} {result.video_seconds:8.3f} {share:7.2%} "
            f"{len(data) / 1000:6.1f}  {name}",
            flush=True,
        )


if __name__ == "__main__":
    main()

"""What the learned reward encoders of a study's trials learned, for trials recorded before
trials kept their fit (the user attr ``encoder_fit``).

    .venv/bin/python benchmarks/study_fits.py SPEC [--storage URL] [--keys vae/0/0,...]

Each learned-encoder trial's fit is done again from its plan entry, as the trial did it (the
same random-policy frames, options and seed: ``agent.trial.build_encoder``), and printed
beside the trial's recorded AUC and reward scale: active latent dimensions
(``encoders.vae.active_dims``), the last epoch's KL and reconstruction error. On the kind of
CPU the trial ran on the fit is the trial's own, float for float; elsewhere it rounds
differently, which moves no count of active dimensions that is not on the edge. One thread;
a fit on 5,000 84x84 frames for 30 epochs takes minutes.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main() -> None:
    import torch

    from agent.trial import build_encoder
    from encoders import encoder_names
    from encoders.registry import encoder_class
    from sweeper.plan._entries import build_plan
    from sweeper.results._frame import load_study_frame, trial_rows
    from sweeper.spec._models import load_spec
    from sweeper.storage import open_for_reading, stored_files

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("spec")
    parser.add_argument("--storage", help="the study's database (default: the spec's)")
    parser.add_argument("--keys", help="comma-separated plan keys (default: every learned one)")
    args = parser.parse_args()

    spec = load_spec(args.spec)
    if args.storage:
        spec = spec.with_overrides(storage=args.storage)
    torch.set_num_threads(1)
    with open_for_reading(spec) as store:
        plan = build_plan(stored_files(spec, store))
    learned = {
        entry.key
        for entry in plan.entries
        if entry.trial_config.method in encoder_names()
        and encoder_class(entry.trial_config.method).needs_fit
    }
    keys = args.keys.split(",") if args.keys else sorted(learned)
    unknown = [k for k in keys if k not in learned]
    if unknown:
        sys.exit(f"study_fits: not a learned-encoder key of {spec.study!r}: {', '.join(unknown)}")
    recorded = trial_rows(load_study_frame(spec.storage_url, spec.study))
    recorded = recorded[recorded["counted"]].set_index("key")
    entries = {e.key: e for e in plan.entries}
    print(f"study {spec.study!r}: {len(keys)} learned-encoder trials, fits done again here")
    print(f"{'key':<12} {'active':>9} {'KL':>7} {'recon':>9} {'AUC':>6} {'scale':>7} {'fit s':>6}")
    for key in keys:
        config = entries[key].trial_config
        start = time.perf_counter()
        _, fit = build_encoder(config, config.image_size, torch.device("cpu"))
        row = recorded.loc[key] if key in recorded.index else None
        auc = f"{row['auc']:.3f}" if row is not None and row["state"] == "COMPLETE" else "–"
        scale = f"{row['reward_scale']:.1f}" if row is not None and row["reward_scale"] > 0 else "–"
        active = f"{fit['active_dims']}/{fit['latent_dim']}"
        print(
            f"{key:<12} {active:>9} {fit['kl']:>7.2f} {fit['recon']:>9.1f} {auc:>6} {scale:>7} "
            f"{time.perf_counter() - start:>6.0f}",
            flush=True,
        )


if __name__ == "__main__":
    main()

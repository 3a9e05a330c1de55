"""Encoder cost on this machine: encode throughput and VAE/CVAE training time per epoch.

    .venv/bin/python benchmarks/bench_encoders.py [--threads 1] [--fit-images 500]

Prints one line per (encoder, image size). VGG runs on random weights (same cost as the
ImageNet ones) at its default 224 input and at 84.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from encoders import make_encoder
from encoders.vgg import vgg16_features


def images_per_second(encoder, images: np.ndarray, repeats: int = 3) -> float:
    encoder.encode(images[:2])  # warm up
    start = time.perf_counter()
    for _ in range(repeats):
        encoder.encode(images)
    return repeats * len(images) / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--batch", type=int, default=64, help="images per encode call")
    parser.add_argument("--fit-images", type=int, default=500)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        weights = Path(tmp) / "vgg16.pth"
        torch.save({f"features.{k}": v for k, v in vgg16_features().state_dict().items()}, weights)
        print(f"torch threads {args.threads}, batch {args.batch}")
        for size in (48, 84):
            x = rng.integers(0, 256, (args.batch, size, size, 3), dtype=np.uint8)
            fit_x = rng.integers(0, 256, (args.fit_images, size, size, 3), dtype=np.uint8)
            for name, options in [
                ("pixel", {}),
                ("linear", {}),
                ("conv", {}),
                ("vae", {"epochs": 1}),
                ("cvae", {"epochs": 1}),
                ("vgg", {"weights_path": str(weights), "input_size": 84}),
                ("vgg", {"weights_path": str(weights)}),
            ]:
                encoder = make_encoder(name, (size, size, 3), seed=0, **options)
                fit = ""
                if encoder.needs_fit:
                    report = encoder.fit(fit_x, progress=False)
                    fit = f", fit {report.seconds:.2f} s/epoch on {args.fit_images} images"
                n = x if name != "vgg" else x[:8]
                label = name + (f"@{encoder.input_size}" if name == "vgg" else "")
                print(
                    f"{size}x{size} {label:8s} dim {encoder.dim:6d}: "
                    f"{images_per_second(encoder, n, 1 if name == 'vgg' else 3):9.1f} images/s"
                    f"{fit}"
                )


if __name__ == "__main__":
    main()

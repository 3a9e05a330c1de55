"""PIXEL: the image itself, flattened and scaled to [0, 1]."""

from __future__ import annotations

import numpy as np

from encoders.base import RewardEncoder


class PixelEncoder(RewardEncoder):
    name = "pixel"

    @property
    def dim(self) -> int:
        h, w, c = self.image_shape
        return h * w * c

    def encode(self, images: np.ndarray) -> np.ndarray:
        images = self.check_images(images)
        return images.reshape(len(images), -1).astype(np.float32) / np.float32(255.0)

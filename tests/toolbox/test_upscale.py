"""toolbox.colour.upscale: a small picture enlarged by an integer factor, each pixel a square block."""
from __future__ import annotations

import numpy as np
import pytest

from toolbox.colour import upscale


@pytest.mark.parametrize("shape", [(144, 176, 3), (37, 91, 3), (5, 7, 3), (200, 3, 3), (144, 176), (600, 800, 3)])
def test_each_pixel_becomes_a_block_of_the_factor(shape):
    image = np.random.default_rng(1).integers(0, 256, shape, dtype=np.uint8)
    factor = max(1, int(np.ceil(480 / max(shape[:2]))))
    np.testing.assert_array_equal(upscale(image), np.repeat(np.repeat(image, factor, axis=0), factor, axis=1))

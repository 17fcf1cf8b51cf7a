import io

import numpy as np
import pytest
from PIL import Image

from simulator.frame import encode_png


@pytest.mark.parametrize("shape", [(1, 1, 3), (1, 7, 3), (5, 1, 3), (37, 53, 3)])
def test_png_decodes_to_the_same_pixels(shape):
    rng = np.random.default_rng(sum(shape))
    for img in (rng.integers(0, 256, shape, dtype=np.uint8),
                np.cumsum(rng.integers(0, 3, shape), axis=0).astype(np.uint8)):  # smooth, wrapping
        decoded = Image.open(io.BytesIO(encode_png(img)))
        decoded.load()
        assert decoded.mode == "RGB" and not decoded.info
        np.testing.assert_array_equal(np.asarray(decoded), img)


def test_png_rejects_other_shapes():
    with pytest.raises(ValueError, match="H, W, 3"):
        encode_png(np.zeros((4, 4), np.uint8))

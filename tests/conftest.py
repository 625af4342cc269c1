"""Shared fixtures: a tiny synthetic sensor with known invalid pixels."""

import numpy as np
import pytest

HEIGHT, WIDTH = 6, 8
"""Sensor rows and columns of the synthetic views."""

INVALID_PIXELS = ((0, 0), (1, 2), (2, 5), (5, 7))
"""(row, column) of the pixels made invalid: a NaN, all zeros, z < 0, z == 0."""


@pytest.fixture
def synthetic_view() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """xyz (HEIGHT, WIDTH, 3) metres, intensity (HEIGHT, WIDTH) and the expected valid mask.

    A tilted plane 0.5-0.8 m in front of the camera with a millimetre texture,
    intensities 10..~1000; the pixels of :data:`INVALID_PIXELS` are invalid.
    """
    rows, cols = np.mgrid[0:HEIGHT, 0:WIDTH]
    z = 0.5 + 0.01 * rows + 0.03 * cols + 0.001 * np.sin(rows * cols)
    xyz = np.stack([(cols - WIDTH / 2) * 0.01 * z, (rows - HEIGHT / 2) * 0.01 * z, z], axis=-1)
    intensity = 10.0 + 30.0 * rows * cols + 0.37 * cols
    valid = np.ones((HEIGHT, WIDTH), dtype=bool)
    for pixel, bad_xyz in zip(INVALID_PIXELS, ([np.nan, 0.1, 0.5], [0, 0, 0], [0.1, 0.1, -0.5], [0.2, 0.1, 0.0])):
        xyz[pixel] = bad_xyz
        valid[pixel] = False
    return xyz, intensity, valid


@pytest.fixture
def sensor() -> dict[str, int]:
    """``{"width", "height"}`` of the synthetic views, as keyword arguments of the readers."""
    return {"width": WIDTH, "height": HEIGHT}

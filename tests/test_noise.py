"""The intensity noise model (surffin.method.noise) and its use in the variability feature."""

import numpy as np
import pytest
import xarray as xr

from surffin.method.features import local_std, variability
from surffin.method.noise import MIN_SAMPLES, NOISE_EDGES, NoiseStatistics, relative_noise

SHAPE = (200, 300)


def _wall(rng, sigma_of, gain_pattern=None):
    """A smooth wall image (intensity ramp over 6 octaves), its noisy version and the per-pixel sigma."""
    yy, xx = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]]
    smooth = 20.0 * 2.0 ** (6.0 * xx / SHAPE[1]) * (1.0 + 0.05 * yy / SHAPE[0])
    gain = np.ones(SHAPE) if gain_pattern is None else gain_pattern
    sigma = sigma_of(smooth)
    return smooth * gain * (1.0 + sigma * rng.standard_normal(SHAPE)), smooth * gain, sigma


def _shot(level):
    return np.sqrt(0.01**2 + 0.2 / level)  # 10 % at 20 counts, 1.2 % at 1280


def test_noise_statistics_recover_a_known_noise_curve():
    rng = np.random.default_rng(0)
    stats = NoiseStatistics()
    for _ in range(4):
        intensity, expected, _ = _wall(rng, _shot)
        stats.add(intensity, intensity / expected, np.ones(SHAPE, bool))
    model = stats.dataset()
    measured = np.sqrt(model["noise_variance"].values)
    level = model["noise_intensity"].values
    ok = np.isfinite(measured)
    # 6 octaves of intensity, 4 bins each, 4 views of 60000 pixels: ~2500 samples per bin, 1.5 % in sigma
    assert ok.sum() >= 20 and (model["noise_samples"].values[ok] >= MIN_SAMPLES).all()
    np.testing.assert_allclose(measured[ok], _shot(level[ok]), rtol=0.06)
    # bins with too few samples are NaN, never a number
    assert np.isnan(measured[model["noise_samples"].values < MIN_SAMPLES]).all()


def test_flat_fielding_takes_out_a_fixed_gain_pattern():
    """Pixel-to-pixel gain differences are no noise: divided out by the calibration, they do not count."""
    rng = np.random.default_rng(1)
    pattern = 1.0 + 0.05 * np.random.default_rng(2).standard_normal(SHAPE)
    flat, raw = NoiseStatistics(), NoiseStatistics()
    intensity, expected, _ = _wall(rng, lambda level: np.full_like(level, 0.01), pattern)
    flat.add(intensity, intensity / expected, np.ones(SHAPE, bool))
    raw.add(intensity, intensity, np.ones(SHAPE, bool))
    assert np.nanmedian(np.sqrt(flat.dataset()["noise_variance"].values)) == pytest.approx(0.01, rel=0.05)
    assert np.nanmedian(np.sqrt(raw.dataset()["noise_variance"].values)) > 0.04


def test_noise_statistics_skip_invalid_neighbourhoods():
    rng = np.random.default_rng(3)
    intensity, expected, _ = _wall(rng, _shot)
    valid = np.ones(SHAPE, bool)
    valid[:, ::2] = False  # no pixel has a full valid 3 x 3 neighbourhood
    stats = NoiseStatistics().add(intensity, intensity / expected, valid)
    assert stats.dataset()["noise_samples"].sum() == 0
    with pytest.raises(ValueError, match="no intensity bin"):
        relative_noise(xr.DataArray(np.ones(3)), stats.dataset())


def test_relative_noise_interpolates_in_log_intensity():
    stats = NoiseStatistics()
    first = 40
    stats.count[first : first + 3] = MIN_SAMPLES
    stats.total[first : first + 3] = MIN_SAMPLES * np.array([0.04, 0.01, 0.0025])
    model = stats.dataset()
    centres = model["noise_intensity"].values[first : first + 3]
    between = np.sqrt(centres[0] * centres[1])  # half way in log intensity
    counts = xr.DataArray([centres[0], between, centres[2], centres[2] * 100, centres[0] / 100, 0.0, np.nan])
    out = relative_noise(counts, model).values
    np.testing.assert_allclose(out[:5], [0.2, 0.15, 0.05, 0.05, 0.2], rtol=1e-6)
    assert np.isnan(out[5:]).all() and out.dtype == np.float32
    assert NOISE_EDGES[first] < centres[0] < NOISE_EDGES[first + 1]


def test_local_std_without_the_noise_measures_the_texture():
    rng = np.random.default_rng(4)
    texture, noise = 0.02, rng.uniform(0.01, 0.05, SHAPE)  # noise sigma varies over the image
    image = 1.0 + texture * rng.standard_normal(SHAPE) + noise * rng.standard_normal(SHAPE)
    da = xr.DataArray(image, dims=("y", "x"))
    plain = local_std(da, 7).values
    corrected = local_std(da, 7, noise_variance=xr.DataArray(noise**2, dims=("y", "x"))).values
    # the plain local std holds the noise too: sqrt(texture^2 + mean noise^2)
    assert np.median(plain) == pytest.approx(np.sqrt(texture**2 + np.mean(noise**2)), rel=0.03)
    # corrected: the texture alone (the median of a 49-pixel estimate sits slightly low)
    assert np.median(corrected) == pytest.approx(texture, rel=0.1)
    # pure noise: nothing left but the estimate's scatter, clipped at zero
    pure = xr.DataArray(1.0 + noise * rng.standard_normal(SHAPE), dims=("y", "x"))
    left = local_std(pure, 7, noise_variance=xr.DataArray(noise**2, dims=("y", "x"))).values
    assert np.median(left) < 0.3 * np.median(noise) and (left >= 0).all()


def test_variability_takes_out_the_relative_noise():
    rng = np.random.default_rng(5)
    aoi = xr.DataArray(
        np.full(SHAPE, 0.5), dims=("y", "x"), coords={"y": np.arange(SHAPE[0]), "x": np.arange(SHAPE[1])}
    )
    relative = aoi * 0 + 0.03
    surface = 0.8 * (1.0 + 0.02 * rng.standard_normal(SHAPE))
    observed = aoi.copy(data=surface * (1.0 + 0.03 * rng.standard_normal(SHAPE)) * np.cos(0.5))
    plain = variability(observed, aoi).values
    corrected = variability(observed, aoi, relative_noise=relative).values
    assert np.median(plain) == pytest.approx(0.8 * np.hypot(0.02, 0.03), rel=0.05)
    assert np.median(corrected) == pytest.approx(0.8 * 0.02, rel=0.1)
    with pytest.raises(ValueError, match="same \\(y, x\\) grid"):
        variability(observed, aoi, relative_noise=relative.isel(x=slice(1, None)))

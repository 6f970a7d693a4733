"""`banded_downsample`: a large one-lobe level downsampled in bands of rows is bit-identical to
`em_downsample` in one piece (every texel meets the same EM chunk), odd sizes included."""

import jax
import numpy as np
import pytest

from fitting.em import em_downsample
from fitting.pyramid import banded_downsample
from fitting.synth import synth_maps


@pytest.mark.parametrize("shape", [(70, 32), (67, 31)])
def test_bands_equal_one_piece(shape):
    level = synth_maps(jax.random.key(4), shape)   # one lobe: a fit's level 0
    # chunks of 256 texels, bands of 256 output texels: 16 output columns -> bands of 16 rows
    one_out, one_info = em_downsample(level, chunk=256)
    out, info = banded_downsample(level, chunk=256, band_texels=256)
    assert out.weight.shape == one_out.weight.shape == (-(-shape[0] // 2), -(-shape[1] // 2))
    for got, ref in zip(jax.tree.leaves((out, info)), jax.tree.leaves((one_out, one_info)), strict=True):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(ref))


def test_small_or_two_lobe_levels_in_one_piece():
    level = synth_maps(jax.random.key(4), (20, 32))  # 10 output rows < 2 bands of 16
    out, _ = banded_downsample(level, chunk=256, band_texels=256)
    np.testing.assert_array_equal(np.asarray(out.rho_d), np.asarray(em_downsample(level, chunk=256)[0].rho_d))

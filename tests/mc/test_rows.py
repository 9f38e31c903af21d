"""``mc/rows.py``: a chunk's results as table rows."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from stereopose_mc.mc import rows as mc_rows


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 40), st.integers(0, 130), st.floats(0.0, 1.0), st.integers(0, 2**32 - 1))
def test_row_means_are_each_rows_own_whatever_the_batch(rows, width, nan_share, seed):
    """``rows.row_nanmean``: each row's mean of its non-NaN values, bit for bit that of the row reduced alone
    (``row[~isnan(row)].mean()``), and the same bits when fewer rows share the array (the rows without NaN are
    reduced together: numpy's pairwise sum along the contiguous axis, per row)."""
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((rows, width)) * 10.0 ** rng.uniform(-8, 8, (rows, width))
    a[rng.random((rows, width)) < nan_share * rng.random((rows, 1))] = np.nan
    got = mc_rows.row_nanmean(a)
    want = np.array([r[~np.isnan(r)].mean() if (~np.isnan(r)).any() else np.nan for r in a])
    np.testing.assert_array_equal(got, want)
    k = max(1, rows // 3)
    np.testing.assert_array_equal(mc_rows.row_nanmean(a[k:]), got[k:])
    np.testing.assert_array_equal(mc_rows.row_nanmean(a[:, None, :])[:, 0], got)  # any leading shape
    np.testing.assert_array_equal(mc_rows.row_nanmean(np.asfortranarray(a)), got)  # any memory order

"""Feature slots (sim/slots.py): assignment rules on hand-built track tables, and the measurement arrays."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings, strategies as hs

from stereopose_mc.config.sensor import PixelCamera
from stereopose_mc.sim.slots import FREE, assign_slots, slot_measurements

CAM = PixelCamera(width=640, height=480, f_px=800.0, cx=320.0, cy=240.0)


def table(lives: dict[int, tuple[int, int]]) -> pd.DataFrame:
    """One row per step of each track's life ``{id: (first, last)}``; positions encode (id, step)."""
    rows = [(k, i) for i, (a, b) in lives.items() for k in range(a, b + 1)]
    df = pd.DataFrame(rows, columns=["step", "track_id"]).sort_values(["step", "track_id"], kind="stable")
    k, i = df["step"].to_numpy(float), df["track_id"].to_numpy(float)
    df["col_r"], df["row_r"] = 100.0 + i + 0.01 * k, 200.0 + i
    df["col_l"], df["row_l"] = 90.0 + i + 0.01 * k, 200.0 + i
    first = df.groupby("track_id")["step"].transform("min").to_numpy() == df["step"].to_numpy()
    for c, v in (("dcol_r", 0.01), ("drow_r", 0.0), ("dcol_l", 0.01), ("drow_l", 0.0)):
        df[c] = np.where(first, np.nan, v)  # nan at detection, as the tracker writes
    return df.reset_index(drop=True)


def test_tracks_ending_and_appearing_reuse_the_lowest_free_slot():
    # ids 0, 1 from step 0; 0 ends at step 2 -> its slot 0 is free at step 3, where 5 and 6 are born:
    # 5 takes slot 0, 6 takes slot 2; 7 (born at 3 too) finds no slot and is never used, even when 1 ends
    a = assign_slots(table({0: (0, 2), 1: (0, 4), 5: (3, 6), 6: (3, 6), 7: (3, 6), 8: (6, 6)}), 3, 6)
    want = np.array([[0, 1, FREE], [0, 1, FREE], [0, 1, FREE], [5, 1, 6], [5, 1, 6], [5, FREE, 6], [5, 8, 6]])
    assert np.array_equal(a.track, want)
    assert a.unused.tolist() == [7]


def test_more_tracks_than_slots_at_the_start():
    a = assign_slots(table({i: (0, 3) for i in (4, 2, 9, 7)}), 2, 3)
    assert np.array_equal(a.track, np.tile([2, 4], (4, 1))) and a.unused.tolist() == [7, 9]


def test_rows_beyond_the_last_step_and_no_rows():
    a = assign_slots(table({0: (2, 8)}), 2, 4)
    assert a.track.shape == (5, 2) and a.track[:, 0].tolist() == [FREE, FREE, 0, 0, 0]
    empty = assign_slots(table({}), 3, 2)
    assert (empty.track == FREE).all() and empty.unused.size == 0
    with pytest.raises(ValueError, match="n_slots"):
        assign_slots(table({}), 0, 2)


def test_measurements_in_normalized_units_channel_order_born_and_body():
    df = table({0: (0, 2), 1: (0, 4), 5: (3, 4)})
    df["body_x"], df["body_y"], df["body_z"] = df["track_id"] * 1.0, 2.0, 3.0
    df.loc[(df["track_id"] == 1) & (df["step"] == 0), "body_x"] = np.nan  # first finite value counts
    df["sigma_px"], df["sigma_pxps"] = 0.2, 0.1
    a = assign_slots(df, 2, 4)
    m = slot_measurements(df, a, CAM)
    assert m.y.shape == (5, 2, 8) and m.body.shape == (5, 2, 3) and m.sigma.shape == (5, 2, 2)
    # slot 0 at step 3 holds track 5, born there: positions, velocities nan (not measured)
    row = df[(df["track_id"] == 5) & (df["step"] == 3)].iloc[0]
    u_r = (row["col_r"] - 320.0) / 800.0
    assert m.y[3, 0, 0] == pytest.approx(u_r, abs=1e-15)
    assert m.y[3, 0, 3] == pytest.approx((row["row_l"] - 240.0) / 800.0, abs=1e-15)
    assert np.isnan(m.y[3, 0, 4:]).all() and not m.measured[3, 0]
    # step 4: velocities in 1/s (px/s / f_px), channel order du_R, dv_R, du_L, dv_L
    assert np.allclose(m.y[4, 0, 4:], np.array([0.01, 0.0, 0.01, 0.0]) / 800.0, rtol=0, atol=1e-18)
    assert m.measured.tolist() == [[False, False], [True, True], [True, True], [False, True], [True, True]]
    assert m.born.tolist() == [[True, True], [False, False], [False, False], [True, False], [False, False]]
    assert np.array_equal(m.body[:, 1], np.tile([1.0, 2.0, 3.0], (5, 1)))
    assert np.array_equal(m.body[4, 0], [5.0, 2.0, 3.0])
    assert np.allclose(m.sigma[1, 0], [0.2 / 800.0, 0.1 / 800.0])
    # the track id array alone works the same
    assert np.array_equal(slot_measurements(df, a.track, CAM).y, m.y, equal_nan=True)


def test_empty_slots_and_gaps_are_nan_and_unmeasured():
    df = table({0: (0, 4)})
    df = df[df["step"] != 2].drop(columns=["body_x"], errors="ignore")  # a step without a row inside the life
    a = assign_slots(df, 2, 4)
    m = slot_measurements(df, a, CAM)
    assert a.track[:, 0].tolist() == [0, 0, 0, 0, 0]  # the slot stays the track's
    assert np.isnan(m.y[2, 0]).all() and np.isnan(m.y[:, 1]).all() and np.isnan(m.body).all()
    assert m.measured[:, 0].tolist() == [False, True, False, True, True]
    assert not m.born[1:].any() and np.isnan(m.sigma).all()


lives = hs.dictionaries(hs.integers(0, 40), hs.tuples(hs.integers(0, 12), hs.integers(0, 12)).map(sorted),
                        max_size=25)  # fmt: skip


@settings(max_examples=60, deadline=None)
@given(lives=lives, n=hs.integers(1, 6))
def test_assignment_properties(lives, n):
    K = 10
    df = table({i: tuple(v) for i, v in lives.items()})
    a = assign_slots(df, n, K)
    slot = a.track
    for k in range(K + 1):
        live = slot[k][slot[k] != FREE]
        assert len(set(live.tolist())) == len(live)  # a track holds one slot at most
    for i, (first, last) in lives.items():
        if first > K:
            continue
        where = np.argwhere(slot == i)
        if i in a.unused:
            assert where.size == 0
            assert (slot[first] != FREE).all()  # it found every slot taken at its birth
            continue
        # used: one slot, exactly over its life
        assert len(set(where[:, 1].tolist())) == 1
        assert sorted(where[:, 0].tolist()) == list(range(first, min(last, K) + 1))
    m = slot_measurements(df, a, CAM)
    assert (m.measured <= (slot != FREE)).all()
    assert m.born.sum() == len([i for i, (f, _) in lives.items() if f <= K and i not in a.unused])

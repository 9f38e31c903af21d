"""Track and truth files (sim/tracks_file.py): round trips, and one-line errors naming the file and column."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from stereopose_mc.sim.tracks_file import (STATE_COLUMNS, TRACK_FILE_COLUMNS, TracksFileError, read_tracks,
                                           read_truth, write_tracks)  # fmt: skip


def tracks(n_steps=4, ids=(3, 7)) -> pd.DataFrame:
    rng = np.random.default_rng(0)
    rows = [(k, i) for k in range(n_steps) for i in ids]
    df = pd.DataFrame(rows, columns=["step", "track_id"])
    df["t_s"] = 2.0 * df["step"]
    for c in ("col_r", "row_r", "col_l", "row_l"):
        df[c] = rng.uniform(0, 1024, len(df))
    for c in ("dcol_r", "drow_r", "dcol_l", "drow_l"):
        df[c] = np.where(df["step"] == 0, np.nan, rng.normal(0, 1, len(df)))
    df["quality"] = 0.9  # an extra column is kept
    return df


@pytest.mark.parametrize("suffix", [".parquet", ".csv"])
def test_round_trip(tmp_path, suffix):
    df = tracks()
    df["body_x"] = np.where(df["track_id"] == 3, np.nan, 0.25)
    path = write_tracks(df, tmp_path / f"t{suffix}")
    back = read_tracks(path)
    assert list(back.columns) == ["trial", *df.columns] and (back["trial"] == 0).all()
    pd.testing.assert_frame_equal(back.drop(columns="trial"), df)  # floats exact, nan kept, int64 kept
    assert not list(tmp_path.glob(".*"))  # no temporary file left


def test_time_only_gives_steps_from_dt(tmp_path):
    df = tracks().drop(columns="step")
    path = write_tracks(df, tmp_path / "t.csv")
    assert read_tracks(path, dt=2.0)["step"].tolist() == [0, 0, 1, 1, 2, 2, 3, 3]
    with pytest.raises(TracksFileError, match=r"t\.csv: column 't_s' is not a whole number of dt = 3 s"):
        read_tracks(path, dt=3.0)
    with pytest.raises(TracksFileError, match="needs the scenario's dt"):
        read_tracks(path)


def _error(tmp_path, df, suffix=".csv", **kw) -> str:
    path = write_tracks(df, tmp_path / f"bad{suffix}")
    with pytest.raises(TracksFileError) as exc:
        read_tracks(path, **kw)
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith(str(path) + ": ")
    return msg[len(str(path)) + 2:]


def test_errors_name_the_file_and_the_column(tmp_path):
    assert _error(tmp_path, tracks().drop(columns="row_l")).startswith("missing column 'row_l'")
    assert _error(tmp_path, tracks().drop(columns=["step", "t_s"])).startswith("missing column 'step' (or 't_s')")
    bad = tracks().astype({"col_r": object})
    bad.loc[2, "col_r"] = "left"
    assert _error(tmp_path, bad).startswith("column 'col_r' must be numeric (got ")
    frac = tracks().astype({"track_id": float})
    frac.loc[1, "track_id"] = 7.5
    assert _error(tmp_path, frac).startswith("column 'track_id' must hold whole numbers >= 0 (row 1")
    dup = tracks()
    dup.loc[1, "track_id"] = 3
    assert _error(tmp_path, dup) == "column 'track_id': track 3 appears twice at step 0 (trial 0, row 1)"
    back = tracks().iloc[[0, 1, 4, 5, 2, 3]]
    assert _error(tmp_path, back).startswith("column 'step' goes back in time at row 4 (2 -> 1, trial 0)")
    t_bad = tracks()
    t_bad.loc[2, "t_s"] = 0.0
    assert _error(tmp_path, t_bad).startswith("column 't_s' does not increase with 'step' at row 2")
    nan_pos = tracks()
    nan_pos.loc[5, "col_l"] = np.nan
    assert _error(tmp_path, nan_pos) == "column 'col_l' is not finite at row 5"
    sig = tracks().assign(sigma_px=0.0)
    assert _error(tmp_path, sig) == "column 'sigma_px' must be > 0 (row 0)"
    assert _error(tmp_path, tracks().assign(step=lambda d: d["step"] - 1)).startswith(
        "column 'step' must hold whole numbers >= 0")


def test_trials_are_separate_sequences(tmp_path):
    a, b = tracks().assign(trial=1), tracks().assign(trial=0)
    both = pd.concat([a, b], ignore_index=True)  # trial 1 then trial 0: each in time order
    back = read_tracks(write_tracks(both, tmp_path / "t.parquet"))
    assert back["trial"].tolist() == [1] * 8 + [0] * 8


def test_unreadable_files(tmp_path):
    (tmp_path / "x.txt").write_text("a,b\n")
    with pytest.raises(TracksFileError, match=r"x\.txt: expected a \.parquet or \.csv file"):
        read_tracks(tmp_path / "x.txt")
    with pytest.raises(TracksFileError, match=r"nope\.csv: file not found"):
        read_tracks(tmp_path / "nope.csv")
    (tmp_path / "broken.parquet").write_bytes(b"PAR1 not really")
    with pytest.raises(TracksFileError, match=r"broken\.parquet: cannot read: "):
        read_tracks(tmp_path / "broken.parquet")


def test_truth_file(tmp_path):
    truth = pd.DataFrame({"t": [0.0, 1.0, 2.0], **{c: np.linspace(0, 1, 3) + j for j, c in enumerate(STATE_COLUMNS)}})
    path = tmp_path / "truth.csv"
    truth.to_csv(path, index=False)
    got = read_truth(path, dt=1.0)
    assert got["step"].tolist() == [0, 1, 2] and np.array_equal(got["q3"], truth["q3"])
    truth.drop(columns="omega_y").to_csv(path, index=False)
    with pytest.raises(TracksFileError, match=r"truth\.csv: missing column 'omega_y'"):
        read_truth(path, dt=1.0)


def test_schema_lists_the_required_columns():
    for c in ("track_id", "col_r", "row_r", "col_l", "row_l"):
        assert "required" in TRACK_FILE_COLUMNS[c]

"""Round trip of trajectory tables through Rerun .rrd recordings."""

import numpy as np
import pandas as pd
import pytest
import rerun as rr

from rdsexp.experiment.recording import read_recording, write_recording

COLUMNS = ["q[0]", "q[1]", "u[0]", "x_pred_mean[0]", "xi_filt_std[1]"]


def _grid(rng, experiment, n_steps, n_paths, inner=None):
    """Random grid table sorted by (k, path[, member]) with NaN after a path 'diverges'."""
    axes = [np.arange(n_steps), np.arange(n_paths)] + ([np.arange(inner)] if inner else [])
    mesh = [m.ravel() for m in np.meshgrid(*axes, indexing="ij")]
    keys = {"experiment": experiment, "k": mesh[0], "path": mesh[1]} | ({"member": mesh[2]} if inner else {})
    frame = pd.DataFrame(keys | {c: rng.standard_normal(len(mesh[0])) for c in COLUMNS})
    frame.loc[(frame["path"] == 1) & (frame["k"] >= 2), COLUMNS] = np.nan
    return frame


def _table(n_steps_paths, inner=None):
    rng = np.random.default_rng(0)
    experiments = ["closed_loop/proposed", "open_loop"]
    frames = [_grid(rng, e, k, p, inner) for e, (k, p) in zip(experiments, n_steps_paths, strict=True)]
    return pd.concat(frames, ignore_index=True)


@pytest.mark.parametrize("n_steps_paths", [[(4, 3), (4, 3)], [(5, 3), (3, 2)]], ids=["same-grid", "own-grids"])
def test_round_trip_is_exact(tmp_path, n_steps_paths):
    trajectories = _table(n_steps_paths)
    assert trajectories[COLUMNS].isna().any().all()

    write_recording(tmp_path / "run.rrd", trajectories, recording_id="round-trip")

    pd.testing.assert_frame_equal(read_recording(tmp_path / "run.rrd"), trajectories)


def test_members_are_recorded(tmp_path):
    trajectories, members = _table([(4, 3), (4, 3)]), _table([(4, 3), (4, 3)], inner=2)

    write_recording(tmp_path / "run.rrd", trajectories, recording_id="members", members=members)

    pd.testing.assert_frame_equal(read_recording(tmp_path / "run.rrd"), trajectories)
    store = rr.chunk.RrdReader(tmp_path / "run.rrd").stream().collect()
    entity = "/open_loop/members/x_pred_mean/0"
    assert entity in store.schema().entity_paths()
    cells = store.reader(index="k", contents=entity).to_arrow_table()
    column = store.schema().column_for(entity, "Scalars:scalars").name
    # Instances of a step are path * M + member, i.e. the member rows of that step in order.
    recorded = np.stack([np.asarray(cell, dtype=np.float64) for cell in cells.column(column).to_pylist()])
    expected = members.loc[members["experiment"] == "open_loop", "x_pred_mean[0]"].to_numpy().reshape(4, 6)
    np.testing.assert_array_equal(recorded, expected)


def test_incomplete_grid_is_rejected(tmp_path):
    trajectories = _table([(4, 3), (4, 3)]).drop(index=5)

    with pytest.raises(ValueError, match="complete grid"):
        write_recording(tmp_path / "run.rrd", trajectories, recording_id="incomplete")

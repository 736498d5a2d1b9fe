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


def _static_text(path, entity):
    store = rr.chunk.RrdReader(path).store().stream().filter(content=entity).collect()
    table = store.reader(index=None, contents=entity).to_arrow_table()
    name = store.schema().column_for(entity, rr.TextDocument.descriptor_text().component).name
    return table.column(name)[0].as_py()[0]


def test_summary_entities_match_the_tables(small_run):
    """The run's recording, read back with Rerun's reader: the summary's curves are the tables'."""
    import json

    from rdsexp.experiment.recording import read_series
    rrd = small_run / "recording.rrd"
    info = json.loads((small_run / "run.json").read_text())
    traj = pd.read_parquet(small_run / "trajectories.parquet")
    exact = pd.read_parquet(small_run / "exact.parquet")
    gains = pd.read_parquet(small_run / "gains.parquet")
    for loop in ("closed_loop", "open_loop"):
        frame = traj[traj["experiment"] == loop].sort_values(["k", "path"])
        q = frame[[f"q[{i}]" for i in range(6)]].to_numpy().reshape(frame["k"].nunique(), -1, 6)
        sq = (q ** 2).sum(-1)
        k, mean = read_series(rrd, f"/summary/rms/{loop}/mean")
        np.testing.assert_allclose(mean, np.sqrt(sq.mean(axis=1)), rtol=1e-12)
        # the band of the figures too: the delta-method interval of log E||q_k||^2 (analysis.rms_band)
        _, low = read_series(rrd, f"/summary/rms/{loop}/band_low")
        _, high = read_series(rrd, f"/summary/rms/{loop}/band_high")
        rel = 1.959963984540054 * sq.std(axis=1, ddof=1) / np.sqrt(sq.shape[1]) / sq.mean(axis=1)
        np.testing.assert_allclose(low, np.sqrt(sq.mean(axis=1) * np.exp(-rel)), rtol=1e-12)
        np.testing.assert_allclose(high, np.sqrt(sq.mean(axis=1) * np.exp(rel)), rtol=1e-12)
        from rdsexp import report
        np.testing.assert_allclose(np.stack(report.rms_with_band(q)), np.stack([mean, low, high]), rtol=1e-12)
        _, ex = read_series(rrd, f"/summary/rms/{loop}/exact")
        np.testing.assert_allclose(ex, exact[exact["experiment"] == loop]["rms"], rtol=1e-12)
        _, log_mean = read_series(rrd, f"/summary/log10_rms/{loop}/mean")
        np.testing.assert_allclose(log_mean, np.log10(mean), rtol=1e-12)
    lam = gains[gains["selected"]]["lam"].iloc[0]
    k, lam_k = read_series(rrd, "/summary/rms/closed_loop/lambda_k")
    np.testing.assert_allclose(lam_k, exact["rms"].iloc[0] * lam ** k, rtol=1e-12)
    # modeled mean drawn over the window K0..K0+K1 = 5..25 of the SMALL config, at the model table's mean
    model = pd.read_parquet(small_run / "model.parquet")
    k, modeled = read_series(rrd, "/summary/xi/xi1/modeled_mean")
    assert (k[0], k[-1]) == (5, 25)
    np.testing.assert_allclose(modeled, model[(model["quantity"] == "mean") & (model["row"] == 1)]["value"].iloc[0])
    k, estimate = read_series(rrd, "/summary/xi/xi0/estimate")
    ident = pd.read_parquet(small_run / "identification.parquet")
    np.testing.assert_allclose(estimate, ident[ident["path"] == 0]["xi_filt_mean[0]"])
    report = _static_text(rrd, "/summary/report")
    assert f"lambda {info['summary']['lam']:.4g}" in report and "## Gain F (u = F x)" in report
    assert f"{gains[gains['selected']]['F[0,1]'].iloc[0]:.4g}" in report

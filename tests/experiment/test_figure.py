"""A run's static figure (figure.png, `rdsexp.experiment.figure`): written beside the tables, named by the console,
drawn again from the stored tables to the same bytes by `rdsexp-runs plot RUN`, off with tracking.figure=false."""
import json

import numpy as np
import pandas as pd
from conftest import SMALL, rdsexp

from rdsexp.experiment import pipeline
from rdsexp.experiment.figure import squares_of


def test_a_run_writes_its_figure_and_the_catalog_draws_the_same_from_the_stored_tables(tmp_path):
    proc = rdsexp("plant=dropout", *SMALL, "tracking.recording=false", "tracking.figure=true", cwd=tmp_path)
    (run_dir,) = sorted((tmp_path / "outputs" / "runs").iterdir())
    figure = run_dir / "figure.png"
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert f"figure: {figure}" in proc.stdout
    info = json.loads((run_dir / "run.json").read_text())
    assert info["figure"]["file"] == "figure.png" and "figure" in info["timings"]
    # the run's own figure is what the catalog returns; drawn elsewhere from the stored tables, the same bytes
    shown = rdsexp("plot", str(run_dir), module="rdsexp.runs", cwd=tmp_path)
    assert shown.stdout.strip() == str(figure)
    rdsexp("plot", str(run_dir), "--out", str(tmp_path / "again"), module="rdsexp.runs", cwd=tmp_path)
    assert (tmp_path / "again" / "figure.png").read_bytes() == figure.read_bytes()
    # a run without its figure gets it from the catalog, in its directory
    rdsexp("plant=dropout", *SMALL, "tracking.recording=false", "tracking.figure=false", "seed=1", cwd=tmp_path)
    (other,) = [d for d in (tmp_path / "outputs" / "runs").iterdir() if d != run_dir]
    assert not (other / "figure.png").exists() and "figure" not in json.loads((other / "run.json").read_text())
    rdsexp("plot", str(other), module="rdsexp.runs", cwd=tmp_path)
    assert (other / "figure.png").exists()


def test_the_stored_trajectories_give_the_loops_squares_the_run_kept():
    """`squares_of` a run's trajectories table is the ||q_k||^2 (K+1, P) per loop the run drew its figure from."""
    from hydra import compose, initialize_config_module

    from rdsexp.experiment.config import build
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        exp = build(compose("config", overrides=[*SMALL, "tracking=summary", "closed_loop.paths=5"]))
    out = pipeline.run_experiment(exp)
    squares = squares_of(out.tables["trajectories"])
    assert set(squares) == set(out.squares) == {"closed_loop", "open_loop"}
    for name, sq in out.squares.items():
        np.testing.assert_allclose(squares[name], sq, rtol=1e-12)
    assert isinstance(out.tables["metrics"], pd.DataFrame)


def test_the_xi_panels_intervals_are_the_stated_ones_and_a_std_stops_at_zero():
    """The panel's bars span modeled +- 1.96 stated sd (what `model_calibration.py` scores), except that a std's
    bar stops at 0, where no std lies."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rdsexp.experiment.figure import xi_panel
    summary = {"xi_mean": [0.0, 1.0], "xi_std": [0.1, 0.5], "plant_xi_mean": [0.0, 1.0], "plant_xi_std": [0.2, 0.4],
               "modeling_uncertainty": {"xi_mean_sd": [0.2, 0.1], "xi_std_sd": [0.2, 0.1]}}
    fig, (ax_mean, ax_std) = plt.subplots(2)
    xi_panel(ax_mean, ax_std, summary)
    span = lambda ax: np.array([seg[:, 1] for seg in ax.containers[0].lines[2][0].get_segments()])
    np.testing.assert_allclose(span(ax_mean), [[-0.392, 0.392], [0.804, 1.196]])
    np.testing.assert_allclose(span(ax_std), [[0.0, 0.492], [0.304, 0.696]])
    plt.close(fig)

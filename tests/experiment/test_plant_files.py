"""Any plant through the CLI: xi families, model from the plant, identification under feedback,
designs that cannot be applied as statuses."""
import json
import sys

import numpy as np
import pandas as pd
import pytest
import yaml
from conftest import REPO, rdsexp, undocumented

from rdsexp.experiment.recording import read_series
from rdsexp.numerics import distributions as D
from rdsexp.numerics.systems import MomentModel

SMALL = ["closed_loop.paths=4", "enkf.ensemble_size=20", "closed_loop.horizon=30", "closed_loop.disturbance.until=10",
         "identification.horizon=30", "identification.K0=5", "identification.K1=20", "tracking=off"]


@pytest.mark.parametrize("dist", [D.Uniform([-1, 0.5], [2, 0.5]), D.Bernoulli([0.9, 0.0, 1.0]),
                                  D.Discrete([[0, 1], [2, -1], [1, 1]], [0.2, 0.5, 0.3])])
def test_family_samples_have_its_exact_moments(dist):
    x = dist.sample(np.random.default_rng(1), (200_000,))
    assert x.shape == (200_000, dist.p)
    se = np.sqrt(np.diag(dist.cov) / x.shape[0]) + 1e-12
    assert np.all(np.abs(x.mean(0) - dist.mean) < 5 * se)
    emp = MomentModel.from_samples(x)
    np.testing.assert_allclose(emp.cov, dist.cov, atol=5 * np.sqrt(2 / x.shape[0]) * np.abs(dist.cov).max() + 1e-12)


@pytest.mark.parametrize("spec, words", [({"family": "bernoulli", "prob": [1.2]}, "[0, 1]"),
                                         ({"family": "uniform", "low": [2], "high": [1]}, "<= high"),
                                         ({"family": "discrete", "values": [[0], [1]], "probs": [0.5, 0.6]}, "sum to 1"),
                                         ({"family": "gamma"}, "expected one of"),
                                         ({"family": "uniform", "low": [0]}, "takes")])
def test_family_errors_are_one_line(spec, words):
    with pytest.raises(ValueError) as err:
        D.from_spec(spec)
    assert words in str(err.value) and "\n" not in str(err.value)


def random_plant(rng, n, m, p, ny, family):
    """An open-loop unstable affine random plant with random B, C and nonzero D."""
    A0 = rng.standard_normal((n, n))
    A0 *= 1.1 / np.abs(np.linalg.eigvals(A0)).max()                  # spectral radius 1.1
    A = [A0] + [0.05 * rng.standard_normal((n, n)) for _ in range(p)]
    B = [rng.standard_normal((n, m))] + [0.05 * rng.standard_normal((n, m)) for _ in range(p)]
    xi = {"normal": {"mean": [0.0] * p, "cov": np.eye(p).tolist()},
          "bernoulli": {"family": "bernoulli", "prob": [0.8] * p},
          "uniform": {"family": "uniform", "low": [-1.0] * p, "high": [1.0] * p},
          "independent": {"family": "independent", "components": [{"family": "bernoulli", "prob": [0.8]},
                                                                    {"family": "uniform", "low": [-1.0] * (p - 1),
                                                                     "high": [1.0] * (p - 1)}]}}[family]
    return {"name": f"random{n}", "A": np.round(A, 4).tolist(), "B": np.round(B, 4).tolist(),
            "C": [np.round(rng.standard_normal((ny, n)), 4).tolist()],
            "D": [np.round(0.1 * rng.standard_normal((ny, m)), 4).tolist()], "xi": xi}


def status_explained(s: dict) -> bool:
    """A model was made, and a status other than ok says why: the iterated identification's passes (the paper's
    estimator; unsettled names its last change) or the simulated estimator's account (at_prior_edge,
    weakly_identified name their components; unsettled its fallback)."""
    status, passes, estimator = s["modeling_status"], s.get("identification_passes") or {}, s["modeling_estimator"]
    if estimator["name"] == "paper":
        settled = not passes.get("passes") or passes["converged"]
        return status == ("ok" if settled else "unsettled") and (settled or passes["last_change"] >= passes["tolerance"])
    reasons = {"unsettled": "fallback", "at_prior_edge": "at_prior_edge", "weakly_identified": "weakly_identified"}
    return status == "ok" and not any(estimator.get(r) for r in reasons.values()) or bool(estimator.get(reasons.get(status)))


@pytest.mark.parametrize("n, m, p, ny, family", [(2, 1, 0, 1, "normal"), (5, 2, 3, 2, "bernoulli"),
                                                 (8, 3, 6, 3, "uniform"), (3, 1, 2, 1, "independent")])
@pytest.mark.slow
def test_random_plant_file_runs_end_to_end(tmp_path, n, m, p, ny, family):
    (tmp_path / "conf" / "plant").mkdir(parents=True)
    plant = random_plant(np.random.default_rng(n), n, m, p, ny, family)
    (tmp_path / "conf" / "plant" / "mine.yaml").write_text(yaml.safe_dump(plant))
    proc = rdsexp("--config-dir", str(tmp_path / "conf"), "plant=mine", "gain.designs=[pole_placement]", *SMALL[:-1],
                  cwd=tmp_path)
    assert "Traceback" not in proc.stderr
    assert "plant random" in proc.stdout and "model plant's own structure" in proc.stdout
    assert "paper" not in proc.stdout                                # no reference numbers for this plant
    (run,) = (tmp_path / "outputs" / "runs").iterdir()
    info = json.loads((run / "run.json").read_text())
    s = info["summary"]
    assert info["status"] == "complete"
    assert s["identification_feedback"]["used"] == "nominal"          # unstable at its mean: under feedback
    assert s["designs"]["pole_placement"] == "not_applicable"         # no poles in this plant file
    # a user's plant: the window is placed (auto) after the disturbance (until k = 10) and after the
    # EnKF has seen n outputs, within the horizon 30
    assert s["rate_window_source"] == "auto" and s["rate_window"][0] == max(10, n) < s["rate_window"][1] <= 30
    assert s["closed_loop_verdict"] in ("stable", "unstable", "undetermined", "failed")
    # the same verdict in the metrics table and in the catalog
    metrics = pd.read_parquet(run / "metrics.parquet").set_index("experiment")
    assert metrics.loc["closed_loop", "verdict"] == s["closed_loop_verdict"]
    assert metrics.loc["closed_loop", "verdict_reason"] == s["closed_loop_verdict_reason"]
    from rdsexp.experiment.store import RunStore
    catalog = RunStore(tmp_path / "outputs").table()
    assert catalog["metrics.closed_loop_verdict"].tolist() == [s["closed_loop_verdict"]]


def test_paper_design_without_poles_and_bad_feedback(tmp_path):
    proc = rdsexp("gain=pole_placement", "plant.poles=null", *SMALL, cwd=tmp_path)
    assert "Traceback" not in proc.stderr
    proc = rdsexp("identification.feedback=sometimes", *SMALL, cwd=tmp_path, check=False)
    assert proc.returncode == 2 and "identification.feedback: 'sometimes' is not allowed" in proc.stderr


LIBRARY = sorted(p.stem for p in (REPO / "conf" / "plant").glob("*.yaml") if p.stem != "recorded")   # (no system)
FEEDBACK = {"paper": None, "dropout": "nominal", "multiplicative": "open_loop", "two_carts": "open_loop",
            "cart_pole": "nominal"}          # what each plant file's comment says it shows


@pytest.mark.slow
def test_systems_sweep_runs_every_library_plant(tmp_path):
    sweep = yaml.safe_load((REPO / "conf" / "sweep" / "systems.yaml").read_text())
    assert sorted(sweep["hydra"]["sweeper"]["params"]["plant"].split(",")) == LIBRARY == sorted(FEEDBACK)
    for name in LIBRARY:                        # every plant file cites its source in a comment
        assert "Source" in (REPO / "conf" / "plant" / f"{name}.yaml").read_text() or name == "paper"
    rdsexp("+sweep=systems", "seed=0", "gain.designs=all", *SMALL[:-1], cwd=tmp_path)     # every design, every plant
    infos = {}
    for run in (tmp_path / "outputs" / "sweeps").glob("*/*/run.json"):
        info = json.loads(run.read_text())
        infos[info["summary"]["plant"]] = info
    assert sorted(infos) == LIBRARY
    for name, info in infos.items():
        s = info["summary"]
        assert info["status"] == "complete" and status_explained(s), (name, s)
        assert s["identification_feedback"].get("used") == FEEDBACK[name], (name, s["identification_feedback"])
        assert ("reference" in s) == (name == "paper")
        assert np.isfinite(s["lam"]) and np.isfinite(s["rate_plant"]), (name, s["synthesis_status"])
        assert not s["synthesis_status"].startswith(("failed", "not_applicable"))
        if name != "paper":
            assert s["designs"]["pole_placement"] == "not_applicable" and s["model"] == "plant's own structure"


# an unstable mode (1.5) that no input reaches: identification must run open loop (no stabilizing
# nominal gain), every design is not_ms_stabilizable, and q_k[0] = 1.5^k leaves the bound 1e6 at k = 35
STUCK = {"A": [[[1.5, 0], [0, 0.5]], [[0, 0], [0, 1]]], "B": [[[0], [1]]], "xi": {"mean": [0], "cov": [[0.04]]}}


def user_dir(tmp_path, name, plant):
    (tmp_path / "conf" / "plant").mkdir(parents=True, exist_ok=True)
    (tmp_path / "conf" / "plant" / f"{name}.yaml").write_text(yaml.safe_dump(plant))
    return str(tmp_path / "conf")


def test_not_stabilizable_default_design_is_stated(tmp_path):
    # the default design (ms_lqr) proves that no gain exists and returns none: no closed loop, said so
    conf = user_dir(tmp_path, "stuck", STUCK)
    proc = rdsexp("--config-dir", conf, "plant=stuck", *SMALL[:-1], cwd=tmp_path)
    assert "Traceback" not in proc.stderr
    assert "no stabilizing gain: ms_lqr returned none (not_ms_stabilizable); no closed loop" in proc.stdout
    assert "not_ms_stabilizable: proven: no gain makes the design moments mean-square stable" in proc.stdout
    (run,) = (tmp_path / "outputs" / "runs").iterdir()
    assert json.loads((run / "run.json").read_text())["summary"]["synthesis_status"] == "not_ms_stabilizable"


def test_not_stabilizable_and_diverged_paths_are_stated(tmp_path):
    # Theorem 2's bisection returns its best gain (rate 1.5 on the model): the loop runs and diverges
    conf = user_dir(tmp_path, "stuck", STUCK)
    proc = rdsexp("--config-dir", conf, "plant=stuck", "gain=proposed", *SMALL[:-1], "closed_loop.horizon=60",
                  cwd=tmp_path)
    assert "Traceback" not in proc.stderr
    (run,) = (tmp_path / "outputs" / "runs").iterdir()
    s = json.loads((run / "run.json").read_text())["summary"]
    assert s["identification_feedback"]["used"] == "open_loop (no stabilizing nominal gain)"
    assert s["synthesis_status"] == "not_ms_stabilizable" and abs(s["rate_plant"] - 1.5) < 1e-9
    assert "no stabilizing gain: not_ms_stabilizable, the best rate found on the model is 1.5000" in proc.stdout
    assert s["closed_loop_failed"] == {"fraction": 1.0, "first_k": 35, "median_k": 35.0, "reasons": {"diverged": 4}}
    assert undocumented(s) == []
    assert "100% of paths failed (first at k = 35, median k = 35): the plant state diverged on 4" in proc.stdout
    # the auto window starts where the disturbance ends (k = 10); no path reaches its end
    assert "closed loop rate k=10..60: n/a (not every path reached the window), ideal loop 1.4982: failed" in proc.stdout
    # the open loop's observer does not act on the plant: its diverged paths are the plant's growth
    assert s["closed_loop_verdict"] == "failed" and s["open_loop_verdict"] == "unstable"
    assert s["open_loop_verdict_reason"].startswith("the uncontrolled plant grows: its state diverged on 100% of paths")


def test_no_model_is_stated(tmp_path):
    # unstable, no input at all reaching it, identified in open loop: q_k = 3^k leaves 1e6 at k = 13
    conf = user_dir(tmp_path, "wild", {"A": [[[3.0]], [[0.1]]], "B": [[[0.0]]], "xi": {"mean": [0], "cov": [[1]]},
                                       "identification_feedback": "none"})
    proc = rdsexp("--config-dir", conf, "plant=wild", *SMALL[:-1], cwd=tmp_path)      # default tracking
    assert "Traceback" not in proc.stderr
    assert "no model: identification failed at k = " in proc.stdout
    assert ": the plant state diverged; no gain designed, no closed loop" in proc.stdout
    assert "closed loop" not in proc.stdout.replace("no closed loop", "")
    # under the default tracking the run completes and records what exists: the identification run
    # in the recording, the gains table with its columns and no rows
    (run,) = (tmp_path / "outputs" / "runs").iterdir()
    assert json.loads((run / "run.json").read_text())["status"] == "complete"
    gains = pd.read_parquet(run / "gains.parquet")
    assert len(gains) == 0 and {"method", "selected", "status", "F[0,0]"} <= set(gains.columns)
    ident = pd.read_parquet(run / "identification.parquet")
    k, estimate = read_series(run / "recording.rrd", "/summary/xi/xi0/estimate")
    np.testing.assert_allclose(estimate, ident.loc[ident["path"] == 0, "xi_filt_mean[0]"])
    assert np.isfinite(estimate).sum() == 13           # k = 0..12, before the plant left the bound


@pytest.mark.slow
def test_failing_stage_is_a_status_not_a_traceback(tmp_path):
    # a stage that raises (here: modeling, patched to fail) ends the run with status error and its
    # stage named in the summary; the traceback goes to run.json and rdsexp.log only
    (tmp_path / "broken.py").write_text(
        "import rdsexp.experiment.pipeline.identification as p\n"
        "def boom(*a, **k):\n    raise RuntimeError('boom')\n"
        "p.model_distribution = boom\n"
        "from rdsexp.experiment.cli import main\nmain()\n")
    proc = rdsexp(*SMALL[:-1], cwd=tmp_path, module="broken", check=False)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr + proc.stdout
    assert "failed: stage modeling: RuntimeError: boom" in proc.stdout
    (run,) = (tmp_path / "outputs" / "runs").iterdir()
    info = json.loads((run / "run.json").read_text())
    assert info["status"] == "error" and "RuntimeError: boom" in info["traceback"]
    assert "Traceback" in (run / "rdsexp.log").read_text()


def test_process_noise_matrix_from_the_command_line(tmp_path):
    from hydra import compose, initialize_config_module

    from rdsexp.experiment.config import build
    Q = np.diag(np.arange(1.0, 10.0)) + 0.1 * (np.ones((9, 9)) - np.eye(9))
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        exp = build(compose("config", overrides=[f"enkf.Q.matrix={Q.tolist()}".replace(" ", "")]))
        np.testing.assert_array_equal(exp.filter.enkf.Q, Q)
        exp = build(compose("config", overrides=["enkf.Q.matrix=[1,2,3,4,5,6,7,8,9]", "enkf.q_scale=2"]))
        np.testing.assert_array_equal(exp.filter.enkf.Q, 2 * np.diag(np.arange(1.0, 10.0)))
    proc = rdsexp("enkf.Q=[[1,2],[3,4]]", cwd=tmp_path, check=False)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1
    assert proc.stderr.startswith("rdsexp: config error: enkf.Q: [[1,2],[3,4]] is not allowed") \
        and "enkf.Q.matrix=[[1,2],[3,4]]" in proc.stderr


def test_readme_plant_file_runs(tmp_path):
    text = (REPO / "README.md").read_text()
    section = text[text.index("## Your own system"):]
    plant = section[section.index("```yaml\n") + 8:section.index("```", section.index("```yaml\n") + 8)]
    assert plant.count("\n") <= 12
    (tmp_path / "mine" / "plant").mkdir(parents=True)
    (tmp_path / "mine" / "plant" / "cart.yaml").write_text(plant)
    assert "rdsexp --config-dir mine plant=cart" in section
    proc = rdsexp("--config-dir", "mine", "plant=cart", *SMALL, cwd=tmp_path)
    assert "plant cart, model plant's own structure" in proc.stdout and "modeling ok" in proc.stdout


def test_plant_file_with_inline_model(tmp_path):
    # the plant's xi is one gain; the model (inline) has its own two parameters on both A entries
    plant = {"A": [[[0.5, 0.1], [0, 0.7]], [[0, 0], [0, 0]]], "B": [[[0], [1]], [[1], [0]]],
             "xi": {"family": "uniform", "low": [0.5], "high": [1.0]},
             "model": {"A": [[[0.5, 0.1], [0, 0.7]], [[1, 0], [0, 0]], [[0, 0], [0, 1]]],
                       "B": [[[0], [1]], [[0], [0]], [[0], [0]]]}}
    conf = user_dir(tmp_path, "own", plant)
    rdsexp("--config-dir", conf, "plant=own", *SMALL[:-1], cwd=tmp_path)
    (run,) = (tmp_path / "outputs" / "runs").iterdir()
    s = json.loads((run / "run.json").read_text())["summary"]
    assert s["model"] == "inline in the plant file" and len(s["xi_mean"]) == 2


def test_a_loop_the_outputs_cannot_carry_is_explained_by_its_exact_rate(tmp_path):
    # x2 doubles and y sees x1 only: the gain stabilizes the plant with the true state (rate 0.51), but no
    # observer of y can estimate x2, so the loop through y has rate 2 whatever L: the summary says so
    conf = user_dir(tmp_path, "blind", {"A": [[[0.5, 0.0], [0.0, 2.0]], [[0.1, 0.0], [0.0, 0.0]]], "B": [[[0.0], [1.0]]],
                                        "C": [[[1.0, 0.0]]], "xi": {"mean": [0.0], "cov": [[1.0]]},
                                        "identification_feedback": "none"})
    proc = rdsexp("--config-dir", conf, "plant=blind", "gain.source=fixed", "+gain.F=[[0.0,-1.9]]", *SMALL[:-1],
                  cwd=tmp_path)
    assert "Traceback" not in proc.stderr
    (run,) = (tmp_path / "outputs" / "runs").iterdir()
    s = json.loads((run / "run.json").read_text())["summary"]
    assert s["rate_plant"] == pytest.approx(np.sqrt(0.26), rel=1e-12) and s["closed_loop_verdict"] != "stable"
    assert s["closed_loop_verdict"] == "failed" and s["closed_loop_through_y"]["rate"] == pytest.approx(2.0, rel=1e-9)
    assert undocumented(s) == []
    assert "the gap is the outputs': with the best linear observer of y found" in proc.stdout


# a random plant (experiments/random_plants.py --seed 1, plant 42): mean-square unstable in open loop (1.24) but
# stable at the mean of xi (0.73), so `auto` identifies it in open loop, where the EnKF's estimate diverges first
UNSTABLE_BUT_STABLE_AT_MEAN = {
    "A": [[[-1.76531, -0.0583627], [0.121774, 0.237077]], [[-0.474025, 0.494553], [0.0421395, -0.143605]],
          [[0.931346, -1.36022], [0.885178, -0.354614]], [[0.935744, -0.75468], [-1.11291, -0.553699]]],
    "B": [[[-0.0449377, 0.791972], [-0.630707, 0.610557]], [[0, 0], [0, 0]], [[0, 0], [0, 0]],
          [[-1.02235, 0.0], [0.0, 0.0]]],
    "C": [[[0.928649, 0.370959]]], "xi": {"family": "bernoulli", "prob": [0.67869, 0.877016, 0.715101]},
    "nominal": [0.67869, 0.877016, 0.715101]}        # a prior guess right on average: stable at the guess


def test_open_loop_identification_whose_estimate_diverges_is_run_again_under_feedback(tmp_path):
    conf = user_dir(tmp_path, "grows", UNSTABLE_BUT_STABLE_AT_MEAN)
    proc = rdsexp("--config-dir", conf, "plant=grows", "closed_loop.paths=2", "closed_loop.floor_paths=2",
                  "closed_loop.open_loop=false", cwd=tmp_path)
    assert "Traceback" not in proc.stderr
    (run,) = (tmp_path / "outputs" / "runs").iterdir()
    s = json.loads((run / "run.json").read_text())["summary"]
    feedback = s["identification_feedback"]
    assert feedback["open_loop_rate_at_guess"] < 1 and feedback["used"] == "nominal"
    assert feedback["open_loop_failure"] == "filter_diverged" and feedback["open_loop_diverged_at"] > 0
    assert f"in open loop the EnKF estimate diverged at k = {feedback['open_loop_diverged_at']}, identified again" \
        in proc.stdout
    assert status_explained(s)


def test_random_plants_guess_off_is_the_mean_moved_by_whole_standard_deviations():
    """random_plants.py --guess-off SD: every run's identification.xi_guess is the plant file's mean moved by SD
    standard deviations of each component, signs alternating (seed 0's rp9: seed + index odd, so - + -), kept 0.02
    inside a Bernoulli's [0, 1]; a user's --override of the same key replaces it."""
    import argparse
    sys.path.insert(0, str(REPO / "experiments"))
    import random_plants
    rp9 = random_plants.draw_plants(10, 0)[9]
    mean, sd = np.array([0.825327, 0.651176, 0.670957]), np.sqrt([0.825327 * (1 - 0.825327), 0.077627, 0.066362])
    np.testing.assert_allclose(random_plants.wrong_guess(rp9, 0, 1.0), mean + [-1, 1, -1] * sd, rtol=1e-12)
    np.testing.assert_allclose(random_plants.wrong_guess(rp9, 1, 3.0), [0.98, mean[1] - 3 * sd[1], mean[2] + 3 * sd[2]],
                               rtol=1e-12)                                    # seed + index even: + - +, clipped
    args = argparse.Namespace(paths=100, store="S", override=["controller=online"],
                              guesses={"rp9": random_plants.wrong_guess(rp9, 0, 1.0)})
    assert random_plants._overrides(args, "rp9") == ["plant=rp9", "closed_loop.paths=100", "store=S",
                                                     "identification.xi_guess=[0.44564,0.92979,0.41335]",
                                                     "controller=online"]
    assert "identification.xi_guess" not in " ".join(random_plants._overrides(args, "rp8"))    # not drawn off
    args.override = ["identification.xi_guess=[0.5,0.6,0.7]"]
    assert random_plants._overrides(args, "rp9")[-1] == "identification.xi_guess=[0.5,0.6,0.7]"


def test_random_plants_says_why_a_modeled_plant_has_no_loop():
    """experiments/random_plants.py: a plant modeled but given no gain (its identified model not mean-square
    stabilizable) is said so, not as an empty verdict; a loop that is not stable gives its verdict's reason."""
    sys.path.insert(0, str(REPO / "experiments"))
    import random_plants
    row = {"note": None, "run_dir": "run", "run_status": "complete", "modeled": True, "modeling_status": "ok",
           "synthesis_status": "not_ms_stabilizable", "verdict": None, "closed_loop_status": None,
           "verdict_reason": None}
    assert random_plants._why(row) == "no closed loop: the design on the identified model ended not_ms_stabilizable"
    row.update(verdict="unstable", closed_loop_status="ok", verdict_reason="the loop grows")
    assert random_plants._why(row) == "closed loop unstable: the loop grows"


def test_random_plants_counts_the_plants_losing_more_paths_online_apart_where_the_offline_loop_is_stable(capsys):
    """experiments/random_plants.py with controller=online: a plant losing more paths online is marked with its
    offline loop's verdict and whether the paired test finds more than chance explains; the counts say how many
    lose more by the bare counts and by the test, and how many of them have an offline loop called stable; a plant
    without an offline gain is counted in neither; one whose offline gain's loop through y no linear observer holds
    (y_rate >= 1) is said so, and whether online's lost paths held a gain unstable on the plant."""
    sys.path.insert(0, str(REPO / "experiments"))
    import pandas as pd
    import random_plants
    table = pd.DataFrame({"plant": ["a", "b", "c", "d"], "online_final_rate": [0.5, 0.7, 0.9, 0.8],
                          "offline_rate_plant": [0.6, 0.69, 0.8, None], "online_failed_fraction": [0.1, 0.04, 0.0, 0.5],
                          "failed_fraction": [0.0, 0.02, 0.0, None], "verdict": ["stable", "undetermined", "stable", None],
                          "lost_online_only": [10, 3, 0, None], "lost_offline_only": [0, 1, 0, None],
                          "lost_more_p": [2.0 ** -10, 5 / 16, 1.0, None], "y_rate": [0.9, 1.2, None, None],
                          "lost_held_unstable": [0.0, 2.0, None, None]})
    random_plants.print_online(table)
    out = capsys.readouterr().out
    assert ("a: online 0.5000 offline 0.6000 gap -0.1000; lost 0.10 vs 0.00 (10 vs 0 alone, p = 0.000977)  LOST MORE, "
            "beyond chance (offline loop stable; online's lost paths held only gains stable on the plant)") in out
    assert ("lost 0.04 vs 0.02 (3 vs 1 alone, p = 0.312)  WORSE  LOST MORE, within chance (offline loop undetermined; "
            "no linear observer holds its gain's loop through y: y_rate 1.2000; 2 of online's lost paths held a gain "
            "unstable on the plant)") in out
    assert "c: online 0.9000 offline 0.8000 gap +0.1000; lost 0.00 vs 0.00  WORSE" in out
    assert out.strip().splitlines()[-1] == ("online ends no worse than offline (final median rate <= offline + 0.005): "
                                            "1/3 (33%); loses more paths: 2/3, 1/2 where the offline loop is stable; "
                                            "more than chance explains (paired sign test, p < 0.05): 1/3, 1/2 where "
                                            "the offline loop is stable, 0/1 where no linear observer holds the "
                                            "offline gain's loop (y_rate >= 1); no offline gain (not compared): d")
    random_plants.print_online(table.drop(columns=["lost_online_only", "lost_offline_only", "lost_more_p",
                                                   "lost_held_unstable"]))
    assert "lost 0.10 vs 0.00  LOST MORE (offline loop stable)" in capsys.readouterr().out    # runs before the test


def test_paired_null_redraws_only_the_loops_enkf_noise_and_tallies_each_comparison():
    """experiments/paired_null.py: within `noise_drawn_anew` the loops' EnKF streams (spawn key (1,)) are new and
    their plant streams, and every identification stream (spawn key (0,)), are the same numbers; `tally` counts,
    per comparison, the plants losing more by the bare counts and by the paired test, and names them."""
    sys.path.insert(0, str(REPO / "experiments"))
    import json

    import paired_null
    import pandas as pd

    from rdsexp.numerics import simulation
    loops, ident = (np.random.SeedSequence(5, spawn_key=key) for key in ((1,), (0,)))
    first = lambda seed, purpose: simulation.path_generators(seed, purpose, range(3))[2].standard_normal(4)
    before = {(s, p): first(s, p) for s in (loops, ident) for p in (simulation.PLANT, simulation.ENKF)}
    with paired_null.noise_drawn_anew():
        during = {(s, p): first(s, p) for s in (loops, ident) for p in (simulation.PLANT, simulation.ENKF)}
    assert not np.array_equal(during[loops, simulation.ENKF], before[loops, simulation.ENKF])
    for key in ((loops, simulation.PLANT), (ident, simulation.PLANT), (ident, simulation.ENKF)):
        np.testing.assert_array_equal(during[key], before[key])
    np.testing.assert_array_equal(first(loops, simulation.ENKF), before[loops, simulation.ENKF])   # restored

    for bad in (["--seeds", "abc"], ["--seeds", "3-x"], ["--n", "0"]):     # a one-line error before any run
        with pytest.raises(SystemExit):
            paired_null.main(bad)
    assert paired_null.seeds_of("0-2,5") == [0, 1, 2, 5]

    lists = lambda *lost: [json.dumps(list(x)) for x in lost]
    table = pd.DataFrame({"seed": [0, 0, 0], "plant": ["rp0", "rp1", "rp2"], "gain": [True, True, False],
                          "verdict": ["stable", "undetermined", ""], "off": lists([], [1], []),
                          "off_anew": lists([2], [1], []), "on": lists(range(6), [1, 3], range(9)),
                          "on_anew": lists([0, 1], [], [])})
    lines = paired_null.tally(table, 10)
    assert lines[0].startswith("2 plants with an offline gain, 1 with an offline loop called stable")
    counts = {line[2:30].strip(): line[30:].split() for line in lines[1:7]}
    assert counts["offline anew vs offline"] == ["bare", "1", "(1)", "test", "0", "(0)"]
    assert counts["online vs offline"] == ["bare", "2", "(1)", "test", "1", "(1)"]      # rp0: 6 vs 0, p = 1/64
    assert counts["online vs online anew"] == ["bare", "2", "(1)", "test", "0", "(0)"]  # rp0: 4 vs 0, p = 1/16
    assert lines[7] == ("  seed 0 rp0 (stable): lost offline 0 / 1 anew, online 6 / 2 anew; online vs offline alone "
                        "6 vs 0 (p = 0.0156), 2 vs 1 (p = 0.5)")


def test_paired_null_overrides_reach_both_runs_and_a_bad_one_stops_before_any(tmp_path, monkeypatch, capsys):
    """experiments/paired_null.py --override: each run's experiment carries it after the script's own overrides
    (here a 300-step horizon, where online loses paths on plants it keeps at 100); a bad one is argparse's
    one-line error, checked on the first plant before any run is submitted."""
    sys.path.insert(0, str(REPO / "experiments"))
    import paired_null
    from coverage import experiment
    from random_plants import draw_plants, write_plant

    import rdsexp.experiment.pipeline as pipeline
    plant = draw_plants(1, 0)[0]
    write_plant(plant, tmp_path, "test")
    exp = experiment(plant.name, tmp_path, paired_null.run_overrides(5, ["closed_loop.horizon=300"]))
    assert (exp.controller.kind, exp.loop.paths, exp.loop.disturbance.shape[0]) == ("online", 5, 301)

    seen = []

    def record(exp):                                    # lost_paths builds its run from the same overrides
        seen.append(exp.loop.disturbance.shape[0])
        raise RuntimeError("recorded")
    monkeypatch.setattr(pipeline, "run_experiment", record)
    for anew in (False, True):
        with pytest.raises(RuntimeError, match="recorded"):
            paired_null.lost_paths(tmp_path, plant.name, 5, anew, ["closed_loop.horizon=300"])
    assert seen == [301, 301]

    out = tmp_path / "table.csv"
    with pytest.raises(SystemExit):
        paired_null.main(["--seeds", "0", "--n", "1", "--out", str(out), "--override", "closed_loop.horizon=abc"])
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error.endswith(": error: --override: closed_loop.horizon: 'abc' is not allowed, expected an integer >= 1")
    assert seen == [301, 301] and not out.exists()

"""A simulated run is blind: nothing before judging reads the law the plant is simulated from, unless the user
asks for the oracle, which the summary then labels."""
import numpy as np
import pytest
import yaml
from conftest import SMALL, rdsexp
from hydra import compose, initialize_config_module

from rdsexp.errors import ConfigError
from rdsexp.experiment.config import PRIORS, build
from rdsexp.experiment.pipeline.identification import identification_feedback
from rdsexp.experiment.pipeline.online import initial_gain, online_observer
from rdsexp.experiment.pipeline.record import prior_summary

# open-loop unstable, its input through xi_1 (an actuator link), a second parameter on A
PLANT = {"A": [[[1.05, 0.2], [0.0, 0.95]], [[0, 0], [0, 0]], [[0.3, 0], [0, 0]]],
         "B": [[[0], [0.2]], [[0], [1]], [[0], [0]]],
         "C": [[[1, 0]]]}


def experiment(tmp_path, law: dict, *extra, nominal=None):
    (tmp_path / "plant").mkdir(exist_ok=True)
    plant = dict(PLANT, name="blind", xi=law) | ({"nominal": nominal} if nominal is not None else {})
    (tmp_path / "plant" / "blind.yaml").write_text(yaml.safe_dump(plant))
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        return build(compose("config", overrides=[f"hydra.searchpath=[file://{tmp_path}]", "plant=blind",
                                                  "model=plant", *SMALL, "tracking=off", *extra]))


# the same families and supports (the EnKF's projection box and two-point draws come from the family's support,
# which the plant file states as structure: a Bernoulli's {0, 1}), different laws
LAWS = [{"family": "independent", "components": [{"family": "bernoulli", "prob": 0.9},
                                                  {"family": "normal", "mean": [-0.2], "cov": [[0.05]]}]},
        {"family": "independent", "components": [{"family": "bernoulli", "prob": 0.4},
                                                  {"family": "normal", "mean": [0.7], "cov": [[0.01]]}]}]


@pytest.mark.parametrize("nominal, source", [(None, "zero"), ([1.0, 0.0], "nominal")])
def test_the_prior_knowledge_does_not_depend_on_the_law(tmp_path, nominal, source):
    """Two plants that differ only in their law of xi get the same prior guess, EnKF start, identification
    feedback gain and online start gain: all of them come from what the plant file states apart from the law
    (`nominal:`, else xi = 0), never from the law."""
    a, b = (experiment(tmp_path, law, "controller=online", nominal=nominal) for law in LAWS)
    assert a.identification.prior == b.identification.prior == source
    expected = np.zeros(2) if nominal is None else np.array(nominal)
    np.testing.assert_array_equal(a.identification.xi_guess, expected)
    np.testing.assert_array_equal(b.identification.xi_guess, expected)
    np.testing.assert_array_equal(a.filter.psi0, b.filter.psi0)
    np.testing.assert_array_equal(a.filter.psi0[2:], expected)            # the EnKF starts at the guess
    (Fa, info_a), (Fb, info_b) = identification_feedback(a), identification_feedback(b)
    judged = lambda info: {k: v for k, v in info.items() if k != "rate_plant"}    # the gain's rate on the truth
    assert judged(info_a) == judged(info_b) and (Fa is None) == (Fb is None)
    if Fa is not None:
        np.testing.assert_array_equal(Fa, Fb)
    np.testing.assert_array_equal(initial_gain(a, online_observer(a))[0], initial_gain(b, online_observer(b))[0])
    assert prior_summary(a) == prior_summary(b) == {
        "xi_guess": expected.tolist(), "source": source,
        "used_by": ["the EnKF's start", "the identification feedback", "the online controller"]}


def test_the_oracle_is_asked_for_by_name_and_labelled(tmp_path):
    """identification.xi_guess=oracle is the law's mean (the only prior that reads it), and the run says so."""
    exp = experiment(tmp_path, LAWS[1], "identification.xi_guess=oracle", nominal=[1.0, 0.0])
    assert exp.identification.prior == "oracle"
    np.testing.assert_array_equal(exp.identification.xi_guess, [0.4, 0.7])   # LAWS[1]'s mean
    given = experiment(tmp_path, LAWS[1], "identification.xi_guess=[0.5,0.1]", nominal=[1.0, 0.0])
    assert given.identification.prior == "given" and given.identification.xi_guess.tolist() == [0.5, 0.1]
    assert "ORACLE" in PRIORS["oracle"] and "ORACLE" not in "".join(v for k, v in PRIORS.items() if k != "oracle")
    for bad, what in (("identification.xi_guess=truth", "identification.xi_guess: 'truth' is not allowed"),
                      ("identification.xi_guess=[1]", "identification.xi_guess: [1] is not allowed")):
        with pytest.raises(ConfigError, match=what.replace("[", r"\[").replace("]", r"\]")):
            experiment(tmp_path, LAWS[1], bad)
    with pytest.raises(ConfigError, match=r"plant.nominal: \[1.0\] is not allowed"):
        experiment(tmp_path, LAWS[1], nominal=[1.0])


def test_a_run_says_where_its_prior_came_from(tmp_path):
    """The console and run.json name the prior's source; the oracle's line says it is not blind."""
    (tmp_path / "plant").mkdir()
    (tmp_path / "plant" / "blind.yaml").write_text(yaml.safe_dump(dict(PLANT, name="blind", xi=LAWS[1],
                                                                       nominal=[1.0, 0.0])))
    args = ["--config-dir", str(tmp_path), "plant=blind", *SMALL, "tracking=summary", "tracking.recording=false"]
    blind = rdsexp(*args, cwd=tmp_path).stdout
    assert "prior guess of xi [1.0, 0.0]: the plant file's nominal; used by the EnKF's start" in blind
    oracle = rdsexp(*args, "identification.xi_guess=oracle", "seed=1", cwd=tmp_path).stdout
    assert "prior guess of xi [0.4, 0.7]: ORACLE: the mean of the law the plant is simulated from (not blind)" \
        in oracle

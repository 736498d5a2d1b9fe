"""Any plant through the CLI: xi families, model from the plant, identification under feedback,
designs that cannot be applied as statuses (issue 17)."""
import json

import numpy as np
import pytest
import yaml
from conftest import rdsexp

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
          "uniform": {"family": "uniform", "low": [-1.0] * p, "high": [1.0] * p}}[family]
    return {"name": f"random{n}", "A": np.round(A, 4).tolist(), "B": np.round(B, 4).tolist(),
            "C": [np.round(rng.standard_normal((ny, n)), 4).tolist()],
            "D": [np.round(0.1 * rng.standard_normal((ny, m)), 4).tolist()], "xi": xi}


@pytest.mark.parametrize("n, m, p, ny, family", [(2, 1, 0, 1, "normal"), (5, 2, 3, 2, "bernoulli"),
                                                 (8, 3, 6, 3, "uniform")])
def test_random_plant_file_runs_end_to_end(tmp_path, n, m, p, ny, family):
    (tmp_path / "conf" / "plant").mkdir(parents=True)
    plant = random_plant(np.random.default_rng(n), n, m, p, ny, family)
    (tmp_path / "conf" / "plant" / "mine.yaml").write_text(yaml.safe_dump(plant))
    proc = rdsexp("--config-dir", str(tmp_path / "conf"), "plant=mine", *SMALL[:-1], cwd=tmp_path)
    assert "Traceback" not in proc.stderr
    assert "plant random" in proc.stdout and "model plant's own structure" in proc.stdout
    assert "paper" not in proc.stdout                                # no reference numbers for this plant
    (run,) = (tmp_path / "outputs" / "runs").iterdir()
    info = json.loads((run / "run.json").read_text())
    s = info["summary"]
    assert info["status"] == "complete"
    assert s["identification_feedback"]["used"] == "nominal"          # unstable at its mean: under feedback
    assert s["designs"]["pole_placement"] == "not_applicable"         # no poles in this plant file
    assert s["rate_window"] == [18, 24]                               # [0.6, 0.8] of the horizon 30


def test_paper_design_without_poles_and_bad_feedback(tmp_path):
    proc = rdsexp("gain=pole_placement", "plant.poles=null", *SMALL, cwd=tmp_path)
    assert "Traceback" not in proc.stderr
    proc = rdsexp("identification.feedback=sometimes", *SMALL, cwd=tmp_path, check=False)
    assert proc.returncode == 2 and "identification.feedback: 'sometimes' is not allowed" in proc.stderr

"""The shipped data example: recorded inputs and outputs of the library's `dropout` plant (conf/plant/dropout.yaml),
as a testbed would log them, saved in the data format (examples/dropout/dropout.csv).

30 experiments (paths) of 101 steps (k = 0..100): the loop runs under a stabilizing gain designed at the nominal
guess (the plant is open-loop unstable), u_k = F x_{k|k-1} + d_k with an M-sequence d_k in {0, 10} as
excitation (conf/identification's input), and the applied u_k and the measured y_k are logged. A data run
then models the dropout probability from them (README, "Your own data"):

    python experiments/make_dropout_data.py            # writes examples/dropout/dropout.csv
"""
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from rdsexp.experiment.config import system_from
from rdsexp.experiment.data import write
from rdsexp.numerics.distributions import from_spec
from rdsexp.numerics.enkf import EnKF
from rdsexp.numerics.modeling import mls_input, nominal_gain
from rdsexp.numerics.simulation import simulate

REPO = Path(__file__).resolve().parents[1]
PATHS, HORIZON, SEED = 30, 100, 2024


def main(out=REPO / "examples" / "dropout" / "dropout.csv") -> Path:
    cfg = OmegaConf.create({"plant": OmegaConf.load(REPO / "conf" / "plant" / "dropout.yaml")})
    plant = system_from(cfg, "plant", from_spec(OmegaConf.to_container(cfg.plant.xi)))
    F = nominal_gain(plant, plant.xi_dist.mean).F          # the testbed's controller: designed at the guess
    # its observer (a Kalman-like EnKF on the plant's structure, xi at the guess): the testbed's, not rdsexp's
    observer = EnKF(plant, Q=np.diag([1e-4, 1e-4, 0.0]), R=1e-4)
    d = mls_input(HORIZON, plant.m, 7, 10.0, levels="unipolar")     # the identification input of conf/identification
    tr = simulate(plant, observer, F=F, d=d, q0=np.zeros(plant.n), psi0=np.r_[np.zeros(plant.n), 0.8],
                  ensemble_size=20, paths=PATHS, seed=SEED)
    out.parent.mkdir(parents=True, exist_ok=True)
    rows = write(out, tr.u, np.round(tr.y, 10))
    print(f"{out}: {rows} rows, {PATHS} paths x {HORIZON + 1} steps, failed paths: {int((tr.failed_at >= 0).sum())}")
    return out


if __name__ == "__main__":
    main()

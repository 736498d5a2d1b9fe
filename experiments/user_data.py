"""Recorded data of a plant simulated by a researcher's own numpy code, not rdsexp's: the known truth a data run
is measured against (`model_calibration.py --data`, tests/experiment/test_simulated_estimator.py).

    x_{k+1} = (A0 + a_k E) x_k + b_k B u_k + w_k,   y_k = C x_k + v_k,
    a_k ~ U(-0.1, 0.1) (a parameter on A[0, 0]),  b_k ~ Bernoulli(0.75) (an actuator link),
    w_k, v_k ~ N(0, sd^2 I),  u_k = +-1 at random (open loop), x_0 = 0,

C the first `outputs` rows of I (2: both states, 1: the first only). The model file rdsexp identifies it with
(`model(outputs)`) states the structure and a prior guess of xi: U(-0.5, 0.5) for a_k, and a Bernoulli(0.5)
link for b_k. xi = (a, b); its true mean and std are TRUE_MEAN and TRUE_STD.

    python experiments/user_data.py OUT_DIR [--seed 0] [--paths 80] [--sd 0.01] [--outputs 2]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

A0, E, B = np.array([[0.9, 0.2], [-0.1, 0.8]]), np.array([[1.0, 0.0], [0.0, 0.0]]), np.array([1.0, 0.5])
TRUE_LAW = {"family": "independent", "components": [{"family": "uniform", "low": [-0.1], "high": [0.1]},
                                                    {"family": "bernoulli", "prob": [0.75]}]}
SD = 0.01                   # the process and output noise's sd (write's default)
TRUE_MEAN, TRUE_STD = np.array([0.0, 0.75]), np.array([0.2 / np.sqrt(12), np.sqrt(0.75 * 0.25)])


def model(outputs: int = 2) -> dict:
    """The model file (the `model` group of the plant-file schema): bases A_i, B_i, C and the prior guess of xi."""
    return {"name": f"user{outputs}", "A": [A0.tolist(), E.tolist(), np.zeros((2, 2)).tolist()],
            "B": [[[0.0], [0.0]], [[0.0], [0.0]], [[1.0], [0.5]]], "C": [np.eye(2)[:outputs].tolist()],
            "xi": {"family": "independent", "components": [{"family": "uniform", "low": [-0.5], "high": [0.5]},
                                                            {"family": "bernoulli", "prob": [0.5]}]}}


def write(path, seed: int, paths: int = 80, steps: int = 101, sd: float = SD, outputs: int = 2) -> Path:
    """The recorded (u, y) of `paths` paths x `steps` steps in rdsexp's data format (CSV), from default_rng(seed)."""
    rng = np.random.default_rng(seed)
    u = rng.choice([-1.0, 1.0], (paths, steps))
    a, b = rng.uniform(-0.1, 0.1, (paths, steps)), rng.random((paths, steps)) < 0.75
    x, rows = np.zeros((paths, 2)), []
    for k in range(steps):
        y = x[:, :outputs] + sd * rng.standard_normal((paths, outputs))
        rows.append(np.column_stack([np.arange(paths), np.full(paths, k), u[:, k], y]))
        A = A0 + a[:, k, None, None] * E
        x = (A @ x[..., None])[..., 0] + (b[:, k] * u[:, k])[:, None] * B + sd * rng.standard_normal((paths, 2))
    table = np.concatenate(rows)
    table = table[np.lexsort((table[:, 1], table[:, 0]))]
    frame = pd.DataFrame(table, columns=["path", "k", "u[0]", *[f"y[{i}]" for i in range(outputs)]])
    frame.astype({"path": int, "k": int}).to_csv(path, index=False)
    return Path(path)


def write_config(config_dir, outputs: int = 2) -> str:
    """The model file into config_dir/model, and the plant group's `recorded` (no system: rdsexp's defaults for a
    system of one's own), in config_dir (a Hydra search path); returns the model's name."""
    spec = model(outputs)
    for group in ("model", "plant"):
        (Path(config_dir) / group).mkdir(parents=True, exist_ok=True)
    (Path(config_dir) / "model" / f"{spec['name']}.yaml").write_text(yaml.safe_dump(spec))
    (Path(config_dir) / "plant" / "recorded.yaml").write_text("name: recorded\n")
    return spec["name"]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--paths", type=int, default=80)
    parser.add_argument("--sd", type=float, default=SD)
    parser.add_argument("--outputs", type=int, default=2, choices=(1, 2))
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    name = write_config(args.out, args.outputs)
    data = write(args.out / f"user_{args.seed}.csv", args.seed, args.paths, sd=args.sd, outputs=args.outputs)
    print(f"{data} (model={name}; rdsexp --config-dir {args.out} data={data} model={name})")


if __name__ == "__main__":
    main()

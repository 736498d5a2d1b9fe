"""experiments/model_calibration.py's bookkeeping on hand-made rows: a study kept in parts pools into one table."""
import sys

import numpy as np
from conftest import REPO

sys.path.insert(0, str(REPO / "experiments"))
import model_calibration  # noqa: E402


def test_model_calibration_rows_kept_in_parts_pool_into_the_table_of_the_whole(tmp_path):
    """A study split over processes (--rows, --seed-from) and pooled (--pool) prints the numbers of one process that
    ran every seed: the rows' arrays, statuses and end-to-end figures survive the file; a later file's row wins.
    Failures are counted by their reason, not by the step and path they stopped at."""
    rng = np.random.default_rng(0)

    def row(status):
        out = {"status": status}
        if status is None or status.startswith("identification failed"):
            return out
        for what in ("mean", "std"):
            out[what], out[f"{what}_sd"] = rng.normal(size=3), rng.random(3) + 0.1
        out["true_std"] = np.array([0.5, 0.0, 2.0])
        if status == "weakly_identified":
            out["std_sd"][1] = np.nan                           # a component without a stated sd
        out |= {"e2e": 1 + rng.random(), "e2e_kind": "cost x"}
        return out
    statuses = ["ok", "weakly_identified", "identification failed at k = 3 (path 0): the plant state diverged", "ok",
                "misfit", None, "identification failed at k = 41 (path 2): the plant state diverged", "ok"]
    rows = {"a": [row(s) for s in statuses], "b": [row(s) for s in statuses[:4]]}
    first, second = tmp_path / "first.jsonl", tmp_path / "second.jsonl"
    model_calibration.save(rows["a"][:3], first, "a", range(3))
    model_calibration.save(rows["b"], first, "b", range(4))
    model_calibration.save([row("ok")], second, "a", [3])           # replaced by the last file's row for seed 3
    model_calibration.save(rows["a"][3:], second, "a", range(3, len(statuses)))
    pooled = model_calibration.pooled([str(first), str(second)])
    whole = {name: model_calibration.summarize(r) for name, r in rows.items()}
    assert list(pooled) == ["a", "b"]
    assert pooled["a"]["status"] == {"ok": 3, "weakly_identified": 1, "misfit": 1, "None": 1,     # failures by reason
                                     "identification failed: the plant state diverged": 2}
    for name in whole:
        assert pooled[name].keys() == whole[name].keys()
        for key, value in whole[name].items():
            np.testing.assert_array_equal(pooled[name][key], value)

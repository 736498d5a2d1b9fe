"""The run summary's words about the loop: its controller and why its verdict differs from the gain's rate."""
from rdsexp.experiment.summary import estimator_lines, gap, held_gains, identification_lines, initial_gain, lost_paths


def summary(estimate, verdict="unstable", rate=0.6, reason="the loop grows"):
    return {"rate_plant": rate, "closed_loop_verdict": verdict, "closed_loop_verdict_reason": reason,
            "closed_loop_estimation": {"estimate": estimate, "x_error_rms": 2.5, "rms_k_to": 6.0}}


def test_the_gap_names_the_estimate_the_feedback_uses():
    assert "estimate x_{k|k-1}: its error RMS 2.5" in gap(summary("predicted"))[0]
    assert "estimate x_{k|k}: its error RMS 2.5" in gap(summary("filtered"))[0]


def test_no_gap_when_the_verdict_agrees_or_the_floor_explains_it():
    assert gap(summary("filtered", verdict="stable")) == []
    assert gap(summary("filtered", verdict="undetermined", reason="the window ends at the noise floor")) == []
    assert gap(summary("filtered", verdict="unstable", rate=1.2)) == []
    assert "exact rate is 1.2000 >= 1" in gap(summary("filtered", verdict="stable", rate=1.2))[0]


def test_the_gap_says_whether_the_outputs_or_the_enkf_fall_short():
    # the exact rate of the loop through y with the best linear observer found decides whose gap it is
    s = summary("filtered")
    assert gap(s)[0].endswith("the gap is the observer's")                   # not computed (e.g. random C)
    s["closed_loop_through_y"] = {"rate": 1.0328, "kalman_rate": 1.05}
    assert "the gap is the outputs'" in gap(s)[0] and "exact rate 1.0328 >= 1" in gap(s)[0]
    s["closed_loop_through_y"] = {"rate": 0.9361, "kalman_rate": 0.94}
    assert "the gap is the EnKF's" in gap(s)[0] and "exact rate 0.9361 < 1" in gap(s)[0]


def test_the_online_start_names_the_law_its_nominal_gain_was_designed_on():
    start = {"initial": "nominal", "method": "ms_lqr", "nominal_law": "start", "rate_on_law": 0.90483}
    assert initial_gain(start) == "the nominal gain, ms_lqr at the law its EnKF starts from (exact rate there 0.9048)"
    start |= {"method": "lqr_mean", "nominal_law": "guess", "rate_on_law": 0.5}
    assert initial_gain(start) == "the nominal gain, lqr_mean at xi_guess (exact rate there 0.5000)"
    assert initial_gain(start | {"used": "zero (no stabilizing nominal gain)"}) == "F = 0 (no stabilizing nominal gain)"
    assert initial_gain({"initial": "zero"}) == "F = 0" and initial_gain({"initial": "given"}) == "the given gain"


def test_the_online_paths_lost_say_whether_more_than_chance_explains():
    """The console's `online paths lost` line: the paths each loop lost alone and the paired test's verdict, at
    PAIRED_LEVEL; a count that differs by a path or two is within chance."""
    line = lambda on, off, p: lost_paths({"lost_online_only": on, "lost_offline_only": off, "lost_more_p": p})
    assert line(0, 0, 1.0) == "none by one loop alone"
    assert line(5, 0, 1 / 32) == ("5 by online alone, 0 by offline alone: online loses more than chance explains "
                                  "(paired sign test, p = 0.0312)")
    assert line(2, 0, 0.25) == "2 by online alone, 0 by offline alone: within chance (paired sign test, p = 0.25)"
    assert line(1, 3, 0.9375).endswith("within chance (paired sign test, p = 0.938)")


def test_the_gains_lost_paths_held_say_which_loop_grew():
    """Beside the lost paths: a gain unstable on the true plant held before a loss is counted; where every gain held
    is stable there, the line says the loop through the EnKF's estimate grew (or the switching), not one gain's
    ideal loop."""
    line = lambda unstable, worst: held_gains({"lost_held_unstable": unstable, "lost_held_rate_max": worst})
    assert line(3.0, 1.2345) == "3 lost path(s) held a gain unstable on the true plant before the loss (exact rate up to 1.2345)"
    assert line(1.0, None).endswith("(exact rate not finite)")
    assert line(0.0, 0.92891) == ("every gain the lost paths held is mean-square stable on the true plant (exact rate up to "
                                  "0.9289): what grew is the loop through the EnKF's estimate (or the switching "
                                  "between gains), not the ideal loop of any one gain")


def test_identification_paths_are_named_recorded_in_a_data_run_and_simulated_otherwise():
    left_out = {"count": 1, "of": 4, "reasons": {"diverged": 1}}
    assert "1 of 4 identification paths left out of the modeling (their EnKF estimate failed: diverged 1)" in \
        identification_lines({"identification_failed_paths": left_out})[0]
    assert "1 of 4 recorded paths left out" in identification_lines({"identification_failed_paths": left_out,
                                                                      "data": {"name": "d"}})[0]
    estimator = {"usable": [400, 398], "replicates": 400, "summary_mean": [0.7], "summary_std": [0.3],
                 "summary_paths": 4, "replicate_paths": 4}
    line = estimator_lines(estimator)[0]
    assert "read on 4 identification paths (their mean)" in line
    assert "matched over 2 x 400 replicates of the identification on the model, of 1 path each then 4" in line
    line = estimator_lines(estimator | {"replicate_paths": None, "recorded": True, "summary_paths": 60})[0]
    assert "read on 60 recorded paths" in line and "identification runs of the model replaying the recorded" in line

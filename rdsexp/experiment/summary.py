"""A run's summary in words, from its run.json: what the terminal shows at the end of a run."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..numerics.indirect import WEAK
from ..numerics.synthesis import status_meaning
from ..numerics.verdict import ABOVE_FLOOR, AT_FLOOR, FAILURES, PAIRED_LEVEL
from .config import PRIORS
from .store import layout


def summary_text(info: dict, run_dir: Path) -> str:
    """A run's summary as the terminal shows it, a few lines: the plant and model, the key numbers
    (beside the reference numbers when the config carries them), plainly what failed, the run
    directory, its figure and how to view its recording."""
    s = info.get("summary", {})
    lines = [*header_lines(info, s), *identification_lines(s), *model_lines(s), *gain_lines(s), *data_lines(s),
             *design_lines(s), *loop_lines(s), *online_lines(s)]
    reused = stages_reused_text(info)
    if reused:
        lines.append(f"  {reused}")
    lines.append(f"  run directory: {run_dir}")
    if (run_dir / layout.FIGURE).exists():
        lines.append(f"  figure: {run_dir / layout.FIGURE}")
    if (run_dir / layout.RECORDING).exists():
        lines.append(f"  view: rerun {run_dir / layout.RECORDING}")
    return "\n".join(lines)


def fmt(v) -> str:
    return "n/a" if v is None else (f"{v:.4f}" if isinstance(v, float) else str(v))


def interval(r) -> str:
    """A rate with its 95% interval, [rate, low, high]."""
    return (f"{r[0]:.4f} [{r[1]:.4f}, {r[2]:.4f}]" if r and np.all(np.isfinite(r))
            else "n/a (not every path reached the window)")


def beside(s: dict, name: str) -> str:
    """The reference's number for `name` (a paper's), in parentheses, where the config carries one."""
    ref = s.get("reference") or {}
    return f" ({ref.get('source', 'paper')} {ref[name]})" if name in ref else ""


def unstable(rate) -> bool:
    return rate is not None and not rate < 1          # NaN too: not shown to be stable


def vec(v) -> list:
    return np.round(v, 4).tolist()


def header_lines(info: dict, s: dict) -> list[str]:
    """The run, its status, the plant and model or the data file, and the error of a failed run."""
    lines = [f"rdsexp run {info.get('id')}: {info.get('status')}" + (
        f" (reused run {info['reused_from']}: the same config and code version, nothing computed)"
        if info.get("reused_from") else "")]
    if s.get("plant"):                    # a run that failed before its summary has none
        lines.append(f"  plant {s['plant']}, model {s.get('model')}")
    elif s.get("data"):                   # a data run: the recorded data in place of a plant
        d = s["data"]
        lines.append(f"  data {d['name']} (sha256 {d['sha256'][:12]}, {d['rows']} rows, {d['paths']} paths x "
                     f"{d['steps']} steps; {d['identification_paths']} identify, {d['holdout_paths']} held out), "
                     f"model {s.get('model')}; no plant: every rate below is exact on the identified model")
    if info.get("error"):
        lines.append(f"  failed: {info['error']} (traceback in run.json and rdsexp.log)")
    return lines


def identification_lines(s: dict) -> list[str]:
    """How the plant was driven, the recorded paths left out, the iterated identification's passes."""
    lines = []
    prior = s.get("prior") or {}
    if prior.get("used_by"):          # the prior guess of xi, where stages stand on it
        lines.append(f"  prior guess of xi {vec(prior['xi_guess'])}: {PRIORS.get(prior['source'], prior['source'])}; "
                     f"used by {', '.join(prior['used_by'])}")
    ident = s.get("identification_feedback") or {}
    if ident.get("mode", "none") != "none":
        line = f"  identification feedback {ident['mode']}: {ident.get('used')}"
        if "open_loop_rate_at_guess" in ident:
            line += f" (open-loop rate at xi_guess {fmt(ident['open_loop_rate_at_guess'])})"
        if "open_loop_diverged_at" in ident:
            why = FAILURES.get(ident.get("open_loop_failure", "diverged"), "it diverged")
            line += f"; in open loop {why} at k = {ident['open_loop_diverged_at']}, identified again"
        if ident.get("used", "").startswith("nominal"):
            line += f", gain {ident.get('method')} with rate {fmt(ident.get('rate_plant'))} on the true plant"
            if unstable(ident.get("rate_plant")):
                line += " (it does not stabilize the true plant in mean square)"
        lines.append(line)
    if s.get("identification_failed_paths"):          # paths left out of the modeling
        f = s["identification_failed_paths"]
        lines.append(f"  {f['count']} of {f['of']} {paths_word(s)} paths left out of the modeling (their EnKF estimate "
                     f"failed: " + ", ".join(f"{r} {c}" for r, c in f["reasons"].items()) + ")")
    passes = s.get("identification_passes")
    if passes:
        line = (f"  identification iterated: from {passes['first']}, {passes['passes']} run(s) drawing xi i.i.d. "
                f"from the previous run's moments, ")
        line += "converged" if passes["converged"] else "stopped before the moments settled"
        if passes.get("last_change") is not None:
            line += f" (last change {passes['last_change']:.3g}, tolerance {passes['tolerance']:g})"
        if passes.get("failed"):
            line += f"; a further run failed ({passes['failed']}), its previous moments kept"
        lines.append(line)
    return lines


def model_lines(s: dict) -> list[str]:
    """The modeled moments of xi beside the plant file's law, or why there is no model."""
    lines = []
    if "xi_mean" in s:       # a status with moments (`results.MODELED`)
        lines.append(f"  modeling {s['modeling_status']}: xi mean {vec(s.get('xi_mean', []))}{beside(s, 'xi_mean')}, "
                     f"nbar {s.get('nbar')}{beside(s, 'nbar')}")
        estimator = s.get("modeling_estimator") or {}
        if estimator.get("name") == "simulated":
            lines += estimator_lines(estimator)
        if "xi_std" in s:
            line = f"    modeled xi std {vec(s['xi_std'])}"
            if s.get("modeling_covariance") == "total" and estimator.get("name", "paper") == "paper":
                line += " (the spread of xi_{k|k} plus the EnKF's mean filtered spread)"
            if "xi_corr" in s:
                line += f", correlation {vec(s['xi_corr'])}"
            if "plant_xi_mean" in s:
                line += f"; the plant file's xi: mean {vec(s['plant_xi_mean'])}, std {vec(s['plant_xi_std'])}"
                line += f", correlation {vec(s['plant_xi_corr'])}" if "plant_xi_corr" in s else ""
            if "xi_crps" in s:           # a proper score of the modeled marginals against the plant's xi
                line += f"; CRPS {s['xi_crps']:.4f}"
            lines.append(line)
    elif s.get("modeling_status") is not None:
        lines.append(f"  no model: {s.get('modeling_status')}" +
                     ("; no gain designed, no closed loop" if s.get("synthesis_status") is None else ""))
    return lines


def paths_word(s: dict) -> str:
    """recorded (a data run's summary, or its modeling_estimator) or identification (a simulated run's)."""
    return "recorded" if s.get("data") or s.get("recorded") else "identification"


def drawn_over(u: dict) -> str:
    """What the modeled moments' draws (`modeling_uncertainty`) are draws of, in words."""
    words = {"paths": "bootstrap draws of the identification paths", "simulated replicates": "draws of their posterior",
             "the prior box": "draws of the prior box (no law matched the data)"}
    return words.get(u.get("over"), "block-bootstrap draws of the window")


def estimator_lines(estimator: dict) -> list[str]:
    """The simulated estimator's account (`modeling_estimator`): what the window read, the replicates, and what the
    statuses at_prior_edge and weakly_identified name."""
    lines = []
    usable = " and ".join(map(str, estimator["usable"]))
    several = estimator.get("summary_paths")       # the mean of several identification paths' summaries
    read = f"on {several} {paths_word(estimator)} paths (their mean) " if several else ""
    runs = "identification runs of the model" + (" replaying the recorded inputs" if estimator.get("recorded") else "")
    if estimator.get("replicate_paths"):        # a simulated run's identification.paths, after a first round of one
        runs = f"replicates of the identification on the model, of 1 path each then {estimator['replicate_paths']}"
    runs += {"random_shapes": ", each in a law of random shape",
             "normal": ", each in a normal law"}.get(estimator.get("replicate_laws"), "")
    line = (f"    modeled by simulation: the window's xi_{{k|k}} read {read}mean {vec(estimator['summary_mean'])}, "
            f"std {vec(estimator['summary_std'])}")
    if estimator["usable"]:                 # (no replicates where the summary itself is not finite)
        line += f"; matched over {len(estimator['usable'])} x {estimator['replicates']} {runs} " \
                f"({usable} identified)"
    if estimator.get("summary_filter", "random_walk") != "random_walk":
        line += f"; the window read from a run whose EnKF draws xi {estimator['summary_filter']}"
    lines.append(line + (f"; {estimator['fallback']}" if "fallback" in estimator else ""))
    if "noise_scale" in estimator:          # a data run: the replicates' noise, estimated
        noise = estimator["noise_scale"]
        lines.append(f"    the data's noise: {noise['median']:.3g} (95% {noise['low']:.3g}-{noise['high']:.3g}) times "
                     f"the noise the EnKF assumes (enkf.Q's x block and enkf.R), within the prior "
                     f"{noise['box'][0]:g}-{noise['box'][1]:g}")
    if estimator.get("misfit"):
        m = estimator["misfit"]
        lines.append(f"    misfit: no law the replicates tried reproduces the data's {m['summary']} ({m['z']:+.1f} sds "
                     f"off the posterior mean law's, bound {m['bound']:g}): the window's moments of xi_{{k|k}} kept. "
                     f"The model's structure, the noise the EnKF assumes, or (data recorded under feedback) the "
                     f"replicates' open-loop replay of the recorded inputs differ from what made the data")
    if estimator.get("at_prior_edge"):
        wider = f"identification.prior_width={2 * estimator['prior_width']:g}"
        lines.append(f"    the prior box, not the data, stops the posterior of "
                     f"{', '.join(estimator['at_prior_edge'])}: the interval may be cut short ({wider} "
                     f"widens the box)")
    if estimator.get("weakly_identified"):
        lines.append(f"    weakly identified: the data hardly narrow the prior box of "
                     f"{', '.join(estimator['weakly_identified'])} (posterior sd above "
                     f"{WEAK:g} of the box's): the interval is the box, the value its middle")
    if estimator.get("correlations"):       # theta's correlations left to the prior box
        lines.append(f"    correlations {estimator['correlations']}")
    return lines


def gain_lines(s: dict) -> list[str]:
    """The loop's gain: the fallback, the choice against the identification's gain, the moments' spread, and
    the gain's rates (a data run: every design's on the identified model)."""
    lines = []
    if s.get("gain_fallback"):
        f = s["gain_fallback"]
        lines.append(f"  gain {f['instead_of']}: not_applicable ({f['because']}); the loop uses gain.fallback "
                     f"{f['method']}")
    if s.get("gain_choice"):           # the designed gain against the identification's, over the moments' draws
        c = s["gain_choice"]
        lines.append(f"  gain choice: {'kept the identification gain' if c['kept'] == 'identification' else 'designed'}"
                     f"; exact rate's {c['quantile']:.0%} quantile over {c['draws']} draws of the modeled moments: "
                     f"designed {c['designed_quantile']:.4f}, identification's {c['identification_quantile']:.4f} "
                     f"(medians {c['designed_median']:.4f}, {c['identification_median']:.4f}; worst "
                     f"{c['designed_worst']:.4f}, {c['identification_worst']:.4f})")
    if s.get("modeling_uncertainty"):
        u = s["modeling_uncertainty"]
        lines.append(f"    modeled moments' spread over {u['resamples']} {drawn_over(u)}: xi mean "
                     f"sd {np.round(u['xi_mean_sd'], 4).tolist()}, xi std sd {np.round(u['xi_std_sd'], 4).tolist()}"
                     + (f", xi correlation sd {np.round(u['xi_corr_sd'], 4).tolist()}" if "xi_corr_sd" in u else ""))
    if s.get("noise_sensitivity"):     # the moments with the EnKF's assumed noise scaled
        v = s["noise_sensitivity"]
        each = lambda rows: " / ".join(str(vec(r)) for r in rows)
        factors = " / x".join(f"{c:g}" for c in v["scales"])
        lines.append(f"    with the EnKF's assumed noise (enkf.Q's x block and R) x{factors}: xi mean "
                     f"{each(v['xi_mean'])}, xi std {each(v['xi_std'])}")
        if (v.get("range_over_sd") or 0) > 2:
            lines.append(f"    the assumed noise moves the moments {v['range_over_sd']:.0f} times their bootstrap sd: "
                         f"set enkf.Q.x and enkf.R to the noise the data carry")
    if s.get("design_rates"):          # a data run: each design on the identified model, over the moments' draws
        for method, r in s["design_rates"].items():
            line = f"  design {method}: {r['status']}, exact rate on the identified model {fmt(r.get('rate_model'))}"
            if r.get("draws"):
                line += (f" (over {r['draws']} draws of the moments: median {fmt(r['rate_model_median'])}, 5-95% "
                         f"{fmt(r['rate_model_q05'])}-{fmt(r['rate_model_q95'])}, worst {fmt(r['rate_model_worst'])})")
            lines.append(line)
    elif s.get("data") is None and s.get("synthesis_status") is not None:
        lines.append(f"  gain {s.get('gain_method')}: {s.get('synthesis_status')}, lambda {fmt(s.get('lam'))}"
                     f"{beside(s, 'lam')}, exact rate on the true plant {fmt(s.get('rate_plant'))}")
        if s.get("cost_ratio_plant") is not None:         # the end-to-end figure: against the law's optimum
            lines.append(f"    on the true plant against the optimum for its law: LQ cost x{s['cost_ratio_plant']:.4f}")
        if s.get("rate_excess_plant") is not None:
            lines.append(f"    on the true plant against the optimum for its law: rate +{s['rate_excess_plant']:.4f}")
        if s.get("rate_plant") is None:
            lines.append(f"  no stabilizing gain: {s.get('gain_method')} returned none "
                         f"({s.get('synthesis_status')}); no closed loop")
        elif s.get("synthesis_status") == "not_ms_stabilizable":
            lines.append(f"  no stabilizing gain: not_ms_stabilizable, the best rate found on the model is "
                         f"{fmt(s.get('lam'))}")
        elif unstable(s.get("rate_plant")):
            lines.append(f"  the gain does not stabilize the true plant: its exact rate there is "
                         f"{fmt(s.get('rate_plant'))} >= 1")
    return lines


def data_lines(s: dict) -> list[str]:
    """A data run's held-out validation and its loops simulated on the identified model."""
    lines = []
    if s.get("validation"):            # a data run's held-out paths: the modeled law against the nominal model
        v = s["validation"]
        law = lambda name: (f"{name} CRPS {v[name]['crps']:.4g}, coverage {v[name]['coverage_50']:.2f} (50%) "
                            f"{v[name]['coverage_90']:.2f} (90%)")
        lines.append(f"  validation on {v['paths']} held-out paths, y_k one step ahead, k={v['k_from']}..{v['k_to']}: "
                     f"{law('modeled')}; {law('nominal')} (xi at its mean): the modeled law is "
                     f"{'better' if v['modeled_better'] else 'not better'} by CRPS")
        if "calibrated" in v:
            slack = "/".join(f"{x:.2f}" for x in v["coverage_slack"])
            wrong = ": the law, or the noise the EnKF assumes, is wrong for these data"
            lines.append(f"    the modeled law's predictive is {'calibrated' if v['calibrated'] else 'NOT calibrated'}"
                         f": its coverage is {'within' if v['calibrated'] else 'outside'} {slack} of 50% / 90%"
                         + ("" if v["calibrated"] else wrong))
            noise = (s.get("modeling_estimator") or {}).get("noise_scale")
            if not v["calibrated"] and noise:
                lines.append(f"    (the simulated estimator puts the data's noise at {noise['median']:.3g} (95% "
                             f"{noise['low']:.3g}-{noise['high']:.3g}) times the EnKF's: set enkf.Q.x and enkf.R to "
                             f"the noise your sensors and process carry)")
    for name, r in (s.get("loops_on_model") or {}).items():      # data.loops: on the identified model
        if isinstance(r, dict):
            w = s["loops_on_model"]["rate_window"]
            lines += [f"  {name.replace('_', ' ')} ({s['loops_on_model']['label']}), rate k={w[0]}..{w[1]}: "
                      f"{interval(r['rate'])}, ideal loop on the model {fmt(r['exact_rate'])}: {r['verdict']}",
                      f"    {r['verdict_reason']}"]
    return lines


def design_lines(s: dict) -> list[str]:
    """The other designs whose status is not plain, and what each status shown means."""
    lines = []
    others = {m: st for m, st in (s.get("designs") or {}).items()
              if m != s.get("gain_method") and st not in ("optimal", "designed")}
    if others and not s.get("design_rates"):          # a data run lists every design above
        lines.append("  other designs: " + ", ".join(f"{m} {st}" for m, st in others.items()))
    statuses = [s["synthesis_status"]] if s.get("synthesis_status") is not None else []
    for status in dict.fromkeys(statuses + list(others.values())):     # what each status shown means
        lines.append(f"    {status}: {status_meaning(status)}")
    return lines


def loop_lines(s: dict) -> list[str]:
    """The rate window, the loop's controller, and each loop's rate, interval, ideal rate and verdict."""
    lines = []
    k_from, k_to = s.get("rate_window") or (None, None)
    if k_from is not None and "closed_loop_status" in s:
        source = s.get("rate_window_source")
        measured = s.get("noise_floor") is not None and not np.isnan(s["noise_floor"])
        floor = f"{s['noise_floor']:.3g}" if measured else "(not measured)"
        lines.append(f"  rate window k={k_from}..{k_to}: " + (
            "from the config" if source == "config" else
            f"auto, after the disturbance, while the ideal loop's exact curve is {ABOVE_FLOOR:g} and this loop "
            f"{2 * AT_FLOOR:g} times above the noise floor {floor} (the closed loop at rest)" if source == "auto"
            else f"none: after the disturbance the ideal loop ({ABOVE_FLOOR:g} floors) and this loop "
                 f"({2 * AT_FLOOR:g} floors) are not both above the noise floor {floor} for a step; the rates over "
                 f"the rest of the horizon are shown, not judged"))
    if s.get("loop") and "closed_loop_status" in s:           # what the loop's controller is
        c = s["loop"]
        lines.append(f"  loop: u_k = F {'x_{k|k}' if c['estimate'] == 'filtered' else 'x_{k|k-1}'} + d_k, the EnKF "
                     f"{'told' if c['filter_sees_disturbance'] else 'not told'} d_k, its xi "
                     f"{'drawn from the design moments' if c['observer_xi'] == 'model' else 'a random walk'}")
    lines += looks_line(s)
    for loop, label in (("closed_loop", "closed loop"), ("open_loop", "open loop  "), ("online", "online     ")):
        if f"{loop}_status" not in s:
            continue
        line = f"  {label} rate k={k_from}..{k_to}: {interval(s.get(f'{loop}_rate'))}"
        if loop == "closed_loop":
            line += beside(s, "closed_loop_rate")
        if s.get(f"{loop}_exact_rate") is not None and np.isfinite(s[f"{loop}_exact_rate"]):
            line += f", ideal loop {s[f'{loop}_exact_rate']:.4f}"
        lines += [f"{line}: {s.get(f'{loop}_verdict')}", f"    {s.get(f'{loop}_verdict_reason')}"]
        if loop == "closed_loop":
            lines += gap(s)
    return lines


def looks_line(s: dict) -> list[str]:
    """closed_loop.paths auto: the paths the loops were judged on, and why the looks stopped there."""
    looks = s.get("loop_looks")
    if not looks:
        return []
    asking = [name.replace("_", " ") for name in s.get("loop_paths_asking") or ()]
    why = f"the budget closed_loop.max_paths reached, {' and '.join(asking)} asking for more" if asking else \
        "the pilot decided" if len(looks) == 1 else "every verdict settled"
    return [f"  paths: auto, judged on {' then '.join(str(look['paths']) for look in looks)} ({why}); intervals at "
            f"{100 * looks[-1]['level']:g}%, the 5% shared by the looks"]


def online_lines(s: dict) -> list[str]:
    """controller=online: the final gains against the offline gain and the optimum, the start, the paths lost
    and the probe."""
    if not s.get("online"):
        return []
    o, k_from = s["online"], (s.get("rate_window") or (None, None))[0]
    num = lambda v: "nan" if v is None else f"{v:.4f}"
    lines = [f"  online final gains: exact rate on the true plant median {num(o['final_rate_plant_median'])} "
             f"(10-90% {num(o['final_rate_plant_q10'])}-{num(o['final_rate_plant_q90'])}), "
             f"{100 * o['final_stable_fraction']:.0f}% stable, {o['adoptions_per_path']:.1f} adoptions per "
             f"path; offline gain {num(o['offline_rate_plant'])}, optimum {num(o['optimal_rate_plant'])}"]
    start = s.get("online_initial") or {}
    lines.append(f"  online start: {initial_gain(start)}")
    if o.get("lost_more_p") is not None:
        lines.append(f"  online paths lost: {lost_paths(o)}")
    if o.get("lost_held_unstable") is not None:
        lines.append(f"    {held_gains(o)}")
    probe = start.get("probe")
    if probe:                                         # controller.probe: say whether the window holds it
        amplitude, until = probe
        inside = until is None or (k_from is not None and until > k_from)
        lines.append(f"  online probe: +-{amplitude:g} on u until " + ("the end" if until is None else f"k={until}")
                     + ("; it reaches into the rate window, so the online rate measures the probed loop, not "
                        "its decay" if inside else ""))
    return lines


def initial_gain(start: dict) -> str:
    """The online loop's first gain, from the summary's `online_initial`: where it came from and, for the nominal
    gain, the law it was designed on and its exact rate there."""
    if start.get("initial") != "nominal":
        return {"zero": "F = 0", "given": "the given gain"}.get(start.get("initial"), str(start.get("initial")))
    if "used" in start:                                   # no stabilizing nominal design
        return "F = 0 (no stabilizing nominal gain)"
    law = {"start": "at the law its EnKF starts from", "guess": "at xi_guess"}.get(start.get("nominal_law"), "")
    scale = start.get("start_scale", 1.0)
    if law and scale < 1:                                 # the start law narrowed (`pipeline.stabilizable_start`)
        law += f" (its spread x {scale:g}: none is mean-square stable at the full one)"
    return f"the nominal gain, {start.get('method')} {law} (exact rate there {start.get('rate_on_law', np.nan):.4f})"


def held_gains(o: dict) -> str:
    """What the gains the online loop's lost paths held say of the loss: a gain unstable on the true plant, or only
    gains stable there, in which case the loop that grew is the one through the EnKF's estimate."""
    unstable, worst = int(o["lost_held_unstable"]), o["lost_held_rate_max"]
    if unstable:
        up_to = "not finite" if worst is None else f"up to {worst:.4f}"
        return f"{unstable} lost path(s) held a gain unstable on the true plant before the loss (exact rate {up_to})"
    return (f"every gain the lost paths held is mean-square stable on the true plant (exact rate up to {worst:.4f}): "
            f"what grew is the loop through the EnKF's estimate (or the switching between gains), not the ideal loop "
            f"of any one gain")


def lost_paths(o: dict) -> str:
    """The paths the online and offline loops lost alone (the same plant samples per path), with the exact paired
    test of "online loses more": a count that differs by a path or two says nothing on its own."""
    only_on, only_off, p = int(o["lost_online_only"]), int(o["lost_offline_only"]), o["lost_more_p"]
    if only_on + only_off == 0:
        return "none by one loop alone"
    more = "online loses more than chance explains" if p < PAIRED_LEVEL else "within chance"
    return f"{only_on} by online alone, {only_off} by offline alone: {more} (paired sign test, p = {p:.3g})"


def gap(s: dict) -> list[str]:
    """Why the closed loop's verdict differs from what the gain's exact rate promises, when it does:
    the exact rate is of the ideal loop (state feedback); the loop runs on the EnKF's estimate."""
    rate, verdict = s.get("rate_plant"), s.get("closed_loop_verdict")
    if rate is None or not np.isfinite(rate):
        return []
    est = s.get("closed_loop_estimation") or {}
    at_floor = "noise floor" in s.get("closed_loop_verdict_reason", "")       # the reason explains it itself
    if rate < 1 and (verdict in ("unstable", "failed") or verdict == "undetermined" and not at_floor):
        x_hat = {"predicted": "x_{k|k-1}", "filtered": "x_{k|k}"}.get(est.get("estimate"), "x_{k|k-1}")
        line = (f"    the gain stabilizes the plant with the true state (exact rate {rate:.4f}), this loop feeds back "
                f"the EnKF's estimate {x_hat}: its error RMS {est.get('x_error_rms', float('nan')):.3g} (the state's "
                f"RMS at the window's end {est.get('rms_k_to', float('nan')):.3g})")
        y = s.get("closed_loop_through_y") or {}
        if y.get("rate") is None:
            return [line + "; the gap is the observer's"]
        if y["rate"] >= 1:
            return [line + "; the gap is the outputs': with the best linear observer of y found (on the plant's "
                    f"mean) this gain's loop has exact rate {y['rate']:.4f} >= 1, y does not carry enough of the "
                    "state for it"]
        return [line + f"; the gap is the EnKF's: a linear observer of y (on the plant's mean) gives this gain's loop "
                f"exact rate {y['rate']:.4f} < 1"]
    if rate >= 1 and verdict == "stable":
        return [f"    the paths decay over this window although the gain's exact rate is {rate:.4f} >= 1: the ideal "
                f"loop's rate over the same window is {s.get('closed_loop_exact_rate', float('nan')):.4f} (a transient "
                f"of the window, or too few paths to see the growth)"]
    return []


def stages_reused_text(info: dict) -> str:
    """What the run loaded from the stage cache instead of computing it, and from which runs (run.json
    `stages_reused`), in one line; "" when nothing."""
    reused = info.get("stages_reused") or {}
    if not reused:
        return ""
    designs = [label for label, entry in reused.items() if entry.get("stage") == "synthesis"]
    parts = [label.replace("_", " ") for label in reused if label not in designs]
    if designs:
        parts.append(f"{len(designs)} design{'s' if len(designs) > 1 else ''}")
    runs = sorted({entry.get("run") for entry in reused.values()})
    origin = f"run {runs[0]}" if len(runs) == 1 else f"{len(runs)} runs"
    return f"reused from the stage cache ({origin}): {', '.join(parts)}"

"""The command line's own errors, each one line on stderr like rdsexp's config errors: a key no config
has, a YAML syntax error, Ctrl-C during a run or a sweep; and overrides on both sides of -m."""
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import SMALL, rdsexp, serial

TINY = ["closed_loop.paths=2", "enkf.ensemble_size=10", "closed_loop.horizon=20", "tracking.level=off"]


STAGE_LINE = re.compile(r"rdsexp: [a-z ]+ done in \d+\.\d s")     # a stage done (stderr is no terminal here)


def error_lines(stderr: str) -> list[str]:
    """stderr's lines but the stages' progress lines."""
    return [line for line in stderr.strip().splitlines() if not STAGE_LINE.fullmatch(line)]


def one_line(proc) -> str:
    """The only line on stderr (no traceback, no Hydra report around it) beside the stages' progress lines."""
    lines = error_lines(proc.stderr)
    assert len(lines) == 1, proc.stderr
    return lines[0]


@pytest.mark.parametrize("args, message", [
    (["enkf.ensemble_sze=50"], "enkf.ensemble_sze: no such key; did you mean enkf.ensemble_size?"),
    (["-m", "enkf.ensemble_sze=50,100"], "enkf.ensemble_sze: no such key; did you mean enkf.ensemble_size?"),
    (["enkf.initial.meen=0"], "enkf.initial.meen: no such key; did you mean enkf.initial.mean?"),
    (["seeed=3"], "seeed: no such key; did you mean seed?"),
    # outside rdsexp's groups `+` may add a key (check_overrides): Hydra's advice, in one line
    (["enkff.ensemble_size=3"], "enkff.ensemble_size: not in the config; to add it, use +enkff.ensemble_size=3"),
], ids=["run", "sweep", "nested", "top_level", "no_group"])
def test_unknown_key_without_plus_is_one_line_with_the_closest_key(tmp_path, args, message):
    proc = rdsexp(*args, *TINY, cwd=tmp_path, check=False)
    assert proc.returncode == 2
    assert one_line(proc) == f"rdsexp: config error: {message}"
    assert not (tmp_path / "outputs").exists()            # neither a run nor a sweep directory


def test_a_directory_named_like_a_key_in_the_config_dir_is_one_line(tmp_path):
    """A run store kept inside the --config-dir (DIR/store) is a config group to Hydra, which then refuses
    store=...: one line that says why, exit 2, nothing written."""
    (tmp_path / "conf" / "store").mkdir(parents=True)
    proc = rdsexp("--config-dir", str(tmp_path / "conf"), f"store={tmp_path / 'conf' / 'store'}", *TINY,
                  cwd=tmp_path, check=False)
    assert proc.returncode == 2
    assert one_line(proc) == ("rdsexp: config error: store: a directory named 'store' in the --config-dir is read "
                              "by Hydra as a config group and hides the key store; move it out of the config directory")
    assert not any((tmp_path / "conf" / "store").iterdir())


@pytest.mark.parametrize("args, message", [
    (["plant=bad"], "conf/plant/bad.yaml:3:5: mapping values are not allowed here"),
    (["-m", "plant=paper,unclosed"], "conf/plant/unclosed.yaml:4:1: expected ',' or ']', but got '<scalar>' "
                                     "(while parsing a flow sequence at line 2, column 4)"),
], ids=["run", "sweep"])
def test_yaml_syntax_error_is_one_line_with_file_line_and_column(tmp_path, args, message):
    (tmp_path / "conf" / "plant").mkdir(parents=True)
    (tmp_path / "conf" / "plant" / "bad.yaml").write_text("name: bad\nA: [[0.9]]\nB: a: 1\n")
    (tmp_path / "conf" / "plant" / "unclosed.yaml").write_text(
        "name: unclosed\nA: [[0.9, 0.1],\n    [0.0, 0.8]\nB: [[1.0], [0.0]]\n")
    proc = rdsexp("--config-dir", "conf", *args, *TINY, cwd=tmp_path, check=False)
    assert proc.returncode == 2
    assert one_line(proc) == f"rdsexp: config error: {message}"
    assert not (tmp_path / "outputs").exists()


@pytest.mark.slow
def test_overrides_on_both_sides_of_m_make_the_same_sweep(tmp_path):
    """`rdsexp enkf.ensemble_size=10,1 -m ...` is `rdsexp -m enkf.ensemble_size=10,1 ...` (argparse alone
    refuses the overrides after -m): the same two jobs, the second refused by the sweep's validation
    before any job runs (a cheap way to see every job's overrides)."""
    rest = [o for o in TINY if not o.startswith("enkf.ensemble_size")]
    before = rdsexp("enkf.ensemble_size=10,1", rest[0], "-m", *rest[1:], cwd=tmp_path, check=False)
    after = rdsexp("-m", "enkf.ensemble_size=10,1", *rest, cwd=tmp_path, check=False)
    assert before.returncode == after.returncode == 2
    assert one_line(before) == one_line(after) == (
        f"rdsexp: config error in sweep job enkf.ensemble_size=1 {' '.join(rest)}: "
        "enkf.ensemble_size: 1 is not allowed, expected an integer >= 2")


def test_hydra_full_error_keeps_the_traceback_and_the_environment(tmp_path, monkeypatch):
    from hydra.errors import ConfigCompositionException
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    assert rdsexp("enkf.ensemble_sze=50", cwd=tmp_path, check=False).returncode == 2
    assert "HYDRA_FULL_ERROR" not in os.environ             # set only while Hydra runs
    monkeypatch.setenv("HYDRA_FULL_ERROR", "1")
    with pytest.raises(ConfigCompositionException):
        rdsexp("enkf.ensemble_sze=50", cwd=tmp_path, check=False)
    assert os.environ["HYDRA_FULL_ERROR"] == "1"


def start(tmp_path, *args) -> subprocess.Popen:
    # SIGINT ignored by the parent (a test runner in the background): rdsexp must still stop on it
    return subprocess.Popen([sys.executable, "-m", "rdsexp", *serial(args)], cwd=tmp_path, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))


def status(path):
    try:
        return json.loads(path.read_text())["status"]
    except (OSError, ValueError, KeyError):
        return None


def interrupt_when(proc, started, timeout=60.0) -> str:
    """Send SIGINT once started() holds; returns the single stderr line after exit 130."""
    end = time.time() + timeout
    try:
        while not started():
            assert proc.poll() is None, proc.stderr.read()
            assert time.time() < end, "the run did not start"
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr
    lines = error_lines(stderr)
    assert len(lines) == 1, stderr
    return lines[0]


def store_passes_check(tmp_path) -> None:
    """`rdsexp-runs check` finds nothing damaged or inconsistent in tmp_path/outputs, and no temporary file
    is left there."""
    proc = rdsexp("check", "outputs", cwd=tmp_path, module="rdsexp.runs", check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert not list((tmp_path / "outputs").rglob("*.tmp"))


@pytest.mark.slow
def test_ctrl_c_during_a_run_is_one_line_and_exit_130(tmp_path):
    proc = start(tmp_path, "closed_loop.paths=400", "tracking.recording=false")   # some 15 s, stopped after 3
    line = interrupt_when(proc, lambda: any(status(p) == "incomplete" for p in tmp_path.glob("outputs/runs/*/run.json")))
    (run_json,) = tmp_path.glob("outputs/runs/*/run.json")
    assert status(run_json) == "interrupted"
    assert json.loads(run_json.read_text())["error"] == "interrupted by Ctrl-C (SIGINT) before it completed"
    assert line == (f'rdsexp: interrupted: run outputs/runs/{run_json.parent.name} stopped, its run.json says '
                    '"interrupted"; run the same command again to start it over')
    store_passes_check(tmp_path)


@pytest.mark.parametrize("launcher", [[], ["hydra/launcher=parallel"]], ids=["basic", "parallel"])
@pytest.mark.slow
def test_ctrl_c_during_a_sweep_leaves_a_store_that_passes_check_and_resumes(tmp_path, launcher):
    # parallel: the shipped sweeps' default (joblib); its workers' queues leave semaphores that Python's
    # resource tracker removes, without a word on stderr. The jobs still running get status "interrupted",
    # the summary agrees with the jobs, and the same command resumes: a sweep linked to the interrupted
    # one that holds every job (the completed ones as copies). Eight jobs: the Ctrl-C comes when the first has
    # completed, and the seven after it leave seconds for it to arrive on a loaded machine (with four, the
    # sweep once ended before the test's poll saw the first)
    args = ("+sweep=seeds", "seed=range(0,8)", *SMALL, "tracking.recording=false", "model.reported=null", *launcher)
    proc = start(tmp_path, *args)
    line = interrupt_when(proc, lambda: any(status(p) == "complete"
                                            for p in tmp_path.glob("outputs/sweeps/*/*/run.json")))
    (sweep,) = (tmp_path / "outputs" / "sweeps").iterdir()
    statuses = [status(p) for p in sweep.glob("*/run.json")]
    done = statuses.count("complete")
    assert 1 <= done < 8 and set(statuses) <= {"complete", "interrupted"}
    assert line == (f"rdsexp: interrupted: sweep outputs/sweeps/{sweep.name} stopped with {done} of 8 jobs "
                    "completed; run the same command again to resume: the completed jobs are reused")
    store_passes_check(tmp_path)
    resumed = rdsexp(*args, cwd=tmp_path)
    assert f"resuming sweep {sweep.name} (interrupted)" in resumed.stdout
    (new,) = set((tmp_path / "outputs" / "sweeps").iterdir()) - {sweep}
    from rdsexp.runs import search
    jobs = search(tmp_path / "outputs", f"sweep_id == '{new.name}'")
    assert sorted(jobs["seed"]) == list(range(8)) and set(jobs["status"]) == {"complete"}
    assert set(jobs["resumes"]) == {sweep.name}
    assert jobs["reused_from"].notna().sum() == done           # the completed jobs were not computed again
    store_passes_check(tmp_path)


def test_ctrl_c_that_breaks_hydras_cleanup_is_still_one_line_and_exit_130(monkeypatch, capsys):
    """A Ctrl-C inside Hydra's config reader can surface as an error of its cleanup (UnboundLocalError,
    the KeyboardInterrupt as its context; seen when a sweep's next job loaded its config): still Ctrl-C."""
    from rdsexp.errors import RunExit
    from rdsexp.experiment import cli

    def interrupted_in_cleanup():
        try:
            raise KeyboardInterrupt
        finally:
            raise UnboundLocalError("cannot access local variable 'f' where it is not associated with a value")
    monkeypatch.setattr(cli, "hydra_main", interrupted_in_cleanup)
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    # an earlier call in this process ran a sweep (relative to another directory): not this call's job
    monkeypatch.setattr(cli, "RUNNING", {"run_dir": Path("gone/0"), "sweep_dir": Path("outputs/sweeps/gone")})
    with pytest.raises(RunExit) as stop:
        cli.run_hydra_main()
    assert stop.value.code == 130
    assert capsys.readouterr().err.strip().splitlines() == ["rdsexp: interrupted before the run started; nothing "
                                                            "was recorded"]
    assert cli.interrupted_by(ValueError("a config error")) is False


@pytest.mark.parametrize("args, message", [
    (["plant=loss"], "plant=loss: no such plant; did you mean lossy?; options: cart_pole, dropout, lossy, "
                     "multiplicative, paper, recorded, two_carts"),
    (["gain=proposd"], "gain=proposd: no such gain; did you mean proposed?; options: lqr_mean, ms_lqr, nominal_lmi, "
                       "pole_placement, policy_iteration, proposed, robust_box"),
    (["+sweep=seed"], "sweep=seed: no such sweep; did you mean seeds?; options: "),
    (["-m", "plant=paper,zzz"], "plant=zzz: no such plant; options: cart_pole, dropout, lossy,"),
], ids=["plant", "gain", "sweep", "sweep_job"])
def test_a_misspelled_group_option_is_one_line_with_the_closest_options(tmp_path, args, message):
    """Hydra's 16-line report becomes one line: the closest options, then all of them (--config-dir ones too)."""
    (tmp_path / "conf" / "plant").mkdir(parents=True)
    (tmp_path / "conf" / "plant" / "lossy.yaml").write_text("name: lossy\nA: [[[0.9]]]\nB: [[[1.0]]]\n")
    proc = rdsexp("--config-dir", "conf", *args, *TINY, cwd=tmp_path, check=False)
    assert proc.returncode == 2
    assert one_line(proc).startswith(f"rdsexp: config error: {message}")
    assert not (tmp_path / "outputs").exists()


@pytest.mark.parametrize("spelling", ["--config-dir {}", "-cd {}", "--config-dir={}"])
def test_shell_completion_offers_the_plants_of_the_config_dir_on_the_line(tmp_path, monkeypatch, spelling):
    """`rdsexp --config-dir DIR plant=<TAB>` completes DIR's plant files too (the shell passes the line in
    COMP_LINE, not as arguments)."""
    (tmp_path / "conf" / "plant").mkdir(parents=True)
    (tmp_path / "conf" / "plant" / "lossy.yaml").write_text("name: lossy\nA: [[[0.9]]]\nB: [[[1.0]]]\n")
    monkeypatch.setenv("COMP_LINE", f"rdsexp {spelling.format(tmp_path / 'conf')} plant=")
    offered = rdsexp("-sc", "query=bash", cwd=tmp_path).stdout.split()
    assert "plant=lossy" in offered and "plant=paper" in offered
    monkeypatch.setenv("COMP_LINE", "rdsexp plant=")
    assert "plant=lossy" not in rdsexp("-sc", "query=bash", cwd=tmp_path).stdout.split()


def test_an_unknown_key_in_a_plant_file_is_one_line_naming_file_key_and_closest(tmp_path):
    """`Cc:` for `C:` would run with C = I (one output per state): a config error, exit 2, no run directory."""
    (tmp_path / "conf" / "plant").mkdir(parents=True)
    plant = tmp_path / "conf" / "plant" / "lossy.yaml"
    plant.write_text("name: lossy\nA: [[[0.9, 0.1], [0.0, 0.8]]]\nB: [[[0.0], [1.0]]]\nCc: [[[1, 0]]]\n")
    proc = rdsexp("--config-dir", "conf", "plant=lossy", *TINY, cwd=tmp_path, check=False)
    assert proc.returncode == 2
    assert one_line(proc) == f"rdsexp: config error: {plant}: unknown key Cc; did you mean C?"
    assert not (tmp_path / "outputs").exists()
    plant.write_text("name: lossy\nA: [[[0.9, 0.1], [0.0, 0.8]]]\nB: [[[0.0], [1.0]]]\nxii: {mean: [0], cov: [[1]]}\n")
    proc = rdsexp("--config-dir", "conf", "-m", "plant=lossy", "seed=1,2", *TINY, cwd=tmp_path, check=False)
    assert proc.returncode == 2 and "unknown key xii; did you mean xi?" in one_line(proc)
    assert not (tmp_path / "outputs").exists()

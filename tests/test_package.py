"""The package as users get it: layers, console scripts, --help, shell completion, installed configs."""
import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO, SMALL, import_source

import rdsexp as rx

PACKAGE = REPO / "rdsexp"
SCRIPTS = Path(sys.executable).parent


def module_name(path: Path) -> str:
    """rdsexp.experiment.store for rdsexp/experiment/store/__init__.py, rdsexp.errors for rdsexp/errors.py."""
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in PACKAGE.rglob("*.py") if "conf" not in p.relative_to(PACKAGE).parts[:1]}


def imported_modules(path: Path) -> set[str]:
    """Absolute names of the modules a source file imports, at any depth (inside functions too);
    relative imports resolved, and `from PACKAGE import module` named as the module it imports."""
    module = module_name(path)
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            target = import_source(node, package)
            submodules = {f"{target}.{alias.name}" for alias in node.names} & set(MODULES)
            names |= submodules
            if len(submodules) < len(node.names):
                names.add(target)
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
    return names


LAYER = {"errors": -1, "numerics": 0, "paper": 1, "experiment": 2, "report": 3}
FORBIDDEN_IN_NUMERICS = ("hydra", "omegaconf", "pandas", "pyarrow", "rerun", "matplotlib")


@pytest.mark.parametrize("path", sorted(MODULES.values()), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_only_go_downward(path):
    """Layers (docs/design.md): errors < numerics < paper < experiment < report, at any depth of a
    module (imports inside functions too); inside the experiment layer, EXPERIMENT's order."""
    layer = path.relative_to(PACKAGE).with_suffix("").parts[0]
    if layer not in LAYER:
        return                            # rdsexp/__init__.py, __main__.py, runs.py: the public entry points
    for name in imported_modules(path):
        parts = name.split(".")
        if parts[0] == "rdsexp" and len(parts) > 1 and parts[1] in LAYER:
            assert LAYER[parts[1]] <= LAYER[layer], f"{path.name} ({layer}) imports {name}"
        if layer == "numerics":
            assert parts[0] not in FORBIDDEN_IN_NUMERICS, f"numerics module {path.name} imports {name}"
        if layer == "experiment" and parts[:2] == ["rdsexp", "experiment"] and len(parts) > 2:
            here, there = path.relative_to(PACKAGE / "experiment").with_suffix("").parts[0], parts[2]
            if here != there and here != "__init__":
                assert EXPERIMENT.index(there) < EXPERIMENT.index(here), f"{path.name} ({here}) imports {name}"


# the experiment layer from the bottom up: each module imports only those before it
EXPERIMENT = ["metrics", "store", "schema", "data", "config", "montecarlo", "pipeline", "summary", "recording", "figure",
              "runner",
              "failures", "catalog", "sweep", "cli"]


# run.json's readers: only the store reads run.json; every other module, and every script of experiments/, reads
# runs through the catalog's API (rdsexp.runs: search, load, record, open_run) or RunStore and Run, whose `record` is
# the typed RunRecord (parsed at the store's boundary with the fixes for older records): fields, not run.json's keys
STORE_READERS = {"read_run", "read_runs", "read_table", "run_damage", "intact_runs", "RUN_JSON"}
EXPERIMENTS = REPO / "experiments"
# experiments/fingerprint.py hashes the stored files themselves (a refactoring's proof of identical results);
# benchmark_store.py and benchmark_caches.py build stores of copied run.json files to time the store's own reading
# of them
RAW_RECORD_SCRIPTS = {"fingerprint.py", "benchmark_store.py", "benchmark_caches.py"}
# `.info` that is no run's run.json: a numerics result's solver details (SynthesisResult.info), a data file's
# description (exp.data.data.info), MLflow's RunInfo (run.info.run_id, ...), logging (log.info(...), logger.info)
NOT_A_RUN = {"res", "pi", "lq", "prop", "chosen", "exp.data.data", "log", "logger"}
MLFLOW_RUN_INFO = {"run_id", "status", "start_time", "end_time", "run_name", "experiment_id", "lifecycle_stage"}


def run_readers() -> list[Path]:
    """The package's modules outside the store, and experiments/'s scripts but those of RAW_RECORD_SCRIPTS."""
    modules = [p for p in sorted(MODULES.values()) if (PACKAGE / "experiment" / "store") not in p.parents]
    return modules + [p for p in sorted(EXPERIMENTS.glob("*.py")) if p.name not in RAW_RECORD_SCRIPTS]


def raw_record_reads(tree: ast.AST) -> list[str]:
    """`X.info` and `X._info` reads that can be a run's raw run.json (every one but NOT_A_RUN's, MLflow's
    RunInfo fields and calls such as log.info(...)), as source text."""
    calls = {id(node.func) for node in ast.walk(tree) if isinstance(node, ast.Call)}
    mlflow = {id(node.value) for node in ast.walk(tree)
              if isinstance(node, ast.Attribute) and node.attr in MLFLOW_RUN_INFO}
    return [ast.unparse(node) for node in ast.walk(tree)
            if isinstance(node, ast.Attribute) and node.attr in ("info", "_info") and id(node) not in calls
            and id(node) not in mlflow and ast.unparse(node.value) not in NOT_A_RUN]


@pytest.mark.parametrize("path", run_readers(), ids=lambda p: str(p.relative_to(REPO)))
def test_only_the_store_reads_run_json(path):
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and "store" in (node.module or "").split("."):
            used = {alias.name for alias in node.names} & STORE_READERS
            assert not used, f"{path.name} imports {used} from the store: use RunStore / Run"
        if isinstance(node, ast.Attribute):
            assert node.attr not in STORE_READERS, f"{path.name} uses {node.attr}: use RunStore / Run"
        if isinstance(node, ast.Constant) and node.value == "run.json" and path.name != "__init__.py":
            pytest.fail(f"{path.name} names run.json: use RunStore / Run")
    raw = raw_record_reads(tree)
    assert not raw, f"{path.name} reads a run's raw run.json ({', '.join(raw)}): use Run.record's fields"


def test_the_run_json_rule_finds_raw_reads():
    """The rule above would fail on what it forbids, and passes what is no run."""
    found = raw_record_reads(ast.parse("run.info.get('summary'); Run(d)._info['id']; x = job.info\n"
                                       "log.info('x'); res.info['solves']; there.info.run_id"))
    assert sorted(found) == ["Run(d)._info", "job.info", "run.info"]


def test_experiment_order_names_every_module():
    found = {p.relative_to(PACKAGE / "experiment").with_suffix("").parts[0]
             for p in (PACKAGE / "experiment").rglob("*.py") if p.name != "__init__.py" or p.parent.name == "store"}
    assert found == set(EXPERIMENT)


def test_no_import_cycles():
    """No module imports itself through others, counting imports inside functions (Tarjan's SCCs)."""
    graph = {m: sorted(n for n in imported_modules(p) if n in MODULES and n != m) for m, p in MODULES.items()}
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))
    for v in graph:
        if v not in index:
            visit(v)
    assert not cycles, cycles


def test_store_layout_default_is_the_config_default():
    from omegaconf import OmegaConf

    from rdsexp.experiment.store import layout
    assert OmegaConf.load(REPO / "conf" / "config.yaml").store == layout.DEFAULT_ROOT


def test_numerics_api_and_version():
    """`import rdsexp` is the numerics API and loads none of the experiment layer's libraries."""
    assert rx.__version__.count(".") == 2
    for name in ("AffineRandomSystem", "MomentModel", "synthesize", "ms_rate", "second_moments", "empirical_rate"):
        assert callable(getattr(rx, name))
    out = subprocess.run([sys.executable, "-c", "import sys, rdsexp; print(any(m.startswith(('hydra', 'pandas', 'rerun', "
                          "'matplotlib')) for m in sys.modules))"], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_console_scripts_behave_like_python_m(tmp_path):
    help_script = subprocess.run([SCRIPTS / "rdsexp", "--help"], capture_output=True, text=True, check=True).stdout
    help_module = subprocess.run([sys.executable, "-m", "rdsexp", "--help"], capture_output=True, text=True,
                                 check=True).stdout
    assert help_script == help_module
    # the help page: the tool, the groups with their options, examples, outputs; no matrices
    for text in ("rdsexp: experiments on linear random dynamical systems", "gain: ", "policy_iteration",
                 "sweep: ", "== Examples ==", "--config-dir DIR plant=NAME", "== Outputs =="):
        assert text in help_script
    assert "[[" not in help_script and len(help_script.splitlines()) < 60
    runs_script = subprocess.run([SCRIPTS / "rdsexp-runs", "list", str(tmp_path)], capture_output=True, text=True)
    runs_module = subprocess.run([sys.executable, "-m", "rdsexp.runs", "list", str(tmp_path)], capture_output=True,
                                 text=True)
    assert (runs_script.returncode, runs_script.stdout) == (runs_module.returncode, runs_module.stdout)


def test_fast_help_is_hydras_help(tmp_path, capsys):
    """`rdsexp --help` reads file names instead of composing: the same page as Hydra's (printed by
    Hydra when another search path is given), a user's --config-dir groups included."""
    from rdsexp.experiment.cli import help_text
    (tmp_path / "mine" / "plant").mkdir(parents=True)
    shutil.copy(REPO / "conf" / "plant" / "dropout.yaml", tmp_path / "mine" / "plant" / "lossy.yaml")
    argv = ["--config-dir", str(tmp_path / "mine"), "--help"]
    fast = help_text(argv)
    assert "plant: cart_pole, dropout, lossy," in fast and help_text([*argv, "hydra.searchpath=[]"]) is None
    hydra_page = subprocess.run([SCRIPTS / "rdsexp", *argv, "hydra.searchpath=[]"], capture_output=True, text=True,
                                check=True).stdout
    assert hydra_page == fast + "\n"
    from rdsexp.errors import Exit
    assert [int(line.split()[0]) for line in fast.split("== Exit codes ==\n")[1].strip().splitlines()] == \
        [0, 1, 2, 130] == [int(code) for code in Exit]


@pytest.mark.parametrize("argv", [["--help"], ["-sc", "query=bash"]], ids=["help", "completion"])
def test_help_and_completion_import_no_numerics(tmp_path, argv):
    """`rdsexp --help` and a shell completion (each tab press) load Hydra, not the pipeline and its numerics
    (2.5 s of imports)."""
    code = ("import sys; from rdsexp.experiment.cli import main; sys.argv = ['rdsexp', *sys.argv[1:]]; main(); "
            "print('numerics' if 'rdsexp.numerics' in sys.modules else 'none', file=sys.stderr)")
    proc = subprocess.run([sys.executable, "-c", code, *argv], cwd=tmp_path, capture_output=True, text=True,
                          env=dict(os.environ, COMP_LINE="rdsexp gain="), check=True)
    assert proc.stderr.strip().splitlines()[-1] == "none", proc.stderr


def test_bash_completion_of_gain_lists_the_methods(tmp_path):
    script = ('eval "$(rdsexp --shell-completion install=bash)"; COMP_LINE="rdsexp gain="; '
              'COMP_POINT=${#COMP_LINE}; COMP_WORDS=(rdsexp gain=); COMP_CWORD=1; hydra_bash_completion; '
              'printf "%s\\n" "${COMPREPLY[@]}"')
    env = dict(os.environ, PATH=f"{SCRIPTS}{os.pathsep}{os.environ['PATH']}")
    out = subprocess.run(["bash", "-c", script], cwd=tmp_path, capture_output=True, text=True, env=env, check=True)
    assert set(out.stdout.split()) == {f"gain={m}" for m in rx.synthesis.METHODS}


@pytest.mark.slow
def test_configs_found_from_any_directory_and_extendable_with_config_dir(tmp_path):
    """The configs come from the installed package; --config-dir adds a user's own group option."""
    (tmp_path / "mine" / "gain").mkdir(parents=True)
    shutil.copy(REPO / "conf" / "gain" / "policy_iteration.yaml", tmp_path / "mine" / "gain" / "my_gain.yaml")
    out = subprocess.run([SCRIPTS / "rdsexp", "--config-dir", str(tmp_path / "mine"), "gain=my_gain", *SMALL,
                          "tracking=off"], cwd=tmp_path, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "policy_iteration" in out.stdout


def test_every_package_is_installed():
    """pyproject.toml lists packages by name: a new subpackage must be listed, or `pip install .` (not
    editable) would leave it out."""
    import tomllib
    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {module_name(p) for p in PACKAGE.rglob("__init__.py")} | {"rdsexp.conf"} | \
        {f"hydra_plugins.{p.parent.name}" for p in (REPO / "hydra_plugins").glob("*/__init__.py")}   # the sweeper
    assert found == listed

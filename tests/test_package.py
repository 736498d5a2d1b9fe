"""The package as users get it: layers, console scripts, --help, shell completion, installed configs."""
import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO, SMALL

import rdsexp as rx

PACKAGE = REPO / "rdsexp"
SCRIPTS = Path(sys.executable).parent


def imported_modules(path: Path) -> set[str]:
    """Absolute names of the rdsexp modules a source file imports (relative imports resolved)."""
    module = ".".join(path.relative_to(REPO).with_suffix("").parts)
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = package.rsplit(".", node.level - 1)[0] if node.level else ""
            target = ".".join(p for p in (base, node.module) if p) if node.level else node.module or ""
            names.add(target)
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
    return names


LAYER = {"numerics": 0, "paper": 1, "experiment": 2, "report": 3}
FORBIDDEN_IN_NUMERICS = ("hydra", "omegaconf", "pandas", "pyarrow", "rerun", "matplotlib")


@pytest.mark.parametrize("path", sorted((PACKAGE / "numerics").rglob("*.py")) + sorted((PACKAGE / "experiment").rglob("*.py"))
                         + sorted((PACKAGE / "report").rglob("*.py")) + sorted((PACKAGE / "paper").rglob("*.py")),
                         ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_only_go_downward(path):
    layer = path.relative_to(PACKAGE).parts[0]
    for name in imported_modules(path):
        parts = name.split(".")
        if parts[0] == "rdsexp" and len(parts) > 1 and parts[1] in LAYER:
            assert LAYER[parts[1]] <= LAYER[layer], f"{path.name} ({layer}) imports {name}"
        if layer == "numerics":
            assert parts[0] not in FORBIDDEN_IN_NUMERICS, f"numerics module {path.name} imports {name}"


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


def test_bash_completion_of_gain_lists_the_methods(tmp_path):
    script = ('eval "$(rdsexp --shell-completion install=bash)"; COMP_LINE="rdsexp gain="; '
              'COMP_POINT=${#COMP_LINE}; COMP_WORDS=(rdsexp gain=); COMP_CWORD=1; hydra_bash_completion; '
              'printf "%s\\n" "${COMPREPLY[@]}"')
    env = dict(os.environ, PATH=f"{SCRIPTS}{os.pathsep}{os.environ['PATH']}")
    out = subprocess.run(["bash", "-c", script], cwd=tmp_path, capture_output=True, text=True, env=env, check=True)
    assert set(out.stdout.split()) == {f"gain={m}" for m in rx.synthesis.METHODS}


def test_configs_found_from_any_directory_and_extendable_with_config_dir(tmp_path):
    """The configs come from the installed package; --config-dir adds a user's own group option."""
    (tmp_path / "mine" / "gain").mkdir(parents=True)
    shutil.copy(REPO / "conf" / "gain" / "policy_iteration.yaml", tmp_path / "mine" / "gain" / "my_gain.yaml")
    out = subprocess.run([SCRIPTS / "rdsexp", "--config-dir", str(tmp_path / "mine"), "gain=my_gain", *SMALL,
                          "tracking=off"], cwd=tmp_path, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "policy_iteration" in out.stdout

"""The README's two commands: CI runs exactly the test command."""
from conftest import REPO


def readme_commands():
    lines = (REPO / "README.md").read_text().splitlines()
    return [line.strip() for line in lines if line.startswith("    python3 -m venv")][:2]


def test_ci_runs_the_readme_test_command():
    main_command, test_command = readme_commands()
    assert main_command.endswith("python -m rdsexp") and test_command.endswith("python -m pytest -q -n 2 --dist loadfile")
    assert test_command in (REPO / ".ci" / "run").read_text().splitlines()

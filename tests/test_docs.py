"""The documentation site and the README: every bash and python example runs (experiments/docs_examples.py),
the pages the site lists exist, and the commands shown but not run are of the kinds named here."""
import re
import sys

import pytest
import yaml
from conftest import REPO

sys.path.insert(0, str(REPO / "experiments"))
import docs_examples  # noqa: E402

PAGES = docs_examples.pages()


def examples(page) -> tuple:
    """What running `page` does: its fences that run, write a file or check an output, in order."""
    return tuple((f.lang, f.body) for f in docs_examples.fences(page)
                 if f.runs or f.file or (f.lang == "text" and f.attrs.get("title") == "output"))


# a page whose examples are the first ones of another page's is run by that page's run: the site's home
# page is the README's tour (test_the_home_page_is_the_readmes_tour)
def covered_by(page):
    mine = examples(page)
    for other in PAGES:
        theirs = examples(other)
        if other != page and len(theirs) > len(mine) and theirs[:len(mine)] == mine:
            return other
    return None


RUN = [p for p in PAGES if examples(p) and covered_by(p) is None]


def nav_pages(node) -> list[str]:
    if isinstance(node, str):
        return [node]
    if isinstance(node, dict):
        return [p for v in node.values() for p in nav_pages(v)]
    return [p for v in node for p in nav_pages(v)]


NAV = yaml.load((REPO / "mkdocs.yml").read_text(), Loader=yaml.BaseLoader)["nav"]     # !! tags as text
# the guides' examples run in tests/test_docs_guides.py and tests/test_docs_guides_second.py, every other guide
# each: three files, so that --dist loadfile shares the site's slowest tests out rather than ending on one file
GUIDES = {REPO / "docs" / p for section in NAV if isinstance(section, dict) and "Guides" in section
          for p in nav_pages(section["Guides"])}

# what a ```{.bash .no-run} fence may hold, and why the suite does not run it
NOT_RUN = {
    r"python3 -m venv|pip install": "installs an environment (CI runs the README's two commands)",
    r"^rerun |rdsexp-runs view|experiments/docs_screenshots\.py": "opens the Rerun viewer (a window)",
    r"^apt-get install": "installs system packages",
    r"^mlflow server|^optuna-dashboard ": "starts a server that runs until stopped",
    r"hydra/launcher=(slurm|ray_cluster)": "needs a Slurm or Ray cluster",
    r"python experiments/(paper|benchmark_\w+|coverage|random_plants|pole_sets|robust_width|closed_loop_rate"
    r"|identification_input|fig_\w+|reproduction_table|data_round_trip|data_validation|online_defaults"
    r"|online_bound|paired_null|model_calibration|model_bias)\.py": "runs for minutes (a study or a benchmark)",
    r"\+sweep=\w+": "a shipped sweep: tens to hundreds of runs at 200 paths (minutes)",
    r"closed_loop\.paths=10000|--huge": "thousands of paths (minutes, 0.6 GB)",
    r"^export |^eval ": "changes the shell it runs in",
    r"^cd ": "a directory of the reader's",
    r"^mkdocs (build|serve)": "builds or serves this site (CI builds it strictly before the tests)",
}


def commands(body: str) -> list[str]:
    """The command lines of a shell fence (comments, blank lines and continuations dropped)."""
    lines, out = body.replace("\\\n", " ").splitlines(), []
    for line in lines:
        line = line.strip()
        if line and not line.startswith("#"):
            out.append(line)
    return out


def run_examples(page, directory) -> None:
    counts = docs_examples.run_page(page, directory)
    assert counts["bash"] + counts["python"] + counts["files"] + counts["outputs"] == len(examples(page))


HERE = [p for p in RUN if p not in GUIDES]


@pytest.mark.parametrize("page", HERE, ids=[str(p.relative_to(REPO)) for p in HERE])
@pytest.mark.slow
def test_examples_run(page, tmp_path):
    run_examples(page, tmp_path)


def guides_half(half: int) -> list:
    """Every other guide with examples to run (half 0 or 1): one of the two files of guides' tests."""
    return [p for p in RUN if p in GUIDES][half::2]


def test_the_guides_run_in_their_own_files():
    assert GUIDES and GUIDES <= set(PAGES)
    assert set(guides_half(0)) | set(guides_half(1)) == GUIDES & set(RUN) and guides_half(0) and guides_half(1)


def test_the_home_page_is_the_readmes_tour():
    assert covered_by(REPO / "docs" / "index.md") == REPO / "README.md"


def test_commands_shown_but_not_run_are_of_a_named_kind():
    for page in PAGES:
        for fence in docs_examples.fences(page):
            if fence.lang in ("bash", "python") and not fence.runs:
                assert fence.lang == "bash", f"{page}:{fence.line}: python examples all run"
                for command in commands(fence.body):
                    assert any(re.search(kind, command) for kind in NOT_RUN), \
                        f"{page.relative_to(REPO)}:{fence.line}: {command!r} is not run; say why in NOT_RUN"


def test_every_fence_has_a_language():
    for page in PAGES:
        for fence in docs_examples.fences(page):
            assert fence.lang, f"{page.relative_to(REPO)}:{fence.line}: a fence without a language"


def test_the_site_lists_every_page():
    listed = set(nav_pages(NAV))
    present = {p.relative_to(REPO / "docs").as_posix() for p in (REPO / "docs").rglob("*.md")}
    assert listed == present


def test_readme_is_a_landing_page():
    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= 125
    # every page of the site is linked from it
    for page in (REPO / "docs").rglob("*.md"):
        assert f"docs/{page.relative_to(REPO / 'docs').as_posix()}" in text, page


def test_the_pages_math_becomes_mathml_and_code_stays_as_it_is():
    """experiments/docs_math.py: $...$ and $$...$$ outside code become MathML (the site renders them without a
    script); a shell's $run in a code span or fence, and a price of $5 and $10, stay text."""
    from docs_math import mathml
    page = "a `$run` and $x_{k+1}$,\n```bash\necho $HOME $x$\n```\ncosts $5 and $10, and\n$$a^2$$\n"
    out = mathml(page)
    assert out.count("<math ") == 2 and 'display="block"' in out and "<msub><mi>x</mi>" in out
    assert "`$run`" in out and "echo $HOME $x$" in out and "costs $5 and $10" in out
    pages = [p.read_text() for p in (REPO / "docs").glob("*.md")]
    assert sum(mathml(p).count("<math ") for p in pages) >= 8        # the formulas the guides write in LaTeX

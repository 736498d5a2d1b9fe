"""The examples of the documentation site (docs/*.md) and of README.md, run as a reader would run them.

A page is a notebook: its code fences run in order, in one working directory, and a later fence sees
what an earlier one left there (the runs in `outputs/`, a plant file, a figure):

- ```bash: run with `bash -euo pipefail` in the page's directory, with this interpreter's
  environment first on PATH (`rdsexp`, `rdsexp-runs` and `python` are the installed ones);
- ```python: executed in the page's namespace (one per page), the page's directory as working
  directory and matplotlib's Agg backend;
- a ```yaml fence whose first line is a comment naming a file (`# mine/plant/cart.yaml: ...`) is
  written to that file before the fences after it run;
- a ```text fence titled `output` (```text title="output") must equal what the bash fence
  just before it printed, once run ids, dates and directories are replaced by placeholders;
- ```{.bash .no-run}: a command shown but not run here, because it installs an environment, opens
  a window, starts a server, needs a cluster or runs for minutes. `tests/test_docs.py` names each
  kind it accepts (NOT_RUN) and counts them; everything else in bash and python runs.

The working directory has `experiments/`, `docs/` and `examples/` linked from the repository, so that `python
experiments/SCRIPT.py` runs as from the repository's root (examples only read them).

Used by `tests/test_docs.py` (every page's examples) and, as an MkDocs hook (mkdocs.yml: `hooks:`),
by the site's build: a page that shows a figure `figures/NAME.png` gets it from running that page's
examples (they write it into `figures/` of their working directory), so every figure on the site is
drawn by the examples beside it. The figures are cached under `.cache/docs/` by the page's fences and
the code version.

    python experiments/docs_examples.py docs/sweeps.md [DIR]   # run one page's examples in DIR
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import os
import re
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DOCS = REPO / "docs"
CACHE = REPO / ".cache" / "docs"
FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<ticks>`{3,})(?P<info>[^`\n]*)\n(?P<body>.*?)^(?P=indent)(?P=ticks)[ \t]*$",
                   re.MULTILINE | re.DOTALL)
FILE_COMMENT = re.compile(r"^#\s*(?P<path>[\w./-]+\.ya?ml)\b")
FIGURE = re.compile(r"\]\((?P<path>figures/[\w.-]+\.png)\)")
TIMEOUT = 600                     # seconds for one fence


@dataclass
class Fence:
    """One code fence of a page: its language, classes, attributes, text and first line in the file."""
    lang: str
    classes: tuple[str, ...]
    attrs: dict
    body: str
    line: int

    @property
    def runs(self) -> bool:
        return self.lang in ("bash", "python") and "no-run" not in self.classes

    @property
    def file(self) -> str | None:
        """The file a yaml fence writes (its first line's comment names it), else None."""
        match = FILE_COMMENT.match(self.body) if self.lang == "yaml" else None
        return match["path"] if match else None


def parse_info(info: str) -> tuple[str, tuple[str, ...], dict]:
    """Language, classes and key="value" attributes of a fence's info string (```python title="x",
    ```{.bash .no-run})."""
    info = info.strip()
    attrs = dict(re.findall(r'(\w+)="([^"]*)"', info))
    if info.startswith("{"):
        classes = tuple(re.findall(r"\.([\w-]+)", info.split("}")[0]))
        return (classes[0] if classes else ""), classes[1:], attrs
    return (info.split()[0] if info else ""), (), attrs


def fences(path: Path) -> list[Fence]:
    """Every fenced code block of a markdown file, in order (indented fences too: admonitions, tabs)."""
    text = Path(path).read_text()
    out = []
    for m in FENCE.finditer(text):
        lang, classes, attrs = parse_info(m["info"])
        indent = len(m["indent"])
        body = "".join(line[indent:] if line[:indent].strip() == "" else line
                       for line in m["body"].splitlines(keepends=True))
        out.append(Fence(lang, classes, attrs, body, text.count("\n", 0, m.start()) + 1))
    return out


def pages() -> list[Path]:
    """Every page whose examples run: docs/**/*.md and README.md."""
    return sorted(DOCS.rglob("*.md")) + [REPO / "README.md"]


def normalize(text: str, directory: Path) -> str:
    """Output with what changes from run to run replaced: run ids, dates, times and the directory."""
    text = text.replace(str(directory.resolve()), "<dir>").replace(str(directory), "<dir>")
    text = re.sub(r"[^\s:]*/outputs/", "<dir>/outputs/", text)          # /home/you/rdsexp/outputs/...
    text = re.sub(r"\d{4}-\d\d-\d\d_\d\d-\d\d-\d\d-\d{6}_[0-9a-f]{8}", "<id>", text)
    text = re.sub(r"\d+(\.\d+)? s\b", "<seconds> s", text)
    return "\n".join(line.rstrip() for line in text.strip().splitlines())


def environment() -> dict:
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env.update(MPLBACKEND="Agg", PYTHONWARNINGS="ignore::DeprecationWarning", COLUMNS="200")
    env.pop("HYDRA_FULL_ERROR", None)
    return env


class FenceFailed(AssertionError):
    pass


def run_page(path: Path, directory: Path, log=None) -> dict:
    """Run the examples of the page `path` in `directory`, in order; returns the counts
    {"bash": N, "python": N, "files": N, "outputs": N, "not_run": N}. Raises FenceFailed naming the fence
    (file and line), with what it printed, when one fails or an output differs."""
    path, directory = Path(path), Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    for linked in ("experiments", "docs", "examples"):                  # as from the repository's root (read only)
        if not (directory / linked).exists():
            (directory / linked).symlink_to(REPO / linked)
    where = path.relative_to(REPO) if path.is_relative_to(REPO) else path
    counts = dict.fromkeys(("bash", "python", "files", "outputs", "not_run"), 0)
    namespace = {"__name__": "__docs__"}
    last_output = None
    for fence in fences(path):
        if fence.file:
            target = directory / fence.file
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(fence.body)
            counts["files"] += 1
        elif fence.lang == "text" and fence.attrs.get("title") == "output":
            if last_output is None:
                raise FenceFailed(f"{where}:{fence.line}: an output block with no bash block before it")
            shown, printed = normalize(fence.body, directory), normalize(last_output, directory)
            if shown != printed:
                raise FenceFailed(f"{where}:{fence.line}: the output shown differs from the output printed now:\n"
                                  f"{printed}")
            counts["outputs"] += 1
        elif fence.lang in ("bash", "python") and not fence.runs:
            counts["not_run"] += 1
        elif fence.lang == "bash":
            if log:
                log(f"{where}:{fence.line}: bash")
            proc = subprocess.run(["bash", "-euo", "pipefail", "-c", fence.body], cwd=directory, env=environment(),
                                  capture_output=True, text=True, timeout=TIMEOUT, stdin=subprocess.DEVNULL)
            if proc.returncode != 0:
                raise FenceFailed(f"{where}:{fence.line}: exit {proc.returncode}\n{fence.body}\nstdout:\n"
                                  f"{proc.stdout[-4000:]}\nstderr:\n{proc.stderr[-4000:]}")
            last_output = proc.stdout
            counts["bash"] += 1
        elif fence.lang == "python":
            if log:
                log(f"{where}:{fence.line}: python")
            run_python(fence, namespace, directory, where)
            counts["python"] += 1
    return counts


def run_python(fence: Fence, namespace: dict, directory: Path, where) -> None:
    import matplotlib
    matplotlib.use("Agg")
    saved = os.getcwd()
    out = io.StringIO()
    try:
        os.chdir(directory)
        with contextlib.redirect_stdout(out):
            exec(compile(fence.body, f"{where}:{fence.line}", "exec"), namespace)
    except Exception as err:
        raise FenceFailed(f"{where}:{fence.line}: {type(err).__name__}: {err}\n{fence.body}\nprinted:\n"
                          f"{out.getvalue()[-4000:]}") from err
    finally:
        os.chdir(saved)
        import matplotlib.pyplot as plt
        plt.close("all")


# --- the MkDocs hook: figures drawn by the pages' examples -------------------------------------------

def code_version() -> str:
    """The commit and a hash of uncommitted changes to the code (not to docs/), for the figure cache."""
    def git(*args):
        proc = subprocess.run(["git", "-C", str(REPO), *args], capture_output=True, text=True)
        return proc.stdout if proc.returncode == 0 else ""
    diff = git("diff", "HEAD", "--", "rdsexp", "conf", "experiments")
    return git("rev-parse", "HEAD").strip() + hashlib.sha256(diff.encode()).hexdigest()[:12]


def figures_of(page: Path) -> list[str]:
    return sorted(set(FIGURE.findall(page.read_text())))


def draw_figures(page: Path, version: str, log=print) -> dict[str, Path]:
    """The figures `page` shows (figures/NAME.png), drawn by running its examples (cached)."""
    wanted = figures_of(page)
    if not wanted:
        return {}
    key = hashlib.sha256((version + "".join(f.body for f in fences(page))).encode()).hexdigest()[:16]
    cache = CACHE / page.stem / key
    if not all((cache / name).exists() for name in wanted):
        log(f"docs: running the examples of {page.relative_to(REPO)} for {', '.join(wanted)}")
        with tempfile.TemporaryDirectory(prefix="rdsexp-docs-") as tmp:
            run_page(page, Path(tmp))
            missing = [name for name in wanted if not (Path(tmp) / name).exists()]
            if missing:
                raise FenceFailed(f"{page.relative_to(REPO)} shows {', '.join(missing)}, which its examples do "
                                  "not draw")
            shutil.rmtree(CACHE / page.stem, ignore_errors=True)
            for name in wanted:
                (cache / name).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(Path(tmp) / name, cache / name)
    return {name: cache / name for name in wanted}


def on_files(files, config):
    """MkDocs hook: add every figure the pages show, drawn by their examples."""
    import logging

    from mkdocs.structure.files import File
    logger = logging.getLogger("mkdocs.hooks.docs_examples")
    version = code_version()
    docs = Path(config["docs_dir"])
    for page in sorted(docs.rglob("*.md")):
        for name, source in draw_figures(page, version, log=logger.info).items():
            uri = (page.parent.relative_to(docs) / name).as_posix()
            if files.get_file_from_path(uri) is None:
                files.append(File.generated(config, uri, abs_src_path=str(source)))
    return files


def main(argv=None) -> int:
    import argparse
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("page", type=Path)
    parser.add_argument("directory", type=Path, nargs="?")
    args = parser.parse_args(argv)
    directory = args.directory or Path(tempfile.mkdtemp(prefix="rdsexp-docs-"))
    counts = run_page(args.page.resolve(), directory, log=print)
    print(f"{args.page}: {counts} in {directory}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The Rerun viewer screenshots of the documentation site (docs/img/viewer_*.png), taken from real runs.

The viewer needs a display: this runs it under a virtual one (Xvfb, with Mesa's software Vulkan driver),
so on a machine without a screen, first

    apt-get install -y xvfb mesa-vulkan-drivers

then, from the repository's root,

    python experiments/docs_screenshots.py [--out docs/img]

It runs the paper's experiment and a small ensemble-size sweep in a temporary store and opens each
recording with `rerun FILE --screenshot-to PNG --window-size 1600x1000`: the run's summary tab (its
default), its `states` and `closed_loop` tabs (the same default blueprint with another tab active,
saved as a blueprint file beside the recording), and the sweep's summary.rrd. These screenshots are
the site's only pictures not drawn by its executed examples (they need a display).
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
SIZE = "1600x1000"


def rdsexp(*args: str, cwd: Path) -> None:
    subprocess.run([sys.executable, "-m", "rdsexp", *args], cwd=cwd, check=True, stdout=subprocess.DEVNULL)


def tab_blueprint(run: Path, tab: str, out: Path) -> Path:
    """The run's default blueprint with `tab` active, as a .rbl file."""
    import rerun.blueprint as rrb

    from rdsexp.experiment import recording
    from rdsexp.runs import load
    names = ("identification", "paths", "model", "gains", "metrics", "exact")
    tables = {name: load(run, name) for name in names}
    trajectories = load(run, "trajectories")
    keys = [c for c in trajectories.columns if c not in recording.KEYS and c != "run"]
    quantities = list(dict.fromkeys(recording._split(c)[0] for c in keys))
    experiments = list(trajectories["experiment"].unique())
    tabs = [*recording._summary_tabs(tables, trajectories),
            *recording._blueprint(experiments, quantities).root_container.contents]
    index = [str(getattr(container, "name", "")) for container in tabs].index(tab)
    rrb.Blueprint(rrb.Tabs(*tabs, active_tab=index)).save("rdsexp", out)
    return out


def screenshot(files: list[Path], png: Path) -> None:
    png.parent.mkdir(parents=True, exist_ok=True)
    subprocess.run(["xvfb-run", "-a", "rerun", *map(str, files), "--screenshot-to", str(png),
                    "--window-size", SIZE], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                   timeout=300)
    shrink(png)
    print(f"wrote {png}")


def shrink(png: Path) -> None:
    """The viewer renders at twice the window size (HiDPI): halve it, so the site's pages stay light."""
    from PIL import Image
    with Image.open(png) as image:
        small = image.resize((image.width // 2, image.height // 2), Image.LANCZOS).convert("RGB")
    small.save(png, optimize=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "img")
    args = parser.parse_args(argv)
    out = args.out.resolve()
    with tempfile.TemporaryDirectory(prefix="rdsexp-shots-") as tmp:
        tmp = Path(tmp)
        rdsexp(cwd=tmp)
        (run,) = (tmp / "outputs" / "runs").iterdir()
        screenshot([run / "recording.rrd"], out / "viewer_summary.png")
        for tab in ("states", "closed_loop"):
            screenshot([run / "recording.rrd", tab_blueprint(run, tab, tmp / f"{tab}.rbl")], out / f"viewer_{tab}.png")
        rdsexp("+sweep=ensemble_size", "enkf.ensemble_size=30,50,100,300", "seed=0,1,2", "closed_loop.paths=50",
               cwd=tmp)
        (sweep,) = (tmp / "outputs" / "sweeps").iterdir()
        screenshot([sweep / "summary.rrd"], out / "viewer_sweep.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Fig. "estimation": states and parameters of the open-loop plant observed with the EnKF.

The identification run of the first-seed proposed run of the `paper` sweep: q_k against the EnKF's
predicted x_{k|k-1} and filtered x_{k|k}; xi_{k|k} with its ensemble spread, the modeling window
K0..K0+K1, the modeled mean and the true mean of xi (paper: [0.56, 0.2, 0.6]).

    python experiments/fig_estimation.py [--root outputs] [--out outputs/report]
"""
from rdsexp import report

NAME = "estimation"


def draw(run: report.Run):
    ident = run.table("identification")
    model = run.table("model")
    K0, K1 = run.get("identification.K0"), run.get("identification.K1")
    true_mean = report.reference()["plant"]["true_xi_mean"]
    k = ident["k"].to_numpy()
    fig, axes = report.figure(report.PAGE_WIDTH, 5.6, 3, 3, sharex=True)
    for i, ax in enumerate(axes.flat[:6]):
        # the plant as a wide light line under thin dark estimates: distinct in grayscale print
        ax.plot(k, ident[f"q[{i}]"], color="0.72", lw=2.6, solid_capstyle="butt", label="plant $q_k$")
        ax.plot(k, ident[f"x_pred_mean[{i}]"], color="black", lw=0.8, ls="--", label=r"predicted $x_{k|k-1}$")
        ax.plot(k, ident[f"x_filt_mean[{i}]"], color="black", lw=0.8, ls=":", label=r"filtered $x_{k|k}$")
        ax.set_ylabel(f"$q_{{{i + 1}}}$, $x_{{{i + 1}}}$")
    modeled = model[model["quantity"] == "mean"].sort_values("row")["value"].to_numpy()
    for j, ax in enumerate(axes.flat[6:]):
        mean, std = ident[f"xi_filt_mean[{j}]"], ident[f"xi_filt_std[{j}]"]
        ax.fill_between(k, mean - std, mean + std, color="0.75", lw=0, label="ensemble spread (1 sd)")
        ax.plot(k, mean, color="black", label=r"$\xi_{k|k}$")
        # the window hatched, not a second grey fill, so it never reads as the spread
        ax.axvspan(K0, K0 + K1, facecolor="none", edgecolor="0.8", hatch="////", lw=0, zorder=0,
                   label=f"modeling window {K0}..{K0 + K1}")
        ax.axhline(modeled[j], color="0.4", ls="--", label="modeled mean")
        ax.axhline(true_mean[j], color="0.4", ls=":", label="true mean")
        ax.set_ylabel(rf"$\xi_{{{j + 1}}}$")
        ax.set_xlabel("$k$")
    handles, labels = (sum(x, []) for x in zip(*(ax.get_legend_handles_labels() for ax in axes.flat[[0, 6]])))
    fig.legend(handles, labels, loc="outside lower center", ncols=4, frameon=False)
    return fig


def caption(run: report.Run) -> str:
    node = run.get("identification.input")
    return (f"Fig. estimation. Identification run (seed {run.get('seed')}, M = {run.get('enkf.ensemble_size')}): "
            f"the open-loop plant driven by a {node.get('levels', 'bipolar')} maximal-length sequence of amplitude "
            f"{node['amplitude']:g}, each bit held {node.get('hold', 1)} step(s) (register "
            f"{node['register_length']}); top: plant states q_k (wide grey) and the "
            "EnKF's predicted and filtered estimates; bottom: the filtered xi_{k|k} with the ensemble spread, the "
            "modeled mean over the hatched window and the true mean of the plant's parameter.")


def main(argv=None):
    args = report.arguments(__doc__.splitlines()[0], argv)
    runs = report.paper_runs(args)
    run = report.first_seed(runs)
    return report.save_figure(draw(run), args.out, NAME, [run], __file__, caption(run))


if __name__ == "__main__":
    report.script(main)

"""rdsexp's Hydra configs, installed as the package rdsexp.conf (Hydra finds them at pkg://rdsexp.conf)."""


def _register_sweeper() -> None:
    """rdsexp's Optuna sweeper (hydra_plugins/rdsexp_optuna, `hydra/sweeper: rdsexp_optuna`) known to Hydra wherever
    rdsexp is installed: Hydra finds plugins by listing the hydra_plugins namespace, which an editable install does
    not list, so the sweeper and its config are registered here, where every use of rdsexp's configs passes."""
    from hydra.core.plugins import Plugins

    from hydra_plugins.rdsexp_optuna.optuna_sweeper import OptunaSweeper  # its config, into Hydra's ConfigStore
    Plugins.instance().class_name_to_class.setdefault(f"{OptunaSweeper.__module__}.{OptunaSweeper.__name__}",
                                                      OptunaSweeper)


_register_sweeper()

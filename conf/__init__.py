"""rdsexp's Hydra configs, installed as the package rdsexp.conf (Hydra finds them at pkg://rdsexp.conf)."""

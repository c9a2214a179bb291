"""Arguments shared by several subcommands."""
from __future__ import annotations

import argparse


def add_config_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", "-c", default=None, metavar="FILE",
                   help="robot configuration YAML (default: configs/sim.yaml; a bare name like 'sim' "
                        "is looked up in configs/)")

"""Arguments shared by several subcommands."""
from __future__ import annotations

import argparse


def add_config_arg(p: argparse.ArgumentParser, default: str | None = None) -> None:
    p.add_argument("--config", "-c", default=default, metavar="FILE",
                   help=f"robot configuration YAML (default: configs/{default or 'sim'}.yaml; a bare name like "
                        "'sim' is looked up in configs/)")

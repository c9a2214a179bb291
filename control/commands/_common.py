"""Arguments shared by several subcommands."""
from __future__ import annotations

import argparse
from typing import Optional


def add_config_arg(p: argparse.ArgumentParser, default: str | None = None) -> None:
    p.add_argument("--config", "-c", default=default, metavar="FILE",
                   help=f"robot configuration YAML (default: configs/{default or 'sim'}.yaml; a bare name like "
                        "'sim' is looked up in configs/)")


def add_record_overwrite_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing --record file (the new recording takes its place only when complete)")


def record_target_error(args) -> Optional[str]:
    """Why ``--record`` cannot be written (a recording is there and no ``--overwrite``, or its folder is
    missing), or None; checked before any device opens."""
    from vbnav.control.comms.recording import check_record_target
    if not getattr(args, "record", None):
        return None
    try:
        check_record_target(args.record, getattr(args, "overwrite", False))
    except (FileExistsError, FileNotFoundError) as exc:
        return str(exc)
    return None

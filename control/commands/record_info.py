"""``vbnav record-info PATH``: channels, message counts, rates and duration of an MCAP recording."""
from __future__ import annotations

import sys


def register(sub) -> None:
    p = sub.add_parser("record-info", help="summarise an MCAP recording (channels, counts, duration)",
                       description="Summarise a recording made with --record: every channel with its schema, "
                                   "message count and rate, the duration and the run's metadata. Works on "
                                   "interrupted recordings (PATH.part) up to their last complete chunk. Every "
                                   "chunk's CRC is checked: damaged chunks and the messages lost with them are "
                                   "listed. Exit 0: readable; 1: damaged (messages lost); 2: not a recording.")
    p.add_argument("path", metavar="PATH", help="the .mcap file")
    p.set_defaults(func=_run)


def _run(args) -> int:
    from pathlib import Path

    from vbnav.control.comms.recording import PART_SUFFIX, format_summary, read_recording
    try:
        summary = read_recording(args.path)
    except ValueError as exc:
        print(f"vbnav record-info: {exc}", file=sys.stderr)
        return 2
    print(format_summary(summary))
    part = Path(args.path).with_name(Path(args.path).name + PART_SUFFIX)
    if summary.path != part and part.exists():     # a later run with --overwrite that did not end
        print(f"vbnav record-info: note: {part.name} beside it is an interrupted recording (read it with "
              f"'vbnav record-info {part}')", file=sys.stderr)
    return 1 if summary.damaged else 0

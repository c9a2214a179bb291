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
    from vbnav.control.comms.recording import format_summary, read_recording
    try:
        summary = read_recording(args.path)
    except ValueError as exc:
        print(f"vbnav record-info: {exc}", file=sys.stderr)
        return 2
    print(format_summary(summary))
    return 1 if summary.damaged else 0

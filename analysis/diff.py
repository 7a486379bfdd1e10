"""Compare the message payloads of two run logs.

    python -m analysis.diff A.mcap B.mcap

Two runs of the same config and seed must carry byte-identical messages (topic, log
time and payload, in order); metadata (provenance, config text) may differ. Prints the
number of messages compared and the first difference; exit status 0 when identical,
1 when not, 2 when a file cannot be read.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from pathlib import Path

from mcap.reader import make_reader


def messages(path: Path) -> Iterator[tuple[str, int, bytes]]:
    """``(topic, log_time, payload)`` of every message, in file order."""
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=False):
            yield channel.topic, message.log_time, bytes(message.data)


def first_difference(a: Path, b: Path) -> tuple[int, str | None]:
    """How many messages agree, and a description of the first difference (None if
    the logs carry the same messages).
    """
    count = 0
    ita, itb = messages(a), messages(b)
    while True:
        ma, mb = next(ita, None), next(itb, None)
        if ma is None and mb is None:
            return count, None
        if ma != mb:
            where = ma[:2] if ma is not None else mb[:2] if mb is not None else None
            return count, f"message {count} differs (topic, log_time of A or B: {where})"
        count += 1


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    parser = argparse.ArgumentParser(description="Compare the messages of two run logs.")
    parser.add_argument("a", type=Path)
    parser.add_argument("b", type=Path)
    args = parser.parse_args(argv)
    paths = [p / "run.mcap" if p.is_dir() else p for p in (args.a, args.b)]
    for p in paths:
        if not p.is_file():  # missing, or a FIFO or device that would block or never end
            print(f"error: {p} is not a regular file", file=sys.stderr)
            return 2
    try:
        count, diff = first_difference(*paths)
    except Exception as err:  # unreadable: say which and why
        print(f"error: {type(err).__name__}: {err}", file=sys.stderr)
        return 2
    if diff is None:
        print(f"identical: {count} messages")
        return 0
    print(diff)
    return 1


if __name__ == "__main__":
    sys.exit(main())

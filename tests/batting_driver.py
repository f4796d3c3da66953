"""``examples/train_batting.py`` ended abruptly at the K-th commit: a stop at a known point.

    python tests/batting_driver.py K [train_batting.py's arguments]

Runs ``train_batting.main`` with an ``on_checkpoint`` hook (the loop's, called after every
commit) that counts the commits of this process — a run commits its selection, then its
rewarded episodes, then the iteration's result — and at the K-th ends the process with
``os._exit(3)``: no cleanup, as a kill would leave it. ``--backend local`` only (the hook does
not travel to worker processes).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))

import train_batting  # noqa: E402

STOPPED = 3
"""The driver's exit status when it stopped the run."""


def main() -> None:
    limit, argv = int(sys.argv[1]), sys.argv[2:]
    written = 0

    def stop_at_the_limit(api) -> None:
        nonlocal written
        written += 1
        if written >= limit:
            print(f"\n[batting_driver] stopping abruptly after {written} checkpoints", flush=True)
            os._exit(STOPPED)

    train_batting.main(argv, on_checkpoint=stop_at_the_limit)


if __name__ == "__main__":
    main()

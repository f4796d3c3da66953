"""The attacks on a run's store and on the examples' runs, counted (docs/durable_runs.md).

Every try is a real process and real files; the table counts, per attack, the committed
rewards lost or bought twice and the silent damages (a damaged run resumed or read as if it
were whole). Both must be 0.

* ``kill`` (``--kills N``): ``examples/chain_walk_api.py`` SIGKILLed (a quarter of the tries the
  moment its first store appears, the others at a random moment of the run), then
  ``--resume``. The rewarded episodes committed when it died (counted on a copy of its
  stores, the commit in flight rolled back as SQLite does) plus those the resumed process
  buys must be the schedule's, and the numbers those of an uninterrupted run;
* ``signal`` (``--signals N``): the same with SIGINT and SIGTERM (alternately): the commit in
  flight completes, the script ends with its one line (exit 130/143). A signal that comes
  once the results are written (as the process ends) is counted apart, as is one that comes
  after the process ended;
* ``example damage`` (``--example-damages N``): a SIGKILLed example's store files, one file
  damaged (removed, cut, a bit flipped), then ``--resume``: refused in one line (exit 1,
  nothing bought, the files left as they were), or it finishes with the uninterrupted numbers
  and buys no committed reward again;
* ``damage`` (``--damages N``): a store whose writer committed 5 slices and was SIGKILLed
  between commits, or inside a 6th slice whose pages had spilled into the database (its
  journal hot); one of its files (the database, its journal, its counter) removed, cut at a
  random length, one random bit flipped, or replaced by its copy of 2 commits before; then a
  reader (``RunStore.read``) and a writer (``resume=True``) must give back the 5 committed
  slices, value for value, or refuse;
* ``creation``: SIGKILL, or SIGTERM turned into the examples' interrupt, as SQLite starts each
  statement of a store's creation in turn; SIGKILL before each file-system step of it (open,
  write, fsync, rename); a file-size limit (``ulimit -f``) that makes a write of the creation
  fail; then ``resume=True`` must open the run (empty);
* ``commit signal`` (``--commit-signals N``): SIGTERM while a commit is open, sent from inside
  the transaction and at random moments from outside into a writer committing in a loop
  (with a thread that blocks no signal, as ``import torch`` starts); every commit that began
  must stand.

    nice python benchmarks/durability_attacks.py --kills 40 --signals 40 --damages 200 \\
        --out durability_attacks.json
"""

from __future__ import annotations

import argparse
import json
import random
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

import torch  # noqa: E402
from _durability_examples import EXAMPLE, example, reference_run  # noqa: E402,F401
from _durability_store import (  # noqa: E402,F401  (the attacks, also used by the tests)
    COMMITS,
    CONFIG,
    CREATED,
    Tally,
    commit_signals,
    creation,
    damage,
    episodes,
    in_child,
    kill_at_file_step,
    killed_writer,
    signal_inside_a_commit,
    stop_at_statement,
)
from _timing import machine_info  # noqa: E402

EXAMPLE_ATTACKS = {"kill": "kills", "signal": "signals", "example-damage": "example_damages"}
"""The attacks on the examples and the flag that says how many tries each gets."""


# -- the table -------------------------------------------------------------------------------


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--kills", type=int, default=40, help="examples SIGKILLed")
    parser.add_argument("--signals", type=int, default=40, help="examples SIGINTed/SIGTERMed")
    parser.add_argument("--damages", type=int, default=200, help="stores' files damaged")
    parser.add_argument(
        "--example-damages", type=int, default=0, help="killed examples' store files damaged"
    )
    parser.add_argument(
        "--commit-signals", type=int, default=20, help="SIGTERMs into open commits (×2)"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--only", default="", help="one attack: kill, signal, example-damage, damage, creation "
        "or commit-signal"
    )  # fmt: skip
    parser.add_argument("--out", default="", help="also write the outcomes as JSON here")
    args = parser.parse_args()
    rng = random.Random(args.seed)
    torch.set_num_threads(1)
    table: dict[str, Tally] = {}
    began = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        attacks = {
            "creation": lambda d: creation(d),
            "commit-signal": lambda d: commit_signals(d, args.commit_signals, rng),
            "damage": lambda d: damage(d, args.damages, rng),
        }
        reference = []

        def on_example(kind: str, tries: int):
            def attack(d: Path) -> Tally:
                if not reference:
                    reference.append(reference_run(folder))
                return example(d, kind, tries, rng, reference[0])

            return attack

        attacks["kill"] = on_example("kill", args.kills)
        attacks["signal"] = on_example("signal", args.signals)
        attacks["example-damage"] = on_example("damage", args.example_damages)
        for name, attack in attacks.items():
            skipped = name in EXAMPLE_ATTACKS and not getattr(args, EXAMPLE_ATTACKS[name])
            if skipped or (args.only and name != args.only):
                continue
            (folder / name).mkdir()
            started = time.perf_counter()
            table[name] = tally = attack(folder / name)
            print(f"\n{name} ({time.perf_counter() - started:.0f} s)", flush=True)
            for outcome, count in sorted(tally.outcomes.items()):
                print(f"  {count:4d}  {outcome}", flush=True)
    print("\n| attack | tries | committed rewards lost or bought twice | silent damages |")
    print("| --- | ---: | ---: | ---: |")
    for name, tally in table.items():
        print(f"| {name} | {tally.tries} | {tally.lost_or_twice} | {tally.silent} |")
    total = [sum(getattr(t, k) for t in table.values()) for k in ("tries", "lost_or_twice")]
    silent = sum(t.silent for t in table.values())
    print(f"| all | {total[0]} | {total[1]} | {silent} |")
    if args.out:
        payload = {
            "benchmark": "durability_attacks",
            "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
            "machine": machine_info(),
            "seconds": time.perf_counter() - began,
            "attacks": {name: tally.as_dict() for name, tally in table.items()},
        }
        Path(args.out).write_text(json.dumps(payload, indent=1) + "\n")


if __name__ == "__main__":
    main()

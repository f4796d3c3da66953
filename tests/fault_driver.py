"""A durable run that SIGKILLs itself at the K-th event (for tests/test_faults.py).

The rewarded environment counts its reward measurements: every rewarded step appends the rows
it measured to ``MEASURED`` (an unbuffered append, in the kernel before the step returns, so a
kill never hides a measurement). Events, at which the process sends itself SIGKILL:

* every environment step (inside reward-free collection and inside a rewarded slice);
* inside a store transaction, after each row is written and before the commit (mid-write);
* after every commit (e.g. right after a slice is stored, its rewards not yet fitted);
* every boundary between iterations.

    python tests/fault_driver.py RUN.db MEASURED RESULT.json KILL_AT SLICE

KILL_AT: the K-th event (a number; -1: never) or the K-th event of one kind (``KIND@K``, e.g.
``after_put_episodes@2``; kinds as written to ``MEASURED.kills`` with ``_`` for spaces).

Exit 0 with RESULT written when the run completes. ``python tests/fault_driver.py serve`` is a
fork server: it imports everything once, then for each line ``RUN MEASURED RESULT KILL_AT
SLICE`` on stdin forks a child process running that run, prints ``pid P`` and, when the child
has ended, ``exit CODE`` (-9: killed by SIGKILL). The server runs no tensor code itself, so its
children start clean in about a second instead of importing torch for several.
"""

import json
import logging
import os
import signal
import sys

import torch

from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv
from torch_api.core.basis import GaussianActionBasis
from torch_api.loop.durable import DurableRun
from torch_api.loop.iteration import ActivePolicyIteration
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.loop.spec import RunSpec
from torch_api.runs.store import RunStore

SCHEDULE = (3, 2, 2, 1)
TRIALS = 2
STEPS = 10


class CountingChain(ChainWalkEnv):
    """The rewarded chain walk: every step is a measurement, appended to a file."""

    measured_fd: int | None = None

    def _step(self, td):
        out = super()._step(td)
        os.write(self.measured_fd, f"{self.batch_size[0]}\n".encode())
        return out


def make_api(path, slice_mode, resume):
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    spec = RunSpec.of(
        schedule=SCHEDULE,
        num_steps=STEPS,
        gamma=GAMMA,
        psi_mode="grouped",
        num_repeats=2,
        num_trials=TRIALS,
        seed=3,
        rewarded_slice=slice_mode,
    )
    return ActivePolicyIteration(
        spec,
        env=lambda e: CountingChain(batch_size=e),
        selector=SamplingPolicySelector(env=lambda e: ChainWalkEnv(batch_size=e)),
        basis=basis,
        durable=DurableRun(path, resume=resume),
    )


def main(path: str, measured: str, result: str, kill_at: str, slice_mode: str) -> None:
    events = {"count": 0}
    kinds: dict[str, int] = {}

    def event(kind: str) -> None:
        events["count"] += 1
        kinds[kind] = kinds.get(kind, 0) + 1
        if str(events["count"]) == kill_at or f"{kind.replace(' ', '_')}@{kinds[kind]}" == kill_at:
            with open(f"{measured}.kills", "a") as handle:  # what the kill interrupted
                handle.write(kind + "\n")
            os.kill(os.getpid(), signal.SIGKILL)

    CountingChain.measured_fd = os.open(measured, os.O_WRONLY | os.O_CREAT | os.O_APPEND)
    step = ChainWalkEnv._step

    def dying_step(self, td):
        event("rewarded step" if isinstance(self, CountingChain) else "reward-free step")
        return step(self, td)

    ChainWalkEnv._step = dying_step
    put = RunStore._put

    def dying_put(db, *args, **kwargs):
        put(db, *args, **kwargs)
        event("inside a transaction")  # a row written, the transaction not yet committed

    RunStore._put = staticmethod(dying_put)
    for name in ("put_selection", "put_episodes", "put_record"):
        write = getattr(RunStore, name)

        def committed(self, *args, _write=write, _name=name, **kwargs):
            _write(self, *args, **kwargs)
            event(f"after {_name}")  # after put_episodes: rewards bought, not yet fitted

        setattr(RunStore, name, committed)
    api = make_api(path, slice_mode, resume=True)
    while api.iteration < len(api.schedule):
        event("between iterations")
        api.step()
    episodes = api.rewarded.episodes()
    out = {
        "theta": api.theta.tolist(),
        "chosen": [r.chosen for r in api.history],
        "j_mean": [r.j_mean for r in api.history],
        "episodes_per_trial": len(api.rewarded),
        "episodes": {str(k): episodes[k].tolist() for k in episodes.keys(True, True)},
    }
    with open(result, "w") as handle:
        json.dump(out, handle)
    print(f"{events['count']} events", file=sys.stderr)


def serve() -> None:
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    for line in sys.stdin:
        path, measured, result, kill_at, slice_mode = line.split()
        pid = os.fork()
        if pid == 0:  # the child: one run, then out without the parent's cleanup
            code = 0
            try:
                main(path, measured, result, kill_at, slice_mode)
            except BaseException:
                import traceback

                traceback.print_exc()
                code = 1
            finally:
                sys.stderr.flush()
                os._exit(code)
        print(f"pid {pid}", flush=True)
        _, status = os.waitpid(pid, 0)
        print(f"exit {os.waitstatus_to_exitcode(status)}", flush=True)


if __name__ == "__main__":
    if sys.argv[1:] == ["serve"]:
        serve()
    else:
        main(*sys.argv[1:6])

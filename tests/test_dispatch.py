"""torch_api/runs/dispatch.py: trial chunks, their seeds, and running them locally or on Ray."""

from __future__ import annotations

import importlib.util
import os
import sys

import pytest
import torch

from envs.chain_walk import CENTERS, GAMMA, TAU, ChainWalkEnv
from torch_api.core.basis import GaussianActionBasis
from torch_api.loop.iteration import ActivePolicyIteration
from torch_api.loop.spec import RunSpec
from torch_api.runs.dispatch import run_chunks, split_trials, trial_seeds

HAVE_RAY = importlib.util.find_spec("ray") is not None


def test_split_trials_covers_every_trial_once_in_order():
    for trials in range(1, 12):
        for chunks in range(1, trials + 1):
            parts = split_trials(trials, chunks)
            assert len(parts) == chunks
            assert [t for part in parts for t in part] == list(range(trials))
            assert max(map(len, parts)) - min(map(len, parts)) <= 1


@pytest.mark.parametrize(("trials", "chunks"), [(0, 1), (3, 0), (3, 4)])
def test_split_trials_rejects_bad_counts(trials, chunks):
    with pytest.raises(ValueError, match="num_"):
        split_trials(trials, chunks)


def test_trial_seeds_are_the_iteration_defaults_and_ignore_the_chunking():
    api = _api([0, 1, 2, 3, 4], seeds=None)  # default trial seeds of seed=7
    assert trial_seeds(7, range(5)) == api.trial_seeds
    assert [s for part in split_trials(5, 2) for s in trial_seeds(7, part)] == api.trial_seeds


def test_local_backend_keeps_chunk_order():
    assert run_chunks(sum, [[1, 2], [3], [4, 5, 6]]) == [3, 3, 15]
    assert run_chunks(sum, []) == []


@pytest.mark.parametrize("backend", ["local", "processes"])
def test_on_result_sees_every_chunk_once_with_its_result(backend):
    """The progress callback: every chunk's index and result, each once, in the caller."""
    seen = []
    chunks = [[1, 2], [3], [4, 5, 6], [7]]
    results = run_chunks(
        sum, chunks, backend=backend, workers=2, on_result=lambda i, r: seen.append((i, r))
    )
    assert results == [3, 3, 15, 7]
    assert sorted(seen) == [(0, 3), (1, 3), (2, 15), (3, 7)]
    if backend == "local":
        assert [i for i, _ in seen] == [0, 1, 2, 3]


def test_unknown_backend_is_refused():
    with pytest.raises(ValueError, match="backend must be one of"):
        run_chunks(sum, [[1]], backend="dask")


def test_missing_ray_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # makes ``import ray`` fail
    with pytest.raises(ImportError, match=r"torch-api\[ray\]"):
        run_chunks(sum, [[1]], backend="ray")


# -- a tiny chain-walk run of some trials, as a dispatched chunk --------------------------------

SEED = 7


def _api(trials: list[int], seeds: list[int] | None) -> ActivePolicyIteration:
    basis = GaussianActionBasis(centers=torch.tensor(CENTERS)[:, None], tau=TAU, num_actions=2)
    spec = RunSpec.of(
        schedule=(3, 2),
        num_steps=10,
        gamma=GAMMA,
        psi_mode="grouped",
        num_repeats=2,
        num_trials=len(trials),
        seed=SEED,
        trial_seeds=seeds,
    )
    return ActivePolicyIteration(spec, env=lambda rows: ChainWalkEnv(batch_size=rows), basis=basis)


def run_trials(trials: list[int]) -> dict:
    """A chunk: the batched run of some trials; θ and the choices per trial."""
    api = _api(trials, trial_seeds(SEED, trials))
    history = api.run()
    return {"theta": api.theta.tolist(), "chosen": [r.chosen for r in history]}


def _concatenate(parts: list[dict]) -> dict:
    return {
        "theta": [row for part in parts for row in part["theta"]],
        "chosen": [sum((p["chosen"][i] for p in parts), []) for i in range(2)],
    }


def test_processes_backend_keeps_chunk_order_and_gives_the_local_numbers():
    assert run_chunks(sum, [[1, 2], [3], [4, 5, 6]], backend="processes", workers=2) == [3, 3, 15]
    assert run_chunks(sum, [], backend="processes") == []
    chunks = [list(t) for t in split_trials(4, 2)]
    assert run_chunks(run_trials, chunks, backend="processes", workers=2) == run_chunks(
        run_trials, chunks
    )


@pytest.mark.skipif(sys.platform != "linux", reason="fork: the Linux start method")
def test_forked_workers_need_nothing_picklable_and_give_the_local_numbers():
    """With ``start_method="fork"`` the workers inherit the function and the chunks: a
    closure runs (a script under ``python -m cProfile`` has no importable functions)."""
    offset = 10
    closure = lambda chunk: [x + offset for x in chunk]  # noqa: E731 (not picklable)
    chunks = [[1, 2], [3], [4, 5, 6]]
    out = run_chunks(closure, chunks, backend="processes", workers=2, start_method="fork")
    assert out == [[11, 12], [13], [14, 15, 16]]
    parts = [list(t) for t in split_trials(4, 2)]
    forked = run_chunks(run_trials, parts, backend="processes", workers=2, start_method="fork")
    assert forked == run_chunks(run_trials, parts)


def test_spawned_workers_refuse_an_unpicklable_function_before_any_worker_starts():
    """Spawned workers must unpickle ``fn``: a closure is refused at the call with the fix
    named, not by a worker pool's feeder thread (whose late errors Python reports as an
    unhandled exception in a thread)."""
    offset = 10
    closure = lambda chunk: [x + offset for x in chunk]  # noqa: E731 (not picklable)
    with pytest.raises(TypeError, match=r"not picklable.*start_method='fork'"):
        run_chunks(closure, [[1, 2], [3], [4, 5, 6]], backend="processes", workers=2)


def test_local_chunks_equal_one_batch():
    whole = run_trials([0, 1, 2, 3])
    chunked = run_chunks(run_trials, [list(t) for t in split_trials(4, 3)])
    assert _concatenate(chunked) == whole


@pytest.fixture(scope="module")
def local_ray():
    """A local Ray instance on 2 CPUs for this module (this test file pickled by value)."""
    ray = pytest.importorskip("ray", reason="the ray extra is not installed")
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # workers cannot import it
    started = not ray.is_initialized()
    if started:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    if started:
        ray.shutdown()


@pytest.mark.skipif(not HAVE_RAY, reason="the ray extra is not installed (pip install ray)")
def test_ray_chunks_equal_local_ones(local_ray):
    chunks = [list(t) for t in split_trials(4, 2)]
    on_ray = run_chunks(run_trials, chunks, backend="ray")
    assert local_ray.is_initialized()  # an instance started before the call is left running
    assert on_ray == run_chunks(run_trials, chunks)
    assert _concatenate(on_ray) == run_trials([0, 1, 2, 3])


@pytest.mark.skipif(not HAVE_RAY, reason="the ray extra is not installed (pip install ray)")
def test_ray_task_errors_reach_the_caller(local_ray):
    with pytest.raises(Exception, match="ValueError.*seeds must split"):
        run_chunks(_bad_chunk, [[1]], backend="ray")


def _bad_chunk(trials: list[int]) -> None:
    ChainWalkEnv(batch_size=3).set_block_seeds([1, 2])  # 3 rows do not split into 2 blocks

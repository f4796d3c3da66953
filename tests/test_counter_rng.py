"""The counter-based generator: Random123's known answers, the streams' laws, uniformity and
independence of neighbouring keys and counters, the batch guarantee, CPU == CUDA."""

import pickle

import pytest
import torch
from scipy import stats

from counter_rng import CounterStreams, derive_key, derive_keys, philox4x32, philox4x32_int

# Random123 tests/kat_vectors, the "philox4x32" lines less that first word: rounds, counter
# (4 words), key (2 words), expected output (4 words)
KAT = """
7 00000000 00000000 00000000 00000000 00000000 00000000 5f6fb709 0d893f64 4f121f81 4f730a48
7 ffffffff ffffffff ffffffff ffffffff ffffffff ffffffff 5207ddc2 45165e59 4d8ee751 8c52f662
7 243f6a88 85a308d3 13198a2e 03707344 a4093822 299f31d0 4dfccaba 190a87f0 c47362ba b6b5242a
10 00000000 00000000 00000000 00000000 00000000 00000000 6627e8d5 e169c58d bc57ac4c 9b00dbd8
10 ffffffff ffffffff ffffffff ffffffff ffffffff ffffffff 408f276d 41c83b0e a20bc7c6 6d5451fd
10 243f6a88 85a308d3 13198a2e 03707344 a4093822 299f31d0 d16cfe09 94fdcceb 5001e420 24126ea1
"""


def kat_rows():
    for line in KAT.strip().splitlines():
        rounds, *words = line.split()
        words = [int(w, 16) for w in words]
        yield int(rounds), tuple(words[:4]), tuple(words[4:6]), tuple(words[6:])


@pytest.mark.parametrize("rounds, counter, key, expected", list(kat_rows()))
def test_known_answers(rounds, counter, key, expected):
    assert philox4x32_int(counter, key, rounds) == expected
    out = philox4x32(torch.tensor(counter).unsqueeze(-1), torch.tensor(key).unsqueeze(-1), rounds)
    assert tuple(out.squeeze(-1).tolist()) == expected


def test_tensor_and_python_philox_agree_on_random_inputs():
    gen = torch.Generator().manual_seed(0)
    counter = torch.randint(0, 2**32, (4, 200), generator=gen)
    key = torch.randint(0, 2**32, (2, 200), generator=gen)
    out = philox4x32(counter, key)
    for i in range(200):
        expected = philox4x32_int(tuple(counter[:, i].tolist()), tuple(key[:, i].tolist()))
        assert tuple(out[:, i].tolist()) == expected


def test_a_draw_is_the_documented_function_of_key_and_counter():
    """Word i of stream s in draw c is lane i % 4 of Philox(keys[s], (i // 4, 0, c, 0))."""
    keys = [3, 2**62 + 12345]
    streams = CounterStreams(keys)
    streams.uniform((2, 3))  # draw 0
    words = streams._words((2, 6), None)  # draw 1: 6 words per stream
    for s, key in enumerate(keys):
        key_words = (key & 0xFFFFFFFF, key >> 32)
        lanes = philox4x32_int((0, 0, 1, 0), key_words) + philox4x32_int((1, 0, 1, 0), key_words)
        assert words[s].tolist() == list(lanes[:6])
    u = CounterStreams(7).uniform((5,))
    w = CounterStreams(7)._words((5,), None)
    assert torch.equal(u, (w.double() + 0.5) / 2**32)


def test_draws_computed_ahead_are_the_draws_made_one_at_a_time():
    """A run of same-shape draws (computed several at a time), interrupted by another shape,
    equals each draw made alone at its counter."""
    keys = [5, 6, 7]
    streams = CounterStreams(keys)
    shapes = [(3, 4)] * 9 + [(6,)] + [(3, 4)] * 5
    for call, shape in enumerate(shapes):
        alone = CounterStreams(keys, calls=call)._words(shape, None)
        assert torch.equal(streams._words(shape, None), alone), call
    assert streams.calls == len(shapes)


def test_derived_keys_vectorised_equal_scalar():
    keys = derive_keys(torch.tensor([0, 1, 2**62]), torch.tensor([4, 5, 6]), 7, 8)
    assert keys.tolist() == [
        derive_key(0, 4, 7, 8),
        derive_key(1, 5, 7, 8),
        derive_key(2**62, 6, 7, 8),
    ]
    assert (keys >= 0).all() and len(set(keys.tolist())) == 3


def test_uniforms_are_uniform():
    u = CounterStreams(12345).uniform((1_000_000,))
    assert 0.0 < u.min() and u.max() < 1.0
    assert stats.kstest(u.numpy(), "uniform").pvalue > 1e-3
    counts = torch.histc(u, bins=1000, min=0.0, max=1.0)
    assert stats.chisquare(counts.numpy()).pvalue > 1e-3


def test_integers_and_normals_follow_their_laws():
    ints = CounterStreams(99).integers(1, 11, (1_000_000,))
    assert ints.min() == 1 and ints.max() == 10
    assert stats.chisquare(torch.bincount(ints)[1:].numpy()).pvalue > 1e-3
    z = CounterStreams(98).normal((1_000_001,))
    assert stats.kstest(z.numpy(), "norm").pvalue > 1e-3


def pair_chi_square(x: torch.Tensor, y: torch.Tensor, bins: int = 32) -> float:
    cells = (x * bins).long() * bins + (y * bins).long()
    return stats.chisquare(torch.bincount(cells, minlength=bins * bins).numpy()).pvalue


@pytest.mark.parametrize("key", [0, 1, 2**32 - 1, 2**40])
def test_neighbouring_keys_are_independent(key):
    """Streams k and k+1 (e.g. neighbouring trials keyed by raw numbers): no correlation, the
    pairs uniform on the unit square."""
    u = CounterStreams([key, key + 1]).uniform((2, 500_000))
    assert abs(torch.corrcoef(u)[0, 1]) < 5 * 500_000**-0.5
    assert pair_chi_square(u[0], u[1]) > 1e-3


def test_neighbouring_counters_are_independent():
    """Consecutive words of one draw and the same word of consecutive draws."""
    streams = CounterStreams(2024)
    u = streams.uniform((1_000_000,))
    assert abs(torch.corrcoef(torch.stack([u[:-1], u[1:]]))[0, 1]) < 5e-3
    assert pair_chi_square(u[0::2], u[1::2]) > 1e-3
    draws = torch.stack([streams.uniform((1,)) for _ in range(2000)]).squeeze(-1)
    assert abs(torch.corrcoef(torch.stack([draws[:-1], draws[1:]]))[0, 1]) < 0.12


def test_batch_guarantee_streams_alone_together_and_in_chunks():
    keys = derive_keys(torch.arange(8), 1, 2)
    together = CounterStreams(keys)
    alone = [CounterStreams(int(k)) for k in keys[:4]]
    chunks = [CounterStreams(keys[:4]), CounterStreams(keys[4:])]
    for draw in ("uniform", "normal", "integers"):
        args = (0, 7) if draw == "integers" else ()
        big = getattr(together, draw)(*args, (8 * 3, 5))
        for t, stream in enumerate(alone):
            assert torch.equal(big[3 * t : 3 * t + 3], getattr(stream, draw)(*args, (3, 5)))
        parts = torch.cat([getattr(c, draw)(*args, (4 * 3, 5)) for c in chunks])
        assert torch.equal(big, parts)


def test_select_pickle_and_restart_keep_the_position():
    streams = CounterStreams([1, 2, 3])
    streams.uniform((3,))
    copy = pickle.loads(pickle.dumps(streams))
    part = streams.select(slice(1, 3))
    nxt = streams.uniform((3, 2))
    assert torch.equal(copy.uniform((3, 2)), nxt)
    assert torch.equal(part.uniform((2, 2)), nxt[1:])
    assert torch.equal(streams.restart().uniform((3,)), CounterStreams([1, 2, 3]).uniform((3,)))


def test_bad_shapes_and_keys_are_refused():
    with pytest.raises(ValueError, match="equal blocks"):
        CounterStreams([1, 2]).uniform((3,))
    with pytest.raises(ValueError, match="non-negative"):
        CounterStreams([-1])
    with pytest.raises(ValueError, match="low < high"):
        CounterStreams(1).integers(3, 3, (2,))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (CPU == CUDA)")
def test_cpu_and_cuda_draw_the_same_numbers():
    keys = derive_keys(torch.arange(64), 3, 4)
    cpu, cuda = CounterStreams(keys), CounterStreams(keys)
    for _ in range(3):
        assert torch.equal(cpu._words((64 * 100,), "cpu"), cuda._words((64 * 100,), "cuda").cpu())
    assert torch.equal(cpu.uniform((64, 7)), cuda.uniform((64, 7), device="cuda").cpu())
    assert torch.equal(cpu.integers(1, 11, (64,)), cuda.integers(1, 11, (64,), device="cuda").cpu())

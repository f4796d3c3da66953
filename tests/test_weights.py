"""Per-decision importance weights against a brute-force product."""

import pytest
import torch

from torch_api.core.weights import effective_sample_size, per_decision_weights


def test_matches_brute_force_product():
    gen = torch.Generator().manual_seed(0)
    target = torch.rand(2, 3, 6, generator=gen, dtype=torch.float64)
    sample = torch.rand(2, 3, 6, generator=gen, dtype=torch.float64) * 0.9 + 0.1
    w = per_decision_weights(target, sample)
    for i in range(2):
        for m in range(3):
            running = 1.0
            for n in range(6):
                running *= target[i, m, n].item() / sample[i, m, n].item()
                assert w[i, m, n].item() == pytest.approx(running, rel=1e-12)


def test_same_policy_gives_weight_one():
    probs = torch.rand(4, 10, dtype=torch.float64) * 0.8 + 0.1
    torch.testing.assert_close(
        per_decision_weights(probs, probs), torch.ones(4, 10, dtype=torch.float64)
    )


def test_target_zero_gives_zero_weight_onwards():
    target = torch.tensor([[0.5, 0.0, 0.5]])
    sample = torch.tensor([[0.5, 0.5, 0.5]])
    assert per_decision_weights(target, sample).tolist() == [[1.0, 0.0, 0.0]]


def test_mask_zeroes_padding_and_ignores_its_values():
    target = torch.tensor([[0.5, 0.5, 0.5]])
    sample = torch.tensor([[0.25, 0.5, 0.0]])  # the 0 is padding, not a taken action
    mask = torch.tensor([[True, True, False]])
    assert per_decision_weights(target, sample, mask).tolist() == [[2.0, 2.0, 0.0]]


def test_zero_sampling_probability_is_a_data_error():
    with pytest.raises(ValueError, match=r"sample_probs is 0 for a taken action at index \(0, 1\)"):
        per_decision_weights(torch.tensor([[0.5, 0.5]]), torch.tensor([[0.5, 0.0]]))


@pytest.mark.parametrize("bad", [float("nan"), -0.1, 1.5])
def test_invalid_probabilities_rejected(bad):
    with pytest.raises(ValueError, match="target_probs must be finite probabilities"):
        per_decision_weights(torch.tensor([[0.5, bad]]), torch.tensor([[0.5, 0.5]]))


def test_shape_mismatch_rejected():
    with pytest.raises(ValueError, match="same shape"):
        per_decision_weights(torch.ones(2, 3), torch.ones(3, 2))


def test_effective_sample_size():
    assert effective_sample_size(torch.ones(10)).item() == pytest.approx(10.0)
    assert effective_sample_size(torch.tensor([1.0, 0.0, 0.0])).item() == pytest.approx(1.0)


def test_flattened_weights_keep_zeros_and_skip_the_power_at_one():
    from torch_api.core.weights import flatten_weights

    w = torch.tensor([[0.0, 0.25, 4.0], [1.0, 9.0, 0.0]], dtype=torch.float64)
    assert flatten_weights(w, 1.0) is w  # ν = 1: the paper's weights, no power computed
    assert flatten_weights(w, 0.0).tolist() == [[0.0, 1.0, 1.0], [1.0, 1.0, 0.0]]
    per_trial = flatten_weights(w, torch.tensor([[0.5], [1.0]], dtype=torch.float64))
    assert per_trial.tolist() == [[0.0, 0.5, 2.0], [1.0, 9.0, 0.0]]
    with pytest.raises(ValueError, match="must lie in \\[0, 1\\]"):
        flatten_weights(w, 1.5)

"""Layer 2, the paper's maths: pure functions on tensors, with shapes and equation numbers.

===================================== =====================================================
:mod:`torch_api.core.basis`           phi(s, a), Gaussian kernels × actions (eq. 9-10, 50, 64)
:mod:`torch_api.core.quadratic_basis` phi(s, a) = e_a ⊗ [1, s, s_i s_j]: a quadratic Q̂ per action
:mod:`torch_api.core.weights`         per-decision importance weights, ESS, ``w^ν`` (eq. 21)
:mod:`torch_api.core.psi`             psi_hat: grouped, single-sample, k-NN (eq. 14, 20)
:mod:`torch_api.core.design`          episodes → psi_hat rows, weights, rewards (eq. 19-20)
:mod:`torch_api.core.grouped_design`  the same per (s, a) group on finite states (eq. 20, 42-45)
:mod:`torch_api.core.solve`           weighted ridge, J of moments and of rows (eq. 22-28, 40-46)
:mod:`torch_api.core.criterion`       pooled moments of each candidate, J of eq. 46 (eq. 42-46)
:mod:`torch_api.core.lstd`            LSTD-Q and its reward-free error estimate (beyond the paper)
:mod:`torch_api.core.iwcv`            ν of the flattened weights by IWCV (beyond the paper)
:mod:`torch_api.core.fit`             step 3 of Algorithm 1: θ_l on all rewarded episodes (eq. 56)
:mod:`torch_api.core.improvement`     Q̂ → greedy, ε-greedy, softmax (eq. 7-8, 57-58)
===================================== =====================================================

It reads episodes in the format of :mod:`torch_api.data` and imports nothing else above it.
"""

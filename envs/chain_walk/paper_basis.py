"""The paper's basis for the chain-walk experiments (eq. 50): the algorithm's side, not the env's.

Gaussian centres on the state numbers and their width; the experiments build their
:class:`torch_api.core.basis.GaussianActionBasis` from them. The env itself knows no basis.
"""

__all__ = ["CENTERS", "TAU"]

CENTERS = (1.0, 3.0, 5.0, 7.0, 9.0)  # Gaussian basis centres of eq. 50 (state numbers)
TAU = 1.5  # Gaussian basis width of eq. 50 (state numbers)

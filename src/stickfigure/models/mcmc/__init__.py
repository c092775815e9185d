"""Method "mcmc": stick-figure posteriors under a nonparametric Bayesian tree prior.

Meeds, Ross, Zemel & Roweis, "Learning stick-figure models using nonparametric
Bayesian priors over trees" (CVPR 2008). The pieces follow NumPyro's split:

* :mod:`.prior`   -- the tree prior: sampling, exact log-probability, enumeration.
* :mod:`.model`   -- the stick-node data model: eq. 13 and the node base densities.
* :mod:`.state`   -- the chain's state and the log-joint.
* :mod:`.kernels` -- one function per Markov kernel (Gibbs indicators, split-merge,
  tree moves, translations, rotations, precisions, lambda, imputation).
* :mod:`.sampler` -- chains in parallel processes, burn-in, thinning.
* :mod:`.data`    -- normalisation of the data to the priors' scale, starting states.
* :mod:`.diagnostics` -- ArviZ R-hat / ESS and posterior summaries.
* :mod:`.estimator` -- the registered estimator :class:`StickMCMC`.

See docs/mcmc.md for the derivations and how to read the diagnostics.
"""

from .estimator import StickMCMC

__all__ = ["StickMCMC"]

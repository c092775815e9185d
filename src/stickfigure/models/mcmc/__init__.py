"""Method "mcmc" (work in progress)."""

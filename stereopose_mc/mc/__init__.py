"""Monte Carlo: chunks of trials stepping through time together, and the engine."""

"""Scoring policies: batched rollouts on held-out reset seeds, and the statistics
(Wilson intervals per arm, Newcombe's interval for a difference)."""

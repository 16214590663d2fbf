"""The online learner node of the HIL-SERL stage (logic in offline_rl_core.nodes.learner_service)."""

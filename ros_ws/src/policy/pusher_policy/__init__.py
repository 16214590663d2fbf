"""The policy node of pusher-rl (see node.py)."""

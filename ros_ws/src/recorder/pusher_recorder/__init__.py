"""The recorder node of pusher-rl (see node.py)."""

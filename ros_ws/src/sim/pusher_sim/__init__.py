"""The sim node of pusher-rl (see node.py)."""

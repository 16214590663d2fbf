"""The trainer node of pusher-rl (see node.py)."""

"""One module per `offline-rl` subcommand; each exposes ``register(subparsers)``."""

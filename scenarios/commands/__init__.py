"""One module per `aimbench` subcommand; each defines ``register(subparsers)``.

`scenarios.cli` discovers the modules here, so adding a command means adding a module.
"""

"""Sub-commands of ``lightflow``: each module defines ``register(subparsers)``.

``register`` adds one sub-parser (or a group) and sets ``func`` to a function
taking the parsed ``argparse.Namespace`` and returning an exit status.
Modules are discovered automatically, in alphabetical order.
"""

"""The sub-commands of `hil` that are experiments or analyses (compare, sweep, can-analysis): argument parsers and
their handlers; `hil/cli.py` assembles them."""

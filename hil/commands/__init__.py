"""The sub-commands of `hil` besides run and scenarios (compare, sweep, can-analysis, fmu, silkit, recover): argument
parsers and their handlers; `hil/cli.py` assembles them."""

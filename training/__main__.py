"""``python -m training`` is ``python -m training.tune``."""

import argparse

from training.tune import add_arguments, main

parser = argparse.ArgumentParser(prog="python -m training", description="tune a filter")
add_arguments(parser)
raise SystemExit(main(parser.parse_args()))

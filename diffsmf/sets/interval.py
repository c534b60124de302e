"""The box family, ``Interval``: the interval engine's value type (`diffsmf.interval.box`),
re-exported here beside the other set families."""

from diffsmf.interval.box import Interval, interval_eval

__all__ = ["Interval", "interval_eval"]

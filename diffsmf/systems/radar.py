"""Seed 003 radar tracking system (registered as ``"radar"``)."""

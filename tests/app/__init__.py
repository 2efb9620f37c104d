"""Tests of the command line, the demo and the worker pools (haptic_collab/*.py)."""

"""Tests of the research drivers (haptic_collab/research): the paper figures, the fidelity models."""

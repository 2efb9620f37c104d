"""Tests of the benchmarks (haptic_collab/bench): their contracts, not their timings."""

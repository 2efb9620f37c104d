"""Tests of the repository tools (tools/): the generated files."""

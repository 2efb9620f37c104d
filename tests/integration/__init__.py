"""Tests across processes and packages: server and clients over loopback, the wheel, the wire."""

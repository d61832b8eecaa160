"""Deployment over zenoh: wire protocol, policy bridge, simulated robot, benchmark.

See docs/deploy.md.
"""

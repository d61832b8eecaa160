"""Deployment over zenoh: wire protocol, policy bridge, simulated robot, the Go2 adapter
(Unitree SDK) and a fake Go2, benchmark.

See docs/deploy.md.
"""

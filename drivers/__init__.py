"""Device I/O: bytes on the wire ↔ typed, timestamped samples (DESIGN.md §2, §7).

Drivers never import estimators; each device kind has one interface with a real and a
mock implementation (``drivers.mock``) speaking the same wire format.
"""

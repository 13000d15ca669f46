"""Simulated hardware that speaks the real wire formats (pty serial, python-can, camera API)."""

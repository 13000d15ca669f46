"""The hardware-in-the-loop bench: mock devices on real transports + the real daemon."""

from mowerhw.bench.hil import FAULT_KINDS, Bench, FaultSpec, run_bench

__all__ = ["FAULT_KINDS", "Bench", "FaultSpec", "run_bench"]

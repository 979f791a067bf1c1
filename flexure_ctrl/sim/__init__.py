"""Simulated rig: stands in for the hardware behind the same protocols (CAN, tracker TCP)."""

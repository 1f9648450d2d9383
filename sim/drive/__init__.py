"""Simulated servo drive: one CiA 402 model (:mod:`sim.drive.model`) behind CANopen and Modbus front ends."""

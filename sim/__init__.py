"""Simulated rig: device servers speaking the real wire protocols, and the ray-cast scene."""

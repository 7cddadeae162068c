"""Devices behind small interfaces: cameras, USB discovery, the simulated rig."""

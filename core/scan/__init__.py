"""Scanning: patterns shown, frames captured, decoded to projector coordinates, triangulated to a cloud."""

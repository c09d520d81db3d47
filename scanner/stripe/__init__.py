"""Laser stripe extraction: sub-pixel profiles from frames."""

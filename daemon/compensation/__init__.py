"""Compensation write-back: proposals from a stored run, applying and rolling back, its journal."""

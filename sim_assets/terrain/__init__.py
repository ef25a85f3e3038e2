"""Packaged world-relief asset for the terrain demonstration (see PROVENANCE.md)."""

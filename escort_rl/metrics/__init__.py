"""Distances between particle sets and to a reference posterior."""

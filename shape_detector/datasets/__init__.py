"""Loaders for public RGB-D dataset formats."""

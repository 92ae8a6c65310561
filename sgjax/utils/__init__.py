"""Plumbing shared by every layer: atomic file output (`files`) and the cache directory (`cache`).

The bottom layer of sgjax: imports nothing else of the project.
"""
